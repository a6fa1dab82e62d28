"""Pixel tasks: a state task seen through its camera 0, with action repeat and a frame stack.

``walker_walk_pixels`` and the others are the state task's physics, reset and reward; the agent
observes the last ``frames`` RGB frames of camera 0 (:mod:`rebel_jax.envs.render`), stacked on the
channel axis: uint8 ``(size, size, 3 * frames)``, oldest first. Each agent step repeats the
action ``action_repeat`` times and sums the rewards (SURF's pixel branch and DrQ-v2 use 2 for
walker and cheetah). ``info["steps"]`` and the episode length stay counted in environment
frames, so an episode of 1000 frames is 500 agent steps. The state task's observation stays in
``info["state_obs"]`` and its physics in ``pipeline_state``, for scripted teachers and evaluation.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State

from rebel_jax.envs import render
from rebel_jax.envs.dmc import DMCEnv

SUFFIX = "_pixels"


ACTION_REPEAT = 2
"""Environment frames per agent step of the pixel tasks (SURF's pixel branch and DrQ-v2: 2)."""


def agent_steps(frames: int | None, action_repeat: int = ACTION_REPEAT) -> int | None:
    """Agent steps of an episode of ``frames`` environment frames (None: no time limit)."""
    return None if frames is None else math.ceil(frames / action_repeat)


class PixelEnv(Env):
    """A pixel-observation task around ``env``, a ``brax.envs.Env`` like :class:`DMCEnv`.

    Args:
      env: the state task; it must expose ``mj_model``, ``reset``, ``step``, ``action_size``,
        ``episode_length`` and ``dt``, and keep ``mjx.Data`` with current kinematics in
        ``State.pipeline_state``.
      action_repeat: environment frames per agent step (>= 1).
      frames: frames in the observation stack (>= 1).
      size: frame height and width in pixels.
      camera: the model camera (id or name).
      shadows: let the camera cast shadows (see :func:`rebel_jax.envs.render.make_camera`).
    """

    def __init__(
        self,
        env: DMCEnv,
        action_repeat: int = ACTION_REPEAT,
        frames: int = 3,
        size: int = 84,
        camera: int | str = 0,
        shadows: bool = True,
    ):
        if action_repeat < 1 or frames < 1:
            raise ValueError(f"action_repeat and frames must be >= 1; got {action_repeat}, {frames}")
        self.env, self.action_repeat, self.frames = env, action_repeat, frames
        self.camera = render.make_camera(env.mj_model, camera, size, size, shadows=shadows)

    @property
    def observation_shape(self) -> tuple[int, int, int]:
        return (self.camera.height, self.camera.width, 3 * self.frames)

    @property
    def observation_size(self) -> int:
        return math.prod(self.observation_shape)

    @property
    def action_size(self) -> int:
        return self.env.action_size

    @property
    def episode_length(self) -> int | None:
        """Agent steps per episode (None where the state task has no time limit)."""
        return agent_steps(self.env.episode_length, self.action_repeat)

    @property
    def dt(self) -> float:
        return self.env.dt * self.action_repeat

    @property
    def backend(self) -> str:
        return self.env.backend

    @property
    def mj_model(self):
        return self.env.mj_model

    @property
    def unwrapped(self) -> DMCEnv:
        return self.env.unwrapped

    def render(self, state: State) -> jax.Array:
        """The current frame of ``state``: uint8 (size, size, 3)."""
        return self.camera.render(state.pipeline_state)

    def _wrap(self, inner: State, obs: jax.Array) -> State:
        return inner.replace(obs=obs, info=dict(inner.info, state_obs=inner.obs))

    def _unwrap(self, state: State) -> State:
        info = dict(state.info)
        return state.replace(obs=info.pop("state_obs"), info=info)

    def reset(self, rng: jax.Array) -> State:
        """The state task's reset; the stack holds ``frames`` copies of the first frame."""
        inner = self.env.reset(rng)
        frame = self.camera.render(inner.pipeline_state)
        return self._wrap(inner, jnp.tile(frame, (1, 1, self.frames)))

    def step(self, state: State, action: jax.Array) -> State:
        """Repeats ``action`` for ``action_repeat`` frames; the reward is their sum."""
        inner = self._unwrap(state)

        def frame_step(carry, _):
            inner, reward, done = carry
            inner = self.env.step(inner, action)
            return (inner, reward + inner.reward, jnp.maximum(done, inner.done)), None

        # A scan, not a Python loop, so that the physics step is compiled once.
        zero = jnp.zeros_like(inner.reward)
        (inner, reward, done), _ = jax.lax.scan(frame_step, (inner, zero, zero), length=self.action_repeat)
        frame = self.camera.render(inner.pipeline_state)
        obs = jnp.concatenate([state.obs[..., 3:], frame], axis=-1)
        return self._wrap(inner.replace(reward=reward, done=done), obs)
