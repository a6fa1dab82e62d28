"""experiments/collect.py: a device call's finished runs copied into results/runs/<group>/, nothing overwritten."""

from __future__ import annotations

import json
import pathlib
import subprocess
import sys
import tarfile

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "experiments"))

import collect  # noqa: E402


def _run(runs: pathlib.Path, name: str, finished: bool = True, log_inside: bool = False) -> None:
    """A run directory as the device script leaves it (its stdout beside it, or inside as gpu_batch.py writes it)."""
    run_dir = runs / name
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps({"algo": name}))
    (run_dir / "meta.json").write_text(json.dumps({"command": f"python -m rebel_jax.train --run-dir runs/{name}"}))
    rows = [{"round": 0, "env_steps": 40, "eval_return": [1.0, 3.0]}, {"round": 1, "env_steps": 80}]
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    (run_dir / "learning_curve.png").write_bytes(b"\x89PNG " + name.encode())
    (run_dir / "stdout.log" if log_inside else runs / f"{name}.log").write_text(f"{name} printed this\n")
    if finished:
        (run_dir / "final.json").write_text(json.dumps({"status": "completed"}))


def _archive(runs: pathlib.Path, path: pathlib.Path) -> pathlib.Path:
    with tarfile.open(path, "w:gz") as archive:
        archive.add(runs, arcname="runs")
    return path


def _main(*argv) -> subprocess.CompletedProcess:
    script = pathlib.Path(collect.__file__)
    command = [sys.executable, script.name, *map(str, argv)]
    return subprocess.run(command, cwd=script.parent, capture_output=True, text=True, check=False)


def test_finished_runs_are_copied_from_an_archive_with_their_logs_and_unfinished_ones_listed(tmp_path):
    runs = tmp_path / "device" / "runs"
    _run(runs, "pebble_a")
    _run(runs, "surf_b", log_inside=True)
    _run(runs, "rebel_c", finished=False)
    archive = _archive(runs, tmp_path / "runs.tar.gz")
    results = tmp_path / "results"
    done = _main(archive, "pixels", "--results", results)
    assert done.returncode == 0, done.stderr
    assert sorted(p.name for p in (results / "pixels").iterdir()) == ["pebble_a", "surf_b"]
    for name in ("pebble_a", "surf_b"):
        copied = results / "pixels" / name
        expected = {*collect.FILES, "stdout.log"}
        assert {p.name for p in copied.iterdir()} == expected
        for file in expected - {"stdout.log"}:
            assert (copied / file).read_bytes() == (runs / name / file).read_bytes()
        assert (copied / "stdout.log").read_text() == f"{name} printed this\n"
    lines = {line.split()[0]: line for line in done.stdout.splitlines()[1:]}
    assert "copied" in lines["pebble_a"] and "unfinished (not copied)" in lines["rebel_c"]
    assert lines["pebble_a"].split()[-2:] == ["80", "2.0"]  # env steps, the last evaluation's mean


def test_nothing_is_overwritten_and_a_clash_copies_nothing(tmp_path):
    runs = tmp_path / "runs"
    _run(runs, "pebble_a")
    results = tmp_path / "results"
    assert _main(runs, "g", "--results", results).returncode == 0
    (results / "g" / "pebble_a" / "learning_curve.png").write_bytes(b"drawn again")  # a figure is not a clash
    again = _main(runs, "g", "--results", results)
    assert again.returncode == 0 and "already collected" in again.stdout
    assert (results / "g" / "pebble_a" / "learning_curve.png").read_bytes() == b"drawn again"

    _run(runs, "surf_b")
    (results / "g" / "pebble_a" / "metrics.jsonl").write_text("{}\n")
    (results / "g" / "pebble_a" / "stdout.log").unlink()
    clash = _main(runs, "g", "--results", results)
    assert clash.returncode == 2
    assert "pebble_a: metrics.jsonl, stdout.log" in clash.stderr and "nothing was copied" in clash.stderr
    assert not (results / "g" / "surf_b").exists()
    assert (results / "g" / "pebble_a" / "metrics.jsonl").read_text() == "{}\n"

    only = _main(runs, "g", "--results", results, "--only", "surf_b")
    assert only.returncode == 0 and (results / "g" / "surf_b" / "final.json").is_file()


def test_bad_sources_and_names_are_refused(tmp_path):
    runs = tmp_path / "runs"
    _run(runs, "pebble_a")
    missing = _main(runs, "g", "--results", tmp_path / "r", "--only", "pebble_a", "sac_z")
    assert missing.returncode == 2 and "no run sac_z in" in missing.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    assert "no run at all in" in _main(empty, "g", "--results", tmp_path / "r").stderr
    absent = _main(tmp_path / "absent.tar.gz", "g")
    assert absent.returncode == 2 and "does not exist" in absent.stderr
    cut = tmp_path / "cut.tar.gz"
    cut.write_bytes(_archive(runs, tmp_path / "whole.tar.gz").read_bytes()[:100])  # a download cut short
    refused = _main(cut, "g", "--results", tmp_path / "r")
    assert refused.returncode == 2 and "is no readable archive" in refused.stderr, refused.stderr
    assert not (tmp_path / "r").exists()
