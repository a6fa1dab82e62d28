"""``benchmarks/determinism.py``: two runs of one program from the same keys, compared bit for bit.

On the CPU a repeat is the same run, so the benchmark must say "identical"; a one-ulp change to one state leaf
must be found. (On the GPU it measures whether the runs are reproducible; RESULTS.md.)
"""

from __future__ import annotations

import json
import sys

import jax
import numpy as np
import pytest

# The sac flags of test_cli_runs.MICRO_FLAGS (its compiled round, shared through the compilation cache).
FLAGS = (
    "--preset tiny --algo sac --task probe_point --num-envs 2 --episode-length 20 --sac.hidden 16 --sac.batch-size 16"
    " --sac.utd 0.5 --total-steps 120 --seed-steps 20 --steps-per-round 40 --eval-every 40 --eval-episodes 1"
    " --seeds 2 --seed 7"
).split()


@pytest.fixture
def determinism(benchmark_script):
    return benchmark_script("determinism")


def test_a_repeat_on_the_cpu_is_identical_and_the_row_says_so(determinism, tmp_path, monkeypatch):
    out = tmp_path / "determinism.json"
    monkeypatch.setattr(sys, "argv", ["determinism.py", "--rounds", "2", "--out", str(out), "--", *FLAGS])
    determinism.main()
    (row,) = json.loads(out.read_text())["rows"]
    assert row["identical"] and row["metrics_equal"] and row["differing_leaves"] == 0 and row["leaves"] > 10
    assert row["max_abs_difference"] == 0.0 and row["device"] == "cpu" and row["flags"] == " ".join(FLAGS)
    assert [len(times) for times in row["round_seconds"]] == [2, 2]


def test_compare_finds_a_one_ulp_difference_and_key_leaves(determinism):
    state = {"w": np.linspace(0.0, 1.0, 5, dtype=np.float32), "key": jax.random.key(0), "step": np.arange(3)}
    assert determinism.compare(state, state) == {"leaves": 3, "differing_leaves": 0, "max_abs_difference": 0.0}
    moved = dict(state, w=state["w"].copy())
    moved["w"][2] = np.nextafter(moved["w"][2], np.float32(1.0))
    out = determinism.compare(state, moved)
    assert out["differing_leaves"] == 1
    assert out["max_abs_difference"] == pytest.approx(float(np.spacing(np.float32(0.5))))
    other_key = dict(state, key=jax.random.key(1))
    assert determinism.compare(state, other_key)["differing_leaves"] == 1
    nan = dict(state, w=np.full(5, np.nan, np.float32))
    assert determinism.compare(nan, nan)["differing_leaves"] == 0  # NaN where the other has NaN
    assert determinism.metrics_equal([{"a": np.array([np.nan, 1.0])}], [{"a": np.array([np.nan, 1.0])}])
    assert not determinism.metrics_equal([{"a": np.array([0.0])}], [{"a": np.array([1e-9])}])
