"""meta.json's ``git_commit`` is the commit of the package's own source tree, whatever the caller's directory."""

from __future__ import annotations

import os
import shutil
import subprocess

import pytest

from rebel_jax.run import cli_rundir


def _git(*args, cwd) -> str:
    env = {**os.environ, "GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t"}
    env["GIT_COMMITTER_EMAIL"] = "t@t"
    return subprocess.run(["git", *args], cwd=cwd, env=env, capture_output=True, text=True, check=True).stdout.strip()


@pytest.fixture(autouse=True)
def _no_override(monkeypatch):
    monkeypatch.delenv("REBEL_JAX_GIT_COMMIT", raising=False)


def test_the_commit_is_the_package_repository_s_not_the_working_directory_s(tmp_path, monkeypatch):
    """Run from another repository, the commit is still the one ``git -C <package dir>`` names."""
    other = tmp_path / "other"
    other.mkdir()
    _git("init", "-q", cwd=other)
    _git("commit", "-q", "--allow-empty", "-m", "x", cwd=other)
    monkeypatch.chdir(other)
    expected = subprocess.run(
        ["git", "-C", str(cli_rundir.PACKAGE_DIR), "rev-parse", "HEAD"], capture_output=True, text=True
    )
    got = cli_rundir._git_commit()
    assert got != _git("rev-parse", "HEAD", cwd=other)
    if expected.returncode == 0:
        assert got == expected.stdout.strip()


def test_a_package_outside_any_repository_records_its_installed_version(tmp_path):
    """A copy of the package in a plain directory inside another repository (as a venv's site-packages would be):
    not that repository's commit, the installed version instead."""
    repo = tmp_path / "repo"
    repo.mkdir()
    _git("init", "-q", cwd=repo)
    _git("commit", "-q", "--allow-empty", "-m", "x", cwd=repo)
    package = repo / "site-packages" / "rebel_jax"
    package.mkdir(parents=True)
    shutil.copy(cli_rundir.PACKAGE_DIR / "__init__.py", package / "__init__.py")
    got = cli_rundir._git_commit(package)
    assert got != _git("rev-parse", "HEAD", cwd=repo)
    assert got is None or got.startswith("installed ")
