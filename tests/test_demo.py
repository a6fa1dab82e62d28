"""``make train``: the demo run learns, measured against the random policy of the same run.

The command is the one ``make train`` runs, read from ``make -n train`` (with this interpreter
and a temporary ``--run-dir``), and it runs in a subprocess, as the CLI tests do. The random
policy's return is measured by that run on the same evaluation episodes as the trained policy
(``Trainer.evaluate(..., random_actions=True)``), so nothing here is a hard-coded return.
"""

from __future__ import annotations

import json
import os
import pathlib
import shlex
import shutil
import subprocess
import sys

import jax
import matplotlib.image
import numpy as np
import pytest

from rebel_jax.cli import parse

ROOT = pathlib.Path(__file__).parents[1]


def make_train_command(run_dir: pathlib.Path) -> list[str]:
    """The command of ``make train ARGS="--run-dir RUN_DIR --no-progress"``, with this interpreter."""
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    args = f"ARGS=--run-dir {run_dir} --no-progress"
    out = subprocess.run(
        ["make", "-n", "-s", "train", f"PY={sys.executable}", args], cwd=ROOT, capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr
    lines = [line for line in out.stdout.splitlines() if " -m rebel_jax.train " in line]
    assert len(lines) == 1, out.stdout
    return shlex.split(lines[0])


def test_make_train_runs_the_demo_preset_on_three_seeds(tmp_path):
    cmd = make_train_command(tmp_path / "run")
    assert cmd[:3] == [sys.executable, "-m", "rebel_jax.train"]
    args = parse(cmd[3:])
    cfg = args.config
    assert args.seeds == 3 and cfg.preference and cfg.teacher.beta == float("inf")  # the oracle
    assert cfg.env.task in ("walker_stand", "walker_walk", "walker_run", "cheetah_run")  # not the probe


def _table_row(stdout: str, name: str) -> list[str]:
    """The cells of the summary table's row ``name`` (``seed 0``, ``mean``)."""
    rows = [line for line in stdout.splitlines() if line.startswith(name + "  ")]
    assert len(rows) == 1, stdout[-3000:]
    return rows[0][len(name) :].split()


@pytest.mark.slow
def test_make_train_learns_well_above_the_random_policy(tmp_path):
    run_dir = tmp_path / "run"
    cmd = make_train_command(run_dir)
    env = dict(
        os.environ,
        PYTHONPATH=str(ROOT / "src"),
        JAX_COMPILATION_CACHE_DIR=str(jax.config.jax_compilation_cache_dir),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=str(jax.config.jax_persistent_cache_min_compile_time_secs),
    )
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1200)
    assert out.returncode == 0, out.stderr[-3000:]

    final = json.loads((run_dir / "final.json").read_text())
    trained, random = np.asarray(final["final_eval_return"]), np.asarray(final["random_return"])
    assert final["status"] == "completed" and trained.shape == random.shape == (3,)
    # The bar: the mean over the seeds at least 5x the random policy's, or 100 points above it;
    # and every seed above the random policy on the same episodes.
    assert trained.mean() >= 5 * random.mean() or trained.mean() >= random.mean() + 100, (trained, random)
    assert np.all(trained > random), (trained, random)

    # The table printed last holds these numbers, the labels used and the learned reward's correlation.
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    labels = records[-1]["labels_used"]
    sessions = [r for r in records if r.get("session_mean") == 1.0]
    correlation = np.asarray(sessions[-1]["reward_correlation"])
    assert correlation.mean() > 0, correlation  # the learned reward follows the true one
    for i in range(3):
        row = _table_row(out.stdout, f"seed {i}")
        assert row[:4] == [f"{random[i]:.1f}", f"{trained[i]:.1f}", f"{labels[i]:.0f}", f"{correlation[i]:.2f}"]
    mean = _table_row(out.stdout, "mean")
    assert mean[:2] == [f"{random.mean():.1f}", f"{trained.mean():.1f}"]

    # The learning curve and the evaluation clip, whose paths are printed.
    for name in ("learning_curve.png", "eval.gif"):
        assert f"wrote {run_dir / name}" in out.stdout.splitlines()
    image = matplotlib.image.imread(run_dir / "learning_curve.png")
    assert image.ndim == 3 and image.shape[0] > 100 and image.std() > 0
    import imageio.v3 as iio

    frames = iio.imread(run_dir / "eval.gif")
    assert frames.shape[0] == parse(cmd[3:]).video_steps + 1
