"""What the round keeps about its episodes: running true returns, REBEL's recorded evaluation trajectories, and
the divergence check's finiteness test."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct


@struct.dataclass
class EpisodeStats:
    """Running true returns of the current episodes and the last finished ones.

    Attributes:
      running: (num_envs + eval_episodes,) return so far of each environment's episode.
      train_return: () mean return of the last finished training episodes (NaN before any).
      eval_return: () mean return of the last finished evaluation episodes (NaN before any).
      succeeded: (num_all + ...) whether each environment's episode has succeeded so far, on a task that reports
        success (Meta-World's); else None, and so are the two below (a run's state keeps its leaves).
      train_success: () the fraction of the last finished training episodes that succeeded (NaN before any).
      eval_success: () the same of the evaluation episodes: B-Pref's success rate, an episode succeeding if any of
        its steps does (rll-research/BPref@f3ece2e:train_PEBBLE.py:92-114, as a fraction instead of a percentage).
    """

    running: jax.Array
    train_return: jax.Array
    eval_return: jax.Array
    succeeded: jax.Array | None = None
    train_success: jax.Array | None = None
    eval_success: jax.Array | None = None

    @staticmethod
    def init(num_all: int, success: bool = False) -> EpisodeStats:
        """No return yet for ``num_all`` environments; with ``success``, no success either."""
        nan = jnp.full((), jnp.nan, jnp.float32)
        if not success:
            return EpisodeStats(jnp.zeros(num_all), nan, nan)
        return EpisodeStats(jnp.zeros(num_all), nan, nan, jnp.zeros(num_all), nan, nan)

    def after_step(self, reward: jax.Array, done: jax.Array, n: int, success: jax.Array | None = None) -> EpisodeStats:
        """The statistics after one vector step of rewards, done flags and (a task that reports it) success flags,
        the first ``n`` envs training ones."""
        running = self.running + reward
        finished = done > 0

        def finished_mean(values, part, last):
            mask = finished[part]
            mean = jnp.sum(jnp.where(mask, values[part], 0.0)) / jnp.maximum(jnp.sum(mask), 1)
            return jnp.where(jnp.any(mask), mean, last)

        stats = EpisodeStats(
            running=jnp.where(finished, 0.0, running),
            train_return=finished_mean(running, slice(0, n), self.train_return),
            eval_return=finished_mean(running, slice(n, None), self.eval_return),
        )
        if self.succeeded is None:
            return stats
        succeeded = jnp.maximum(self.succeeded, (success > 0).astype(self.succeeded.dtype))
        return stats.replace(
            succeeded=jnp.where(finished, 0.0, succeeded),
            train_success=finished_mean(succeeded, slice(0, n), self.train_success),
            eval_success=finished_mean(succeeded, slice(n, None), self.eval_success),
        )

    def returns_ok(self, before: EpisodeStats) -> jax.Array:
        """Whether both last returns are finite, or still NaN (no episode finished yet) as they were ``before``."""
        ok = [
            jnp.isfinite(new) | (jnp.isnan(new) & jnp.isnan(old))
            for new, old in ((self.train_return, before.train_return), (self.eval_return, before.eval_return))
        ]
        return ok[0] & ok[1]


def init_trajectory(fields: dict[str, tuple[tuple[int, ...], Any]], episodes: int, horizon: int) -> dict:
    """An empty store of REBEL's on-policy trajectories (``TrainState.eval_trajectory``).

    Args:
      fields: name -> (shape of one environment's step, dtype), e.g. the state observation and the
        action (state tasks), or the newest frame and the action (pixel tasks).
      episodes: N, evaluation environments recorded.
      horizon: T, steps recorded from each episode's reset.

    Returns:
      ``{"current": ..., "last": ...}``, each ``{name: (T, N, *shape)}`` zeros.
    """
    episode = {name: jnp.zeros((horizon, episodes, *shape), dtype) for name, (shape, dtype) in fields.items()}
    return {"current": episode, "last": episode}


def record_trajectory(trajectory: dict, step: dict[str, jax.Array], t: jax.Array, episode_length: int) -> dict:
    """Writes the evaluation environments' step ``t`` into ``current``; copies it to ``last`` once complete.

    The episode's step ``k = t mod episode_length`` goes to row k of each field while ``k < T`` (the
    store's horizon; later steps are dropped), and at ``k = T - 1`` the T steps are copied to ``last``:
    ``last`` holds the first T steps of the most recent evaluation episodes that have taken them. The copy
    is a ``lax.cond`` on the unbatched ``t``, a real branch under ``vmap``.

    Args:
      trajectory: the store (:func:`init_trajectory`).
      step: name -> (N, ...) this step's values, the state acted in and the action taken.
      t: the vector-step index (unbatched; all episodes start together).
      episode_length: agent steps per episode.
    """
    k = t % episode_length
    horizon = jax.tree.leaves(trajectory["last"])[0].shape[0]
    current = {name: trajectory["current"][name].at[k].set(value, mode="drop") for name, value in step.items()}
    last = jax.lax.cond(k == horizon - 1, lambda: current, lambda: trajectory["last"])
    return {"current": current, "last": last}


def all_finite(tree) -> jax.Array:
    """Whether every floating-point value in ``tree`` is finite."""
    leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


def physics_positions(pipeline_state) -> jax.Array:
    """The positions a clip is drawn from: MJX's ``qpos``, or the probe's ``pos``."""
    qpos = getattr(pipeline_state, "qpos", None)
    return pipeline_state.pos if qpos is None else qpos
