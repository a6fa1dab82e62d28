"""Batched environments with automatic reset, on brax's ``Wrapper`` and ``VmapWrapper``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State, Wrapper
from brax.envs.wrappers.training import VmapWrapper


def _select(mask: jax.Array, new, old):
    """Per-environment ``where`` over two batched pytrees."""

    def pick(n, o):
        return jnp.where(mask.reshape(mask.shape + (1,) * (n.ndim - 1)), n, o)

    return jax.tree.map(pick, new, old)


class AutoResetWrapper(Wrapper):
    """``num_envs`` copies of an environment, vmapped (brax's ``VmapWrapper``), that restart when done.

    ``step`` returns, for finished environments, the first state of a fresh episode
    while keeping the finished step's ``reward`` and ``done``; the observation that
    ended the episode is kept in ``info["final_obs"]`` so that an off-policy learner
    stores the true next observation. The reset runs under ``lax.cond`` and costs
    nothing on steps where no environment finishes (outside ``vmap``; under a
    ``vmap`` over seeds JAX evaluates both branches, so synchronous trainers reset
    explicitly at episode boundaries instead, see ``rebel_jax.train``).

    Why not brax's ``AutoResetWrapper``: it restarts a finished environment at the state its
    ``reset`` returned, kept in ``info["first_pipeline_state"]`` and ``info["first_obs"]``
    (``brax/envs/wrappers/training.py``, ``AutoResetWrapper``, brax 0.14.2), so every episode of
    an environment starts from one state. Ours draws each episode's start from the task's reset
    distribution, as dm_control does (tested in ``tests/test_brax.py``).
    """

    def __init__(self, env: Env, num_envs: int):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1; got {num_envs}")
        super().__init__(env)
        self.num_envs = num_envs
        self._batch = VmapWrapper(env)  # A batch of keys or states -> a batch of states.

    def reset(self, rng: jax.Array) -> State:
        rng, key = jax.random.split(rng)
        state = self._batch.reset(jax.random.split(key, self.num_envs))
        # One key per environment: with a shared key, environments that finish together would restart alike.
        info = dict(state.info, rng=jax.random.split(rng, self.num_envs), final_obs=state.obs)
        return state.replace(info=info)

    def step(self, state: State, action: jax.Array) -> State:
        rng = state.info["rng"]
        inner = state.replace(info={k: v for k, v in state.info.items() if k not in ("rng", "final_obs")})
        nxt = self._batch.step(inner, action)
        done = nxt.done > 0

        def reset_done(operand):
            nxt, rng = operand
            keys = jax.vmap(jax.random.split)(rng)
            fresh = self._batch.reset(keys[:, 1])
            restarted = _select(done, fresh, nxt).replace(reward=nxt.reward, done=nxt.done)
            return restarted, jnp.where(done[:, None], keys[:, 0], rng)

        restarted, rng = jax.lax.cond(jnp.any(done), reset_done, lambda x: x, (nxt, rng))
        info = dict(restarted.info, rng=rng, final_obs=nxt.obs)
        return restarted.replace(info=info)
