"""Batched environments with automatic reset."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from rebel_jax.envs.dmc import DMCEnv, State
from rebel_jax.envs.probe import PointProbe


def _select(mask: jax.Array, new, old):
    """Per-environment ``where`` over two batched pytrees."""

    def pick(n, o):
        return jnp.where(mask.reshape(mask.shape + (1,) * (n.ndim - 1)), n, o)

    return jax.tree.map(pick, new, old)


class AutoResetWrapper:
    """``num_envs`` copies of an environment, vmapped, that restart when done.

    ``step`` returns, for finished environments, the first state of a fresh episode
    while keeping the finished step's ``reward`` and ``done``; the observation that
    ended the episode is kept in ``info["final_obs"]`` so that an off-policy learner
    stores the true next observation. The reset runs under ``lax.cond`` and costs
    nothing on steps where no environment finishes (outside ``vmap``; under a
    ``vmap`` over seeds JAX evaluates both branches, so synchronous trainers reset
    explicitly at episode boundaries instead, see ``rebel_jax.train``).
    """

    def __init__(self, env: DMCEnv | PointProbe, num_envs: int):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1; got {num_envs}")
        self.env, self.num_envs = env, num_envs

    def reset(self, rng: jax.Array) -> State:
        rng, key = jax.random.split(rng)
        state = jax.vmap(self.env.reset)(jax.random.split(key, self.num_envs))
        info = dict(state.info, rng=jnp.broadcast_to(rng, (self.num_envs,) + rng.shape), final_obs=state.obs)
        return state.replace(info=info)

    def step(self, state: State, action: jax.Array) -> State:
        rng = state.info["rng"]
        inner = state.replace(info={k: v for k, v in state.info.items() if k not in ("rng", "final_obs")})
        nxt = jax.vmap(self.env.step)(inner, action)
        done = nxt.done > 0

        def reset_done(operand):
            nxt, rng = operand
            keys = jax.vmap(jax.random.split)(rng)
            fresh = jax.vmap(self.env.reset)(keys[:, 1])
            restarted = _select(done, fresh, nxt).replace(reward=nxt.reward, done=nxt.done)
            return restarted, jnp.where(done[:, None], keys[:, 0], rng)

        restarted, rng = jax.lax.cond(jnp.any(done), reset_done, lambda x: x, (nxt, rng))
        info = dict(restarted.info, rng=rng, final_obs=nxt.obs)
        return restarted.replace(info=info)
