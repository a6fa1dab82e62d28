"""The replay contract (``rebel_jax.agents.replay``'s docstring): the state ring and the frame ring share their field
and
function names, and keep the task's reward (``true_reward``) and the reward model's (``learned_reward``) apart:
sampling reads the one asked for, relabelling writes only the learned one."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.agents import frame_replay, replay

ENVS, ROWS, LENGTH, FRAME = 2, 12, 6, (8, 8, 3)
SHARED = ("action", "true_reward", "learned_reward", "terminal", "truncated", "episode_step", "ptr", "size")
STEP_FIELDS = ("obs", "action", "next_obs", "true_reward", "learned_reward", "terminal", "truncated", "episode_step")


def _field_names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


def test_both_rings_name_their_fields_and_functions_alike():
    assert set(SHARED) <= _field_names(replay.Buffer) and set(SHARED) <= _field_names(frame_replay.FrameBuffer)
    assert set(STEP_FIELDS) <= _field_names(replay.Step) and set(STEP_FIELDS) <= _field_names(frame_replay.FrameStep)
    for module in (replay, frame_replay):
        for name in ("init", "add", "sample", "relabel"):
            assert callable(getattr(module, name)), (module.__name__, name)
    for buffer in (replay.init(ROWS * ENVS, ENVS, 3, 2), frame_replay.init(ROWS * ENVS, ENVS, FRAME, 2, LENGTH)):
        assert (buffer.rows, buffer.num_envs) == (ROWS, ENVS)
        assert "reward" not in _field_names(type(buffer))  # no field whose meaning depends on the run


def _fill(ring: str):
    """A ring with ``true_reward = 1000 + 10 t + e`` and ``learned_reward = -(10 t + e)`` at step t, env e, and
    ``action[..., 0] = 10 t + e`` naming each transition."""
    envs = np.arange(ENVS)
    if ring == "state":
        buffer = replay.init(ROWS * ENVS, ENVS, 3, 2)
    else:
        buffer = frame_replay.init(ROWS * ENVS, ENVS, FRAME, 2, LENGTH, 3, learned_reward=True)
    add = jax.jit(replay.add if ring == "state" else frame_replay.add)
    rng = np.random.default_rng(0)
    for t in range(ROWS):
        mark = 10.0 * t + envs
        action = np.stack([mark, np.zeros(ENVS)], -1).astype(np.float32)
        fields = dict(
            action=jnp.asarray(action),
            true_reward=jnp.asarray(1000.0 + mark, jnp.float32),
            learned_reward=jnp.asarray(-mark, jnp.float32),
            terminal=jnp.zeros(ENVS),
            truncated=jnp.full(ENVS, float(t % LENGTH == LENGTH - 1)),
        )
        if ring == "state":
            obs = jnp.asarray(rng.normal(size=(ENVS, 3)), jnp.float32)
            step = replay.Step(obs=obs, next_obs=obs, episode_step=jnp.full(ENVS, t % LENGTH, jnp.int32), **fields)
        else:
            obs = jnp.asarray(rng.integers(0, 256, (ENVS, *FRAME[:2], 9)), jnp.uint8)
            step = frame_replay.FrameStep(obs=obs, next_obs=obs, episode_step=jnp.int32(t % LENGTH), **fields)
        buffer = add(buffer, step)
    return buffer


def _sample(ring: str, buffer, learned: bool):
    if ring == "state":
        return jax.jit(replay.sample, static_argnums=(2, 3))(buffer, jax.random.key(1), 256, learned)
    return jax.jit(frame_replay.sample, static_argnums=(2, 3, 4, 5))(buffer, jax.random.key(1), 256, learned, 1, 0.9)


@pytest.mark.parametrize("ring", ["state", "frames"])
def test_sampling_reads_the_reward_asked_for_and_relabelling_writes_only_the_learned_one(ring):
    buffer = _fill(ring)
    for learned in (True, False):
        batch = _sample(ring, buffer, learned)
        mark = np.asarray(batch.action[:, 0])
        np.testing.assert_array_equal(np.asarray(batch.reward), -mark if learned else 1000.0 + mark)
    relabel = replay.relabel if ring == "state" else frame_replay.relabel
    relabelled = jax.jit(relabel, static_argnums=(1, 2))(buffer, _relabel_fn, 4)
    np.testing.assert_array_equal(relabelled.true_reward, buffer.true_reward)
    np.testing.assert_array_equal(relabelled.learned_reward, 2.0 * np.asarray(buffer.action[..., 0]))


def _relabel_fn(obs, action):
    """A reward of the action alone: ``2 x`` the transition's mark, for either ring's leading axes."""
    del obs  # Unused.
    return 2.0 * action[..., 0]


def test_a_ring_without_a_learned_reward_keeps_none():
    """DrQ-v2 learns from the task's reward: its frame ring has no learned reward to read or relabel."""
    buffer = frame_replay.init(ROWS * ENVS, ENVS, FRAME, 2, LENGTH)
    assert buffer.learned_reward is None and buffer.true_reward.shape == (ROWS, ENVS)
