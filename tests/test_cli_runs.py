"""Whole runs: ``python -m rebel_jax.train`` killed and resumed in subprocesses, and SAC learning.

The subprocesses share the tests' persistent compilation cache (conftest sets it for this
process; the children get it through ``JAX_COMPILATION_CACHE_DIR``), so only the first one
compiles. The test process itself compiles nothing for the CLI test: it compares the saved
arrays with orbax.
"""

from __future__ import annotations

import json
import os
import pathlib
import signal
import subprocess
import sys
import textwrap
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
import pytest

from rebel_jax.config import Config, EnvConfig, SACConfig, TrainConfig
from rebel_jax.train import Trainer, compiled, seed_keys

ROOT = pathlib.Path(__file__).parents[1]

# The sac flags of test_train.MICRO (two seeds): the same compiled round, so the cache is shared.
MICRO_FLAGS = (
    "--preset tiny --algo sac --task probe_point --num-envs 2 --episode-length 20 --hidden 16 --batch-size 16"
    " --utd 0.5 --total-steps 120 --seed-steps 20 --steps-per-round 40 --eval-every 40 --eval-episodes 1"
    " --seeds 2 --seed 7 --no-tensorboard --no-progress"
).split()
ROUNDS = 3
TIMING = ("seconds", "env_steps_per_s")  # the only fields of metrics.jsonl that may differ between runs

# ``python -m rebel_jax.train`` that stops, alive, right after logging the round ending at
# PAUSE_AT_STEPS (its checkpoint not yet written) and says so by creating PAUSE_MARKER.
PAUSED_TRAIN = textwrap.dedent(
    """
    import os, pathlib, runpy, sys, time
    from rebel_jax.logging import RunLogger

    write = RunLogger.write

    def write_then_pause(self, env_steps, metrics, extra):
        write(self, env_steps, metrics, extra)
        if env_steps == int(os.environ["PAUSE_AT_STEPS"]):
            pathlib.Path(os.environ["PAUSE_MARKER"]).touch()
            time.sleep(3600)

    RunLogger.write = write_then_pause
    sys.argv[0] = "rebel_jax.train"
    runpy.run_module("rebel_jax.train", run_name="__main__")
    """
)


def _env(**extra: str) -> dict[str, str]:
    return dict(
        os.environ,
        PYTHONPATH=str(ROOT / "src"),
        JAX_COMPILATION_CACHE_DIR=str(jax.config.jax_compilation_cache_dir),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=str(jax.config.jax_persistent_cache_min_compile_time_secs),
        **extra,
    )


def _train(run_dir: pathlib.Path, *flags: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "rebel_jax.train", *MICRO_FLAGS, "--run-dir", str(run_dir), *flags]
    out = subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=1200)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def _steps_on_disk(run_dir: pathlib.Path) -> list[int]:
    """Committed checkpoints (orbax renames a save's temporary directory to ``<step>`` when it is complete)."""
    return sorted(int(p.name) for p in (run_dir / "checkpoints").iterdir() if p.name.isdigit())


def _saved_arrays(run_dir: pathlib.Path, step: int) -> dict[str, np.ndarray]:
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sharding info not provided")
        with ocp.PyTreeCheckpointer() as checkpointer:
            saved = checkpointer.restore((run_dir / "checkpoints" / str(step) / "default").absolute())
    return {k: np.asarray(v) for k, v in saved.items()}


def _metrics(run_dir: pathlib.Path) -> list[dict]:
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows]


