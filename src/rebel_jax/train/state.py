"""What one seed carries from round to round, and the pure helpers on it: :class:`TrainState`, its seeds' keys,
its method's key, and the metrics of a round without a value (NaN)."""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from rebel_jax.envs import State
from rebel_jax.train.episodes import EpisodeStats


@struct.dataclass
class TrainState:
    """Everything one seed carries from round to round (all of it is checkpointed).

    Attributes:
      agent: the agent's state (networks, optimisers; SAC's temperature).
      buffer: the replay of training transitions (the state ring or the frame ring).
      env: batched env state, ``num_envs`` training then ``eval_episodes`` evaluation envs.
      episodes: running and last returns.
      key: the PRNG key of the run.
      reward: the reward ensemble and its labels (preference methods; else None).
      entropy_stats: running statistics of the pre-training kNN distances (preference methods on state tasks).
      lam: () the method's traced knob (REBEL's signed lambda), so that a sweep can vmap over it (None: none).
      teacher: the scripted teacher's knobs (``teachers.knobs``), traced for the same reason (preference methods).
      eval_policy: the policy parameters the evaluation environments follow (``Agent.policy``), frozen at the
        start of each episode.
      eval_trajectory: REBEL's on-policy V (``rebel.source='onpolicy'``; else None): the first
        ``rebel.episodes`` evaluation environments' steps over the first ``rebel.horizon`` steps T of their
        episodes (:func:`rebel_jax.train.episodes.record_trajectory`), ``current`` being written and ``last`` the last
        complete one: ``{"obs": (T, episodes, obs_size), "action": (T, episodes, act_size)}`` on state tasks,
        the newest frames ``{"frame": (T, episodes, H, W, 3) uint8, ...}`` on pixel tasks.
      method: the preference method's own state (``Method.init_state``; None: none), last so that the leaves of a
        state without one are those of a run saved before methods had state.
    """

    agent: Any
    buffer: Any
    env: State
    episodes: EpisodeStats
    key: jax.Array
    reward: Any = None
    entropy_stats: Any = None
    lam: jax.Array | None = None
    teacher: dict[str, jax.Array] | None = None
    eval_policy: Any = None
    eval_trajectory: dict | None = None
    method: Any = None


METHOD_KEY = 0x6D657468
"""Folded into a seed's key to make its method's state (``Method.init_state``), and into a vector step's update key
for the method's pre-training step: keys of their own, which leave every other draw of the run as it was."""


def nan_like(shapes: dict) -> dict[str, jax.Array]:
    """NaN arrays shaped and typed as ``shapes`` (``jax.eval_shape`` output): a metric where it has no value."""
    return {k: jnp.full(v.shape, jnp.nan, v.dtype) for k, v in shapes.items()}


def method_mean(values: jax.Array, weight: jax.Array) -> jax.Array:
    """The ``weight``-weighted mean of a method's per-step metric over the steps where it is defined (not NaN);
    NaN where it is nowhere."""
    defined = ~jnp.isnan(values)
    w = jnp.where(defined, weight, 0.0)
    total = jnp.sum(w)
    return jnp.where(total > 0, jnp.sum(jnp.where(defined, values, 0.0) * w) / jnp.maximum(total, 1e-30), jnp.nan)


def replay_rows(state: TrainState) -> int:
    """T, the transition rows of the replay of ``state`` (columns on its leading axis)."""
    return state.buffer.true_reward.shape[1]


def grow_replay(state: TrainState, like: TrainState) -> TrainState:
    """``state`` with each replay leaf padded with zeros, after its column axis, to the shape of ``like``'s.

    Only for a run extended with a larger ``--total-steps`` whose capacity is its length: such a
    buffer never wrapped, so its ``size`` rows are the first ones and writing continues at ``size``. A pixel
    run's frame ring (``frame_replay.FrameBuffer``) never wrapped either (it holds every frame of its rows):
    its frame rows are padded too, and its next frame row stays where it was.
    """

    def pad(x, target):
        if x.shape == target.shape:
            return x
        rows = (x.shape[0], target.shape[1] - x.shape[1], *x.shape[2:])
        return jnp.concatenate([x, jnp.zeros(rows, x.dtype)], axis=1)

    grown = jax.tree.map(pad, state.buffer, like.buffer)
    return state.replace(buffer=grown.replace(ptr=jnp.array(grown.size, copy=True)))  # not donated twice


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
    """One raw PRNG key per seed: ``fold_in(base, i)``, every integer ``seed`` its own ``base``.

    ``base`` is ``PRNGKey(seed)`` for ``0 <= seed < 2**32`` (``PRNGKey`` keeps 32 bits). Any other seed starts from
    ``PRNGKey`` of the low 32 bits of ``|seed|`` and folds in ``2 * chunks + (seed < 0)``, then each further 32-bit
    chunk of ``|seed|``, low to high: the folded words spell the whole integer, sign included.
    """
    magnitude = abs(int(seed))
    base = jax.random.PRNGKey(magnitude & 0xFFFFFFFF)
    chunks = [(magnitude >> shift) & 0xFFFFFFFF for shift in range(32, magnitude.bit_length(), 32)]
    words = [2 * len(chunks) + (seed < 0), *chunks] if seed < 0 or chunks else []
    for word in words:
        base = jax.random.fold_in(base, word)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(num_seeds))
