"""A pure-JAX probe task for testing the training loop: a damped point mass steered to a goal.

Not a dm_control task. It is a ``brax.envs.Env`` with brax's ``State``, as
:class:`rebel_jax.envs.DMCEnv` is, so the trainer runs it unchanged, but it compiles in seconds where an
MJX model takes about a minute on a CPU. The tests of the training machinery (trace
counts, vmap over seeds, resume, sharding, the preference pipeline, the CLI) use it, as
brax's own tests use its ``fast`` environment, and one test that SAC learns; the tests of the tasks and
the heavy learning tests use the MJX tasks.

Dynamics, per control step, with the action clipped to [-1, 1]^2::

    vel' = (1 - DAMPING) * vel + ACCEL * action
    pos' = clip(pos + vel', -BOUND, BOUND)
    reward = exp(-|pos'|^2 / (2 * WIDTH^2))        # in (0, 1], 1 at the goal (the origin)

The observation is ``concat(pos, vel)``; the reset draws ``pos`` uniformly in [-1, 1]^2 with
``vel = 0``. Episodes end only by the time limit (``episode_length``; ``None`` leaves it to brax's
``EpisodeWrapper`` and keeps no ``steps``/``truncation`` in ``info``, as ``DMCEnv`` does).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State
from flax import struct

DAMPING = 0.1
ACCEL = 0.1
BOUND = 1.5
WIDTH = 0.3


@struct.dataclass
class PointState:
    """The probe's physics: position and velocity, each (2,)."""

    pos: jax.Array
    vel: jax.Array


def reward_of(pos: jax.Array) -> jax.Array:
    """The probe's reward at position ``pos`` (..., 2)."""
    return jnp.exp(-jnp.sum(pos**2, axis=-1) / (2 * WIDTH**2))


class PointProbe(Env):
    """The ``probe_point`` task (see the module docstring)."""

    observation_size = 4
    action_size = 2
    dt = 0.1
    backend = "jax"

    def __init__(self, episode_length: int | None = 1000):
        if episode_length is not None and episode_length < 1:
            raise ValueError(f"episode_length must be >= 1 or None; got {episode_length}")
        self.episode_length = episode_length

    @property
    def unwrapped(self) -> PointProbe:
        return self

    def _state(self, p: PointState, done: jax.Array, info: dict) -> State:
        distance = jnp.linalg.norm(p.pos)
        obs = jnp.concatenate([p.pos, p.vel])
        return State(p, obs, reward_of(p.pos), done, {"distance": distance}, info)

    def reset(self, rng: jax.Array) -> State:
        pos = jax.random.uniform(rng, (2,), minval=-1.0, maxval=1.0)
        zero = jnp.zeros(())
        info = {} if self.episode_length is None else {"steps": jnp.zeros((), jnp.int32), "truncation": zero}
        return self._state(PointState(pos, jnp.zeros(2)), zero, info)

    def step(self, state: State, action: jax.Array) -> State:
        if action.shape != (self.action_size,):
            raise ValueError(f"probe_point: action must have shape (2,), got {action.shape}")
        p = state.pipeline_state
        vel = (1.0 - DAMPING) * p.vel + ACCEL * jnp.clip(action, -1.0, 1.0)
        pos = jnp.clip(p.pos + vel, -BOUND, BOUND)
        if self.episode_length is None:
            return self._state(PointState(pos, vel), jnp.zeros_like(state.done), dict(state.info))
        steps = state.info["steps"] + 1
        done = (steps >= self.episode_length).astype(jnp.float32)
        return self._state(PointState(pos, vel), done, dict(state.info, steps=steps, truncation=done))
