"""``--algo drqv2`` in the scanned round on the tiny-image probe: traced once, vmapped over seeds, DrQ-v2's schedule."""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.agents import frame_replay
from rebel_jax.agents.drqv2 import DrQV2Config
from rebel_jax.config import Config, ConfigError, EnvConfig, TrainConfig
from rebel_jax.run.cli import parse
from rebel_jax.train import Trainer, compiled, seed_keys

# Episodes of 20 frames = 10 agent steps (action repeat 2), 16x16 images, rounds of one episode.
MICRO = Config(
    algo="drqv2",
    env=EnvConfig(task="probe_point_pixels", num_envs=2, episode_length=20),
    drqv2=DrQV2Config(feature_dim=8, hidden=16, batch_size=16, nstep=3, std_steps=40),
    train=TrainConfig(total_steps=60, seed_steps=20, steps_per_round=20, eval_every=20, eval_episodes=1),
)
ROUNDS, SEEDS = 3, 2


@pytest.fixture(scope="module")
def run():
    trainer = Trainer(MICRO)
    init, round_fn, evaluate = compiled(trainer)
    state = init(seed_keys(0, SEEDS))
    metrics = []
    for r in range(ROUNDS):
        state, m = round_fn(state, jnp.int32(r))
        metrics.append(jax.device_get(m))
    return trainer, state, metrics, evaluate


def test_round_is_traced_once_and_updates_on_drqv2_schedule(run):
    trainer, state, metrics, _ = run
    assert trainer.trace_count == 1
    envs, every = MICRO.env.num_envs, MICRO.drqv2.update_every
    vector_steps = ROUNDS * MICRO.train.steps_per_round // envs
    # One update per `every` agent steps once the seed steps are collected (drqv2.py:233, train.py:180).
    expected = sum(envs // every for t in range(vector_steps) if t * envs >= MICRO.train.seed_steps)
    np.testing.assert_array_equal(state.agent.steps, expected)
    assert expected > 0
    assert int(state.buffer.size[0]) == vector_steps
    for key in ("critic_loss", "actor_loss", "q", "train_return", "eval_return"):
        assert np.all(np.isfinite(metrics[-1][key])), key
    np.testing.assert_array_equal(metrics[-1]["diverged"], 0.0)
    assert np.all(metrics[0]["critic_loss"] == 0.0)  # the first round only seeds
    # The std schedule is read at the seed's agent-step count (DrQ-v2's global_step).
    assert 0.1 <= float(metrics[-1]["std"][0]) < 1.0


def test_seed_loop_rounds_equal_the_batched_rounds(run):
    """``drqv2.seed_loop`` (on in ``run``) inside the seed-vmapped round (scan, cond, donation): the batched
    update gives the same run up to float rounding."""
    _, looped, looped_metrics, _ = run
    assert MICRO.drqv2.seed_loop
    trainer = Trainer(dataclasses.replace(MICRO, drqv2=dataclasses.replace(MICRO.drqv2, seed_loop=False)))
    init, round_fn, _ = compiled(trainer)
    state = init(seed_keys(0, SEEDS))
    for r in range(ROUNDS):
        state, metrics = round_fn(state, jnp.int32(r))
    assert trainer.trace_count == 1
    close = functools.partial(np.testing.assert_allclose, rtol=1e-4, atol=1e-5)
    jax.tree.map(close, state.agent, looped.agent)
    close(metrics["critic_loss"], looped_metrics[-1]["critic_loss"])


def test_a_column_is_the_one_seed_run_of_its_key(run):
    """Seeds are independent columns: column 1 of the 2-seed program is the 1-seed program run from that
    column's key (its envs, frames, updates and evaluations use nothing of column 0). One of two walker
    seeds learned nothing in a GPU run (RESULTS.md, question 1); this rules out a mix-up of columns."""
    trainer, state, metrics, _ = run
    alone = Trainer(MICRO)
    init, round_fn, _ = compiled(alone)
    single = init(seed_keys(0, SEEDS)[1:])
    for r in range(ROUNDS):
        single, single_metrics = round_fn(single, jnp.int32(r))
    close = functools.partial(np.testing.assert_allclose, rtol=1e-4, atol=1e-5)  # float rounding of a batch
    jax.tree.map(lambda a, b: close(a[1], b[0]), (state.agent, state.buffer), (single.agent, single.buffer))
    np.testing.assert_array_equal(state.buffer.frames[1], single.buffer.frames[0])  # every pixel
    for key in ("critic_loss", "train_return", "eval_return"):
        close(metrics[-1][key][1], single_metrics[key][0])


def test_seeds_differ_and_the_buffer_holds_frames_once(run):
    trainer, state, _, evaluate = run
    leaves = jax.tree.leaves(state.agent.actor_params)
    assert not np.allclose(leaves[0][0], leaves[0][1])
    frames = state.buffer.frames
    assert frames.dtype == jnp.uint8 and frames.shape[-3:] == (16, 16, 3)
    rows = state.buffer.true_reward.shape[1]
    assert frames.shape[1] < rows + rows // trainer.episode_length + 5
    # The newest row's rebuilt next_obs is what the training environments observe now (the reset comes
    # at the next vector step), so the trainer's rows, frames and episode steps line up with the env.
    for seed in range(SEEDS):
        buffer = jax.tree.map(lambda x, seed=seed: x[seed], state.buffer)
        envs = jnp.arange(MICRO.env.num_envs)
        last = jnp.full_like(envs, (int(buffer.ptr) - 1) % buffer.rows)
        rebuilt = frame_replay.gather(buffer, last, envs, 1, 0.99, False)
        np.testing.assert_array_equal(rebuilt.next_obs, state.env.obs[seed, : MICRO.env.num_envs])
    final = np.asarray(evaluate(trainer.policy_params(state), seed_keys(1, SEEDS)))
    assert final.shape == (SEEDS,) and np.all(np.isfinite(final))


def test_cli_takes_drqv2_only_with_a_pixel_task(capsys):
    args = parse(["--preset", "tiny", "--algo", "drqv2", "--task", "walker_walk_pixels", "--drqv2.nstep", "1"])
    assert args.config.algo == "drqv2" and args.config.drqv2.nstep == 1 and not args.config.preference
    assert args.config.drqv2.seed_loop
    batched = parse(["--preset", "tiny", "--algo", "drqv2", "--task", "walker_walk_pixels", "--drqv2.no-seed-loop"])
    assert not batched.config.drqv2.seed_loop
    for flags in (["--algo", "drqv2", "--task", "walker_walk"], ["--algo", "sac", "--task", "walker_walk_pixels"]):
        with pytest.raises(SystemExit) as err:
            parse(["--preset", "tiny", *flags])
        assert err.value.code == 2
        assert "drqv2" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="update_every"):
        train = TrainConfig(total_steps=6000, steps_per_round=6000, eval_every=6000)
        env = EnvConfig(task="probe_point_pixels", num_envs=6)
        Config(algo="drqv2", env=env, drqv2=DrQV2Config(update_every=4), train=train).validate()
