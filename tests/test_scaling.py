"""``benchmarks/scaling.py``: the efficiency read from two runs' logs, against the formula by hand."""

from __future__ import annotations

import json
import pathlib

import pytest


@pytest.fixture
def scaling(benchmark_script):
    return benchmark_script("scaling")


@pytest.fixture
def differences(benchmark_script):
    return benchmark_script("run_differences")


def _run(path: pathlib.Path, devices: int, columns: int, seconds: list[float]) -> pathlib.Path:
    path.mkdir()
    meta = {"devices": ["GPU"] * devices, "columns": columns, "jax": "0.11.2", "git_commit": "abc", "command": "x"}
    (path / "meta.json").write_text(json.dumps({**meta, "started": "2026-11-27T00:00:00"}))
    rows = [{"round": r, "seconds": s} for r, s in enumerate(seconds)]
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_efficiency_is_the_rate_ratio_over_the_device_count(scaling, tmp_path, capsys):
    multi = _run(tmp_path / "two", 2, 10, [90.0, 21.0, 20.0, 23.0])
    one = _run(tmp_path / "one", 1, 5, [80.0, 19.0, 20.5, 20.0])
    scaling.main([str(multi), str(one)])
    out = capsys.readouterr().out
    expected = (10 / 21.0) / (2 * 5 / 20.0)  # medians of rounds 1-3: 21.0 and 20.0
    assert f"**{expected:.3f}**" in out, out
    assert "21.00, 20.00, 23.00" in out and "90.00" not in out  # round 0 (the compile) is left out


def test_a_run_without_timed_rounds_is_refused(scaling, tmp_path):
    only_compile = _run(tmp_path / "two", 2, 10, [90.0])
    with pytest.raises(SystemExit, match="no round from round 1"):
        scaling.run_rate(only_compile)


def _metrics(path: pathlib.Path, rows: list[dict]) -> pathlib.Path:
    path.mkdir()
    (path / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def test_run_differences_are_the_largest_relative_gap_over_the_seeds(differences, tmp_path, capsys):
    a = _metrics(tmp_path / "a", [{"round": 0, "eval_return": [10.0, 20.0]}, {"round": 1, "eval_return": [3.0, 4.0]}])
    b = _metrics(tmp_path / "b", [{"round": 0, "eval_return": [10.0, 25.0]}, {"round": 2, "eval_return": [1.0, 1.0]}])
    differences.main([str(a), str(b), "--keys", "eval_return", "q"])
    out = capsys.readouterr().out
    gaps = [abs(10.0 - 10.0) / 10.0, abs(20.0 - 25.0) / 25.0]  # by hand: round 0 only (round 1, 2 not in both)
    assert f"| 0 | {max(gaps):.3f} | - |" in out, out
    assert "| 1 |" not in out and "| 2 |" not in out


def test_run_differences_refuse_different_seed_counts(differences, tmp_path):
    a = _metrics(tmp_path / "a", [{"round": 0, "q": [1.0, 2.0]}])
    b = _metrics(tmp_path / "b", [{"round": 0, "q": [1.0]}])
    with pytest.raises(SystemExit, match="different seed counts"):
        differences.table(a, b, ["q"])


def test_runs_per_gpu_hour_project_the_first_round_and_the_median_of_the_rest(benchmark_script, tmp_path, capsys):
    runs_per_hour = benchmark_script("runs_per_hour")
    run = _run(tmp_path / "two", 2, 20, [100.0, 30.0, 26.0, 27.0])
    (run / "config.json").write_text(json.dumps({"train": {"steps_per_round": 10_000}}))
    runs_per_hour.main([str(run), "--total-steps", "45000"])
    out = capsys.readouterr().out
    job = 100.0 + 4 * 27.0  # 5 rounds of 10k (the last one partial): the first, then 4 at the median of 30, 26, 27
    assert f"| {job:,.0f} | {20 * 3600 / (2 * job):.1f} |" in out, out
    with pytest.raises(SystemExit, match="--total-steps must be >= 1"):
        runs_per_hour.main([str(run), "--total-steps", "0"])


@pytest.fixture
def learning_check(benchmark_script):
    return benchmark_script("learning_check")


def test_learning_check_is_the_difference_of_seed_means_and_its_standard_error(learning_check, tmp_path, capsys):
    rows_a = [{"env_steps": 50, "eval_return": [1.0, 3.0, 8.0]}, {"env_steps": 100, "eval_return": [2.0, 4.0, 9.0]}]
    rows_b = [{"env_steps": 50, "eval_return": [4.0, 4.0]}, {"env_steps": 75, "eval_return": [0.0, 1.0]}]
    a = _metrics(tmp_path / "a", [{"round": i, **r} for i, r in enumerate(rows_a)])
    b = _metrics(tmp_path / "b", [{"round": i, **r} for i, r in enumerate(rows_b)])
    learning_check.main([str(a), str(b), "--every", "25"])
    out = capsys.readouterr().out
    # By hand at step 50: A's mean 4, sample variance ((-3)^2 + (-1)^2 + 4^2) / 2 = 13; B's mean 4, variance 0.
    assert f"| 50 | 4.0 +- {13**0.5:.1f} | 4.0 +- 0.0 | +0.0 | {(13 / 3) ** 0.5:.1f} |" in out, out
    assert "| 75 |" not in out and "| 100 |" not in out  # only steps both runs logged


def test_learning_check_refuses_runs_without_a_shared_step(learning_check, tmp_path):
    a = _metrics(tmp_path / "a", [{"round": 0, "env_steps": 10, "eval_return": [1.0, 2.0]}])
    b = _metrics(tmp_path / "b", [{"round": 0, "env_steps": 20, "eval_return": [1.0, 2.0]}])
    with pytest.raises(SystemExit, match="share no logged step"):
        learning_check.table(a, b, every=10)
