"""The persistent compilation cache of ``python -m rebel_jax.train`` (:mod:`rebel_jax.run.compile_cache`).

Whole runs in subprocesses (a fresh JAX each, as a user's second command is), each with its own cache directory
under ``tmp_path``: a first run fills the directory, a second identical one loads every program from it (JAX logs
each hit) and adds nothing, with the same metrics bit for bit as a run that compiled everything itself.
"""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys

import pytest
from test_cli_runs import MICRO_FLAGS, ROOT, _metrics

from rebel_jax.core.errors import ConfigError
from rebel_jax.run import cli, compile_cache, video

JAX_CACHE_VARIABLES = (
    "JAX_COMPILATION_CACHE_DIR",
    "JAX_ENABLE_COMPILATION_CACHE",
    compile_cache.MIN_COMPILE_TIME[1],
    compile_cache.MIN_ENTRY_SIZE[1],
    compile_cache.ENV_DIR,
    "XDG_CACHE_HOME",
)
HIT = "Persistent compilation cache hit for"
"""What JAX logs (at warning level under ``JAX_LOG_COMPILES=1``) for each program loaded from the cache."""


def _user_env(**extra: str) -> dict[str, str]:
    """This process's environment without any cache setting (a user who set none), and ``extra``."""
    env = {k: v for k, v in os.environ.items() if k not in JAX_CACHE_VARIABLES}
    return {**env, "PYTHONPATH": str(ROOT / "src"), "JAX_LOG_COMPILES": "1", **extra}


