"""The probe task the trainer tests run on: its dynamics against a NumPy loop, its interface."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.config import Config, EnvConfig
from rebel_jax.envs import PROBES, make_env, probe


def _numpy_episode(pos0: np.ndarray, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Observations and rewards of one episode, step by step as the module docstring says."""
    pos, vel, obs, rewards = pos0.astype(np.float64), np.zeros(2), [], []
    for a in actions:
        vel = (1 - probe.DAMPING) * vel + probe.ACCEL * np.clip(a, -1, 1)
        pos = np.clip(pos + vel, -probe.BOUND, probe.BOUND)
        obs.append(np.concatenate([pos, vel]))
        rewards.append(np.exp(-np.sum(pos**2) / (2 * probe.WIDTH**2)))
    return np.array(obs), np.array(rewards)


def test_scanned_episode_equals_a_numpy_loop():
    env = make_env("probe_point", episode_length=30)
    actions = jax.random.uniform(jax.random.PRNGKey(1), (30, 2), minval=-2, maxval=2)  # some beyond the clip

    def body(state, action):
        state = env.step(state, action)
        return state, (state.obs, state.reward, state.done, state.info["steps"])

    start = jax.jit(env.reset)(jax.random.PRNGKey(0))
    _, (obs, reward, done, steps) = jax.jit(lambda s, a: jax.lax.scan(body, s, a))(start, actions)
    assert start.obs.shape == (env.observation_size,) and np.all(np.abs(start.obs[:2]) <= 1)
    np.testing.assert_array_equal(start.obs[2:], 0.0)
    ref_obs, ref_reward = _numpy_episode(np.asarray(start.obs[:2]), np.asarray(actions))
    np.testing.assert_allclose(obs, ref_obs, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(reward, ref_reward, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(steps, np.arange(1, 31))
    np.testing.assert_array_equal(done, (np.arange(1, 31) >= 30).astype(np.float32))
    assert np.all((reward > 0) & (reward <= 1))


def test_probe_is_a_task_of_the_config_and_rejects_bad_actions():
    assert "probe_point" in PROBES
    Config(env=EnvConfig(task="probe_point", num_envs=2, episode_length=20)).env.validate()
    env = make_env("probe_point")
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    with pytest.raises(ValueError, match=r"shape \(2,\), got \(6,\)"):
        jax.eval_shape(env.step, state, jnp.zeros(6))
    with pytest.raises(ValueError, match="dm_control"):
        make_env("probe_point", solver="fastest")
