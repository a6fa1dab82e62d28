"""Replay buffer: scan equals loop, ring wrap-around, sampling support, relabelling."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.agents import replay
from rebel_jax.preference import queries

E, OBS, ACT = 3, 4, 2


def _steps(num_rows: int, seed: int = 0) -> replay.Step:
    """``num_rows`` stacked vector steps; obs[t, e, 0] = t and obs[t, e, 1] = e identify each entry."""
    rng = np.random.default_rng(seed)
    t = np.arange(num_rows, dtype=np.float32)[:, None] * np.ones((1, E), np.float32)
    e = np.ones((num_rows, 1), np.float32) * np.arange(E, dtype=np.float32)[None]
    obs = np.concatenate([t[..., None], e[..., None], rng.normal(size=(num_rows, E, OBS - 2))], axis=-1)
    return replay.Step(
        obs=obs.astype(np.float32),
        action=rng.uniform(-1, 1, (num_rows, E, ACT)).astype(np.float32),
        next_obs=(obs + 0.5).astype(np.float32),
        true_reward=rng.normal(size=(num_rows, E)).astype(np.float32),
        terminal=(rng.uniform(size=(num_rows, E)) < 0.3).astype(np.float32),
        truncated=(rng.uniform(size=(num_rows, E)) < 0.2).astype(np.float32),
        episode_step=rng.integers(0, 1000, (num_rows, E)).astype(np.int32),
        learned_reward=rng.normal(size=(num_rows, E)).astype(np.float32),
    )


def _row(steps: replay.Step, t: int) -> replay.Step:
    return jax.tree.map(lambda x: x[t], steps)


def _fill(buffer: replay.Buffer, steps: replay.Step) -> replay.Buffer:
    return jax.jit(lambda b, s: jax.lax.scan(lambda b, x: (replay.add(b, x), None), b, s)[0])(buffer, steps)


FIELDS = ("obs", "action", "next_obs", "true_reward", "learned_reward", "terminal", "truncated", "episode_step")


def test_init_layout():
    buffer = replay.init(capacity=20, num_envs=E, obs_size=OBS, action_size=ACT)
    chex.assert_shape([buffer.obs, buffer.next_obs], (6, E, OBS))
    chex.assert_shape(buffer.action, (6, E, ACT))
    chex.assert_shape(
        [buffer.true_reward, buffer.learned_reward, buffer.terminal, buffer.truncated, buffer.episode_step], (6, E)
    )
    chex.assert_type([buffer.episode_step, buffer.ptr, buffer.size], jnp.int32)
    with pytest.raises(ValueError):
        replay.init(capacity=2, num_envs=E, obs_size=OBS, action_size=ACT)


def test_scan_add_equals_python_loop():
    steps = _steps(5)
    buffer = replay.init(capacity=8 * E, num_envs=E, obs_size=OBS, action_size=ACT)
    scanned = _fill(buffer, steps)
    looped = buffer
    add = jax.jit(replay.add)
    for t in range(5):
        looped = add(looped, _row(steps, t))
    jax.tree.map(np.testing.assert_array_equal, scanned, looped)
    for name in FIELDS:
        np.testing.assert_array_equal(getattr(scanned, name)[:5], getattr(steps, name))
        assert not np.any(getattr(scanned, name)[5:])
    assert int(scanned.ptr) == 5 and int(scanned.size) == 5


def test_add_without_learned_reward_stores_zeros():
    step = _row(_steps(1), 0).replace(learned_reward=None)
    buffer = replay.add(replay.init(2 * E, E, OBS, ACT), step)
    np.testing.assert_array_equal(buffer.learned_reward, 0.0)
    np.testing.assert_array_equal(buffer.true_reward[0], step.true_reward)


def test_ring_wraps_around():
    rows, total = 4, 11
    steps = _steps(total)
    buffer = _fill(replay.init(rows * E, E, OBS, ACT), steps)
    assert int(buffer.size) == rows and int(buffer.ptr) == total % rows
    for r in range(rows):
        t = max(k for k in range(total) if k % rows == r)  # The latest step written to row r.
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(buffer, name)[r], getattr(steps, name)[t])


def test_sample_only_filled_entries():
    steps = _steps(5)
    buffer = _fill(replay.init(16 * E, E, OBS, ACT), steps)
    batch = jax.jit(replay.sample, static_argnums=2)(buffer, jax.random.key(0), 4096, False)
    t, e = np.asarray(batch.obs[:, 0]).astype(int), np.asarray(batch.obs[:, 1]).astype(int)
    assert t.min() == 0 and t.max() == 4  # Rows 5..15 are empty and never drawn.
    assert set(e) == set(range(E))
    counts = np.bincount(t * E + e, minlength=5 * E)
    assert counts.min() > 0.6 * 4096 / (5 * E)  # Every filled pair is drawn, roughly uniformly.
    np.testing.assert_array_equal(batch.action, steps.action[t, e])
    np.testing.assert_array_equal(batch.next_obs, steps.next_obs[t, e])
    np.testing.assert_array_equal(batch.reward, steps.true_reward[t, e])
    np.testing.assert_array_equal(batch.discount, 1.0 - steps.terminal[t, e])


def test_sample_learned_reward_switch():
    steps = _steps(5)
    buffer = _fill(replay.init(8 * E, E, OBS, ACT), steps)
    sample = jax.jit(replay.sample, static_argnums=2)
    for use_learned in (True, False, jnp.asarray(True)):
        batch = sample(buffer, jax.random.key(1), 64, use_learned)
        t, e = np.asarray(batch.obs[:, 0]).astype(int), np.asarray(batch.obs[:, 1]).astype(int)
        expected = steps.learned_reward if bool(use_learned) else steps.true_reward
        np.testing.assert_array_equal(batch.reward, expected[t, e])


def _reward_fn(obs, action):
    return jnp.tanh(obs @ jnp.arange(1.0, OBS + 1)) * jnp.sum(action, axis=-1) + obs[:, 0]


@pytest.mark.parametrize("chunk_rows", [1, 2, 3, 7, 100])
def test_relabel_equals_per_transition_loop(chunk_rows):
    buffer = _fill(replay.init(7 * E, E, OBS, ACT), _steps(5))
    relabelled = jax.jit(replay.relabel, static_argnums=(1, 2))(buffer, _reward_fn, chunk_rows)
    single = jax.jit(lambda o, a: _reward_fn(o[None], a[None])[0])
    expected = np.zeros((buffer.rows, E), np.float32)
    for t in range(buffer.rows):
        for e in range(E):
            expected[t, e] = single(buffer.obs[t, e], buffer.action[t, e])
    np.testing.assert_allclose(relabelled.learned_reward, expected, rtol=1e-6, atol=1e-6)
    for name in set(FIELDS) - {"learned_reward"}:
        np.testing.assert_array_equal(getattr(relabelled, name), getattr(buffer, name))


@pytest.mark.parametrize("total, rows", [(3, 2), (11, 3), (8, 4)])
def test_latest_rows_are_the_last_written_oldest_first(total, rows):
    steps = _steps(total)
    buffer = _fill(replay.init(4 * E, E, OBS, ACT), steps)  # A ring of 4 rows: 11 steps wrap it twice.
    latest = np.asarray(buffer.obs[queries.window_index(buffer, rows)])
    np.testing.assert_array_equal(latest, steps.obs[total - rows : total])