def _train(run_dir: pathlib.Path, env: dict[str, str], *flags: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "rebel_jax.train", *MICRO_FLAGS, "--video-steps", "0", "--run-dir", str(run_dir)]
    out = subprocess.run([*cmd, *flags], cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def _entries(directory: pathlib.Path) -> set[str]:
    """The files under a cache directory (relative paths); empty where it does not exist."""
    return {str(p.relative_to(directory)) for p in directory.rglob("*") if p.is_file()}


def _meta_cache(run_dir: pathlib.Path) -> str | None:
    return json.loads((run_dir / "meta.json").read_text())["compile_cache"]


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """A run in a fresh cache directory given by ``REBEL_JAX_CACHE_DIR``: (run dir, cache dir, its entries)."""
    root = tmp_path_factory.mktemp("compile_cache")
    cache, run_dir = root / "cache", root / "first"
    _train(run_dir, _user_env(REBEL_JAX_CACHE_DIR=str(cache)))
    return run_dir, cache, _entries(cache)


def test_a_first_run_fills_the_cache_directory_and_records_it(first_run):
    run_dir, cache, entries = first_run
    assert entries, "no cache entries written"
    assert _meta_cache(run_dir) == str(cache)


def test_a_second_identical_run_loads_its_programs_from_the_cache(first_run, tmp_path):
    run_dir, cache, entries = first_run
    out = _train(tmp_path / "second", _user_env(REBEL_JAX_CACHE_DIR=str(cache)))
    hits = [line for line in out.stderr.splitlines() if HIT in line]
    assert hits, out.stderr[-3000:]
    assert _entries(cache) == entries  # every program it compiled was there already
    assert _metrics(tmp_path / "second") == _metrics(run_dir)


def test_no_compile_cache_writes_nothing_and_computes_the_same(first_run, tmp_path):
    run_dir, _, _ = first_run
    cache = tmp_path / "cache"
    out = _train(tmp_path / "run", _user_env(REBEL_JAX_CACHE_DIR=str(cache)), "--no-compile-cache")
    assert not cache.exists() and HIT not in out.stderr
    assert _meta_cache(tmp_path / "run") is None
    assert _metrics(tmp_path / "run") == _metrics(run_dir)  # compiled here: the cached programs compute the same


# make test-heavy: two more runs through the command line (about 20 s each on 2 cores); make test checks the same
# order of choice without running anything (test_choose_orders_the_flags_then_jax_then_the_default).
@pytest.mark.heavy
def test_a_users_jax_compilation_cache_dir_wins_over_the_default(tmp_path):
    ours, theirs = tmp_path / "ours", tmp_path / "theirs"
    env = _user_env(REBEL_JAX_CACHE_DIR=str(ours), JAX_COMPILATION_CACHE_DIR=str(theirs))
    env[compile_cache.MIN_COMPILE_TIME[1]] = "0"  # the user's own setting: JAX's 1 s would skip these small programs
    _train(tmp_path / "run", env)
    assert _entries(theirs) and not ours.exists()
    assert _meta_cache(tmp_path / "run") == str(theirs)


@pytest.mark.heavy  # as the test above
def test_compile_cache_flag_moves_the_cache_over_the_users_variables(tmp_path):
    flag, theirs = tmp_path / "flag", tmp_path / "theirs"
    env = _user_env(REBEL_JAX_CACHE_DIR=str(theirs), JAX_COMPILATION_CACHE_DIR=str(theirs))
    _train(tmp_path / "run", env, "--compile-cache", str(flag))
    assert _entries(flag) and not theirs.exists()
    assert _meta_cache(tmp_path / "run") == str(flag)


# -- the choice, without running anything ---------------------------------------------------------------------------
@pytest.mark.parametrize(
    "environ, expected",
    [
        ({"REBEL_JAX_CACHE_DIR": "/a/b", "XDG_CACHE_HOME": "/x"}, pathlib.Path("/a/b")),
        ({"XDG_CACHE_HOME": "/x"}, pathlib.Path("/x/rebel_jax/jax")),
        ({"XDG_CACHE_HOME": "relative"}, pathlib.Path.home() / ".cache/rebel_jax/jax"),
        ({"REBEL_JAX_CACHE_DIR": " ", "XDG_CACHE_HOME": ""}, pathlib.Path.home() / ".cache/rebel_jax/jax"),
        ({}, pathlib.Path.home() / ".cache/rebel_jax/jax"),
    ],
)
def test_default_dir_follows_rebel_jax_then_xdg_then_home(environ, expected):
    assert compile_cache.default_dir(environ) == expected


def test_choose_orders_the_flags_then_jax_then_the_default():
    env = {"REBEL_JAX_CACHE_DIR": "/ours"}
    assert compile_cache.choose(None, True, "/theirs", True, env).directory is None
    assert compile_cache.choose("/flag", False, "/theirs", False, env).directory == "/flag"
    assert compile_cache.choose(None, False, "/theirs", True, env) == compile_cache.CacheChoice(
        "/theirs", "JAX_COMPILATION_CACHE_DIR", ours=False
    )
    assert compile_cache.choose(None, False, None, False, env).directory is None  # JAX's own switch, off
    assert compile_cache.choose(None, False, None, True, env) == compile_cache.CacheChoice(
        "/ours", "REBEL_JAX_CACHE_DIR", ours=True
    )


@pytest.mark.parametrize("flags", [("--compile-cache", "x", "--no-compile-cache"), ("--compile-cache", " ")])
def test_bad_compile_cache_flags_are_one_line_errors(flags, tmp_path, capsys):
    with pytest.raises(ConfigError):
        compile_cache.choose(flags[1], "--no-compile-cache" in flags, None, True, {})
    for main, argv in ((cli.main, [*MICRO_FLAGS, "--run-dir", str(tmp_path / "run")]), (video.main, [str(tmp_path)])):
        with pytest.raises(SystemExit) as exit_:
            main([*argv, *flags])
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and err.startswith("error: compile_cache=") and err.count("\n") == 1, err
    assert not (tmp_path / "run").exists()


def test_an_unwritable_compile_cache_dir_is_refused(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("")
    choice = compile_cache.choose(str(blocker / "cache"), False, None, True, {})
    with pytest.raises(ConfigError, match="allowed a writable directory"):
        compile_cache.apply(choice)


@pytest.fixture
def jax_updates(monkeypatch):
    """The ``jax.config.update`` calls of :func:`compile_cache.apply`, recorded instead of made (and no cache reset)."""
    from jax.experimental.compilation_cache import compilation_cache

    calls: dict[str, object] = {}
    monkeypatch.setattr(compile_cache.jax.config, "update", lambda name, value: calls.__setitem__(name, value))
    monkeypatch.setattr(compilation_cache, "reset_cache", lambda: None)
    return calls


def test_apply_caches_every_program_unless_the_environment_says_otherwise(jax_updates, tmp_path):
    choice = compile_cache.choose(None, False, None, True, {compile_cache.ENV_DIR: str(tmp_path / "c")})
    environ = {compile_cache.MIN_ENTRY_SIZE[1]: "100"}  # the user's own: kept
    assert compile_cache.apply(choice, environ) == choice
    assert jax_updates == {
        "jax_enable_compilation_cache": True,
        "jax_compilation_cache_dir": str(tmp_path / "c"),
        compile_cache.MIN_COMPILE_TIME[0]: compile_cache.MIN_COMPILE_TIME[2],
    }


def test_apply_leaves_a_users_jax_settings_alone(jax_updates):
    choice = compile_cache.choose(None, False, "/theirs", True, {})
    assert compile_cache.apply(choice, {}) == choice and jax_updates == {}


def test_an_unwritable_default_dir_runs_without_the_cache_with_a_warning(jax_updates, tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("")
    choice = compile_cache.choose(None, False, None, True, {compile_cache.ENV_DIR: str(blocker / "cache")})
    assert compile_cache.apply(choice, {}).directory is None
    assert jax_updates == {"jax_enable_compilation_cache": False}
    err = capsys.readouterr().err
    assert err.startswith("warning: the compilation cache directory") and err.count("\n") == 1, err
