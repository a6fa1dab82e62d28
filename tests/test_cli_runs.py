"""SAC learning on whole runs, and the CLI flags and subprocess environment the CLI tests share.

Runs killed, stopped by their time limit and resumed are in ``test_cli_reliability.py``. Subprocesses
share the tests' persistent compilation cache (conftest sets it for this process; the children get it
through ``JAX_COMPILATION_CACHE_DIR``, :func:`_env`).
"""

from __future__ import annotations

import json
import os
import pathlib

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
    "--preset tiny --algo sac --task probe_point --num-envs 2 --episode-length 20 --sac.hidden 16 --sac.batch-size 16"
    " --sac.utd 0.5 --total-steps 120 --seed-steps 20 --steps-per-round 40 --eval-every 40 --eval-episodes 1"
    " --seeds 2 --seed 7 --no-tensorboard --no-progress"
).split()
ROUNDS = 3
TIMING = ("seconds", "env_steps_per_s")  # the only fields of metrics.jsonl that may differ between runs


def _metrics(run_dir: pathlib.Path) -> list[dict]:
    """A run's ``metrics.jsonl`` rows without their :data:`TIMING` fields."""
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows]


def _saved_arrays(run_dir: pathlib.Path, step: int) -> dict[str, np.ndarray]:
    """The leaves of checkpoint ``step`` as NumPy arrays, whatever devices saved them."""
    path = (run_dir / "checkpoints" / str(step) / "default").absolute()
    with ocp.PyTreeCheckpointer() as checkpointer:
        leaves = checkpointer.metadata(path).item_metadata.keys()
        as_numpy = {k: ocp.RestoreArgs(restore_type=np.ndarray) for k in leaves}
        return checkpointer.restore(path, restore_args=as_numpy)


def _env(**extra: str) -> dict[str, str]:
    return dict(
        os.environ,
        PYTHONPATH=str(ROOT / "src"),
        JAX_COMPILATION_CACHE_DIR=str(jax.config.jax_compilation_cache_dir),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=str(jax.config.jax_persistent_cache_min_compile_time_secs),
        **extra,
    )


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
    before = np.asarray(evaluate(state.agent.actor_params, eval_keys))
    for r in range(config.train.num_rounds):
        state, _ = round_fn(state, jnp.int32(r))
    return before, np.asarray(evaluate(state.agent.actor_params, eval_keys))


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
