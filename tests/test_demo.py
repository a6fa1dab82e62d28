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

from rebel_jax.config import Config, EnvConfig, SACConfig, TrainConfig
from rebel_jax.run.cli import _final_evaluation, last_logged, parse, summary_table
from rebel_jax.train import Trainer, compiled

ROOT = pathlib.Path(__file__).parents[1]


def make_train_command(run_dir: pathlib.Path) -> list[str]:
    """The command of ``make train ARGS="--run-dir RUN_DIR --no-progress"``, with this interpreter."""
    if shutil.which("make") is None:
        pytest.skip("make is not installed")
    args = f"ARGS=--run-dir {run_dir} --no-progress"
    env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MFLAGS", "MAKELEVEL")}  # under `make test`
    cmd = ["make", "-n", "-s", "train", f"PY={sys.executable}", args]
    out = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True)
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
@pytest.mark.heavy
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


# The probe task (compiles in seconds): 3 evaluation episodes of 15 steps.
PROBE = Config(
    env=EnvConfig(task="probe_point", num_envs=1, episode_length=15),
    sac=SACConfig(hidden=16, batch_size=16),
    train=TrainConfig(total_steps=15, steps_per_round=15, eval_every=15, eval_episodes=3),
)


def _loop_return(trainer: Trainer, params, key: jax.Array, random_actions: bool) -> float:
    """Mean return of the evaluation episodes stepped one by one in Python (the reference)."""
    key_reset, key_actions = jax.random.split(key)
    # Each call jitted alone (one compile, not one per operation); the loop over steps and episodes stays Python's.
    reset, step, act = (jax.jit(f) for f in (trainer.env.reset, trainer.env.step, trainer.agent.act_deterministic))
    states = [reset(k) for k in jax.random.split(key_reset, trainer.cfg.train.eval_episodes)]
    totals = np.zeros(len(states))
    for key_t in jax.random.split(key_actions, trainer.env.episode_length):
        uniform = jax.random.uniform(key_t, (len(states), trainer.env.action_size), minval=-1.0, maxval=1.0)
        for i, state in enumerate(states):
            action = uniform[i] if random_actions else act(params, state.obs[None])[0]
            states[i] = step(state, action)
            totals[i] += float(states[i].reward)
    return float(totals.mean())


def test_random_policy_evaluation_matches_a_step_loop_on_the_same_initial_states():
    trainer = Trainer(PROBE)
    _, _, evaluate = compiled(trainer)
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    params = jax.vmap(trainer.agent.init)(keys).actor_params
    policy, random = np.asarray(evaluate(params, keys)), np.asarray(evaluate(params, keys, True))
    both = np.asarray(evaluate(params, keys, (False, True)))  # one batch of episodes, as a finished run evaluates
    np.testing.assert_allclose(both, np.stack([policy, random], axis=1), rtol=1e-5, atol=1e-5)
    # A run compiles that program from the shapes while its first round runs: the same numbers.
    ahead = _final_evaluation(evaluate, trainer, jax.eval_shape(jax.vmap(trainer.init), keys), keys)
    returns, success = ahead(params)
    np.testing.assert_array_equal(np.asarray(returns), both)
    assert success is None  # the probe reports no success
    for i in range(2):
        one = jax.tree.map(lambda x, i=i: x[i], params)
        np.testing.assert_allclose(policy[i], _loop_return(trainer, one, keys[i], False), rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(random[i], _loop_return(trainer, one, keys[i], True), rtol=1e-4, atol=1e-4)
    assert not np.allclose(policy, random)


def _write_metrics(path: pathlib.Path, records: list[dict]) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))


def test_summary_table_shows_the_last_logged_values_per_seed_and_their_mean(tmp_path):
    step, segment = "reward_correlation", "reward_correlation_return"
    records = [
        {"env_steps": 10, "labels_used": [0, 0], step: [None, None], "eval_return": [1, 2]},
        {"env_steps": 20, "labels_used": [4, 4], step: [0.5, 0.25], segment: [0.5, 0.6]},
        {"env_steps": 30, "labels_used": [8, 6], step: [None, 0.75], segment: [None, None]},
    ]
    _write_metrics(tmp_path / "metrics.jsonl", records)
    logged = last_logged(tmp_path, 2)
    np.testing.assert_array_equal(logged["labels_used"], [8, 6])
    np.testing.assert_array_equal(logged["reward_correlation"], [0.5, 0.75])
    np.testing.assert_array_equal(logged["reward_correlation_return"], [0.5, 0.6])

    random, final = np.array([1.04, 2.0]), np.array([10.0, 31.26])
    lines = summary_table(["seed 0", "seed 1"], random, final, logged).splitlines()
    assert len(lines) == 4 and "random-policy return" in lines[0]
    assert lines[1].split()[2:] == ["1.0", "10.0", "8", "0.50", "0.50"]
    assert lines[2].split()[2:] == ["2.0", "31.3", "6", "0.75", "0.60"]
    expected = [f"{random.mean():.1f}", f"{final.mean():.1f}", "7", f"{0.625:.2f}", f"{0.55:.2f}"]
    assert lines[3].split()[1:] == expected

    # SAC logs no labels or correlations: dashes.
    (tmp_path / "sac").mkdir()
    _write_metrics(tmp_path / "sac" / "metrics.jsonl", [{"env_steps": 10, "eval_return": [1.0]}])
    row = summary_table(["seed 0"], random[:1], final[:1], last_logged(tmp_path / "sac", 1)).splitlines()[1]
    assert row.split()[2:] == ["1.0", "10.0", "-", "-", "-"]