@pytest.mark.slow
def test_cli_run_killed_or_stopped_by_its_time_limit_resumes_to_the_same_result(tmp_path):
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    out_whole = _train(whole)  # compiles (or loads from the cache) everything the others load

    marker = tmp_path / "paused"
    per_round = 40
    env = _env(PAUSE_AT_STEPS=str(3 * per_round), PAUSE_MARKER=str(marker))
    cmd = [sys.executable, "-c", PAUSED_TRAIN, *MICRO_FLAGS, "--run-dir", str(killed)]
    with open(tmp_path / "killed.log", "w") as log:
        proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 1200
        while not marker.exists():
            assert proc.poll() is None, (tmp_path / "killed.log").read_text()[-3000:]
            assert time.monotonic() < deadline, "the run never reached round 3"
            time.sleep(0.1)
        # Round 3 is done and logged; its checkpoint is not written: the latest on disk is round 2's.
        assert _steps_on_disk(killed) == [1, 2]
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
    assert proc.returncode == -signal.SIGKILL
    assert not (killed / "final.json").exists() and len(_metrics(killed)) == 3

    out_resumed = _train(killed, "--resume")

    assert _steps_on_disk(whole) == _steps_on_disk(killed) == [ROUNDS - 1, ROUNDS]
    a, b = _saved_arrays(whole, ROUNDS), _saved_arrays(killed, ROUNDS)
    assert a.keys() == b.keys() and len(a) > 50
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=f"leaf {k}")
    assert json.loads((whole / "final.json").read_text()) == json.loads((killed / "final.json").read_text())
    # The resumed run logged round 3 once more: one row per round, the same as the whole run's.
    assert _metrics(whole) == _metrics(killed)
    assert [row["round"] for row in _metrics(killed)] == list(range(ROUNDS))
    final_line = [line for line in out_whole.stdout.splitlines() if line.startswith("final evaluation return")]
    assert len(final_line) == 1 and final_line[0] in out_resumed.stdout.splitlines()

    # --time-limit: stops after the first round with its checkpoint; --resume finishes the same run.
    timed = tmp_path / "timed"
    out_timed = _train(timed, "--time-limit", "1e-9")
    assert "stopped after round 0" in out_timed.stdout
    assert _steps_on_disk(timed) == [1] and not (timed / "final.json").exists() and len(_metrics(timed)) == 1
    _train(timed, "--resume")
    c = _saved_arrays(timed, ROUNDS)
    for k in a:
        np.testing.assert_array_equal(a[k], c[k], err_msg=f"leaf {k}")
    assert json.loads((whole / "final.json").read_text()) == json.loads((timed / "final.json").read_text())
    assert _metrics(whole) == _metrics(timed)


# SAC on probe_point (a point mass steered to the origin; reward in (0, 1], so an episode of 50 steps
# returns at most 50): it compiles in seconds, so `make test` checks that SAC learns on every run.
PROBE_LEARNING = Config(
    env=EnvConfig(task="probe_point", num_envs=4, episode_length=50),
    sac=SACConfig(hidden=64, batch_size=128, utd=1.0, actor_lr=3e-3, critic_lr=3e-3, gamma=0.9, init_temperature=0.02),
    train=TrainConfig(total_steps=2_000, seed_steps=200, steps_per_round=400, eval_every=400, eval_episodes=1),
)
# SAC on walker_stand with 100-step episodes (return in [0, 100]), tuned to learn fast on a
# CPU: a high update rate (8 updates per vector step), large learning rates, a short horizon
# (gamma 0.9) and a low initial temperature. 12 rounds of 800 steps per seed. One evaluation
# environment in the round (its returns are not used here) keeps the rounds cheap.
LEARNING = Config(
    env=EnvConfig(task="walker_stand", num_envs=8, episode_length=100),
    sac=SACConfig(hidden=64, batch_size=128, utd=1.0, actor_lr=3e-3, critic_lr=3e-3, gamma=0.9, init_temperature=0.02),
    train=TrainConfig(total_steps=9_600, seed_steps=400, steps_per_round=800, eval_every=800, eval_episodes=1),
)
EVAL_EPISODES = 16


def _learn(config: Config, seed: int, seeds: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """Frozen-policy evaluation returns (per seed) of the initial and of the trained actor.

    Both are evaluated on the same ``EVAL_EPISODES`` initial states, so the comparison is paired.
    """
    init, round_fn, _ = compiled(Trainer(config))
    many = Config(env=config.env, sac=config.sac, train=TrainConfig(eval_episodes=EVAL_EPISODES))
    evaluate = jax.jit(jax.vmap(Trainer(many).evaluate))
    eval_keys = jax.random.split(jax.random.PRNGKey(123), seeds)
    state = init(seed_keys(seed, seeds))
    before = np.asarray(evaluate(state.sac.actor_params, eval_keys))
    for r in range(config.train.num_rounds):
        state, _ = round_fn(state, jnp.int32(r))
    return before, np.asarray(evaluate(state.sac.actor_params, eval_keys))


def test_sac_learns_the_probe_task_near_its_best_return():
    before, after = _learn(PROBE_LEARNING, seed=0)
    best = PROBE_LEARNING.env.episode_length  # the reward is at most 1 per step
    # Seen (base seeds 0-3, 2 seeds each): before 4-12, after 48.1-48.3.
    assert np.all(before < 0.5 * best), before
    assert np.all(after > 0.9 * best), after


# Minutes-long at XLA's default optimisation level on 2 cores: `make test-heavy`.
@pytest.mark.heavy
def test_sac_return_goes_up_on_walker_stand():
    before, after = _learn(LEARNING, seed=0)
    # Seen (16-episode means, 2 seeds x base seeds 0-3): before 20-26, after 31-40, gains 6.0-19.0.
    assert np.all(after > before + 3), (before, after)
    assert after.mean() > before.mean() + 6 and after.mean() > 1.25 * before.mean(), (before, after)
