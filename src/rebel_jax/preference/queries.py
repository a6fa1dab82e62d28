"""Segment sampling and query selection (PEBBLE / B-Pref, rll-research/BPref@f3ece2e).

The replay buffer is time-major: every field is shaped (T, E, ...) with E environments per
seed, rows are written in a ring at ``ptr`` and ``size`` rows are filled. Any object with the
attributes ``obs``, ``action``, ``reward``, ``episode_step``, ``ptr`` and ``size`` works here.

**Recent episodes** (``QueryConfig.pool``). B-Pref draws query segments from its last 100
*complete* episodes, each segment starting uniformly in ``[0, episode_length - H)``
(``reward_model.py`` ``get_queries`` at rll-research/BPref f3ece2e, lines 300-331:
``np.random.choice(len_traj - size_segment)``, the unfinished episode dropped). ``pool =
"episodes"`` does exactly that (:func:`sample_episode_segments`): an episode is complete once
its last transition (terminal, truncated or at step ``episode_length - 1``) is in the buffer.
``pool = "rows"``, this project's earlier rule, kept for the ablation: the buffer interleaves
E environments row by row, so "the most recent ``recent_episodes`` episodes" is approximated
by the most recent
``W = ceil(recent_episodes * episode_length / E)`` rows (clipped to T): these rows hold
``recent_episodes * episode_length`` transitions, i.e. ``recent_episodes`` episodes' worth
spread over the E environments. Unlike B-Pref, the current incomplete episode of each
environment is included (its finished part is as recent as data gets).

**Episode boundaries.** A segment of H steps starting at window row ``i`` of env ``e`` is valid
iff its H rows are filled and inside the window, and ``episode_step[i + H - 1] ==
episode_step[i] + H - 1``. Because ``episode_step`` restarts at 0 on every new episode and
grows by one per step, that equality holds exactly when no episode starts inside the segment
(any restart makes the last step smaller), with or without early termination; it implies
``episode_step[i] + H <= episode_length``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any, Literal

import flax.struct
import jax
import jax.numpy as jnp

from rebel_jax.core.errors import check as _check

Sampling = Literal["uniform", "disagreement", "entropy"]


@dataclasses.dataclass(frozen=True)
class QueryConfig:
    """Which segment pairs are shown to the teacher."""

    segment_length: int = 50
    """Steps H per segment (B-Pref: 50)."""
    recent_episodes: int = 100
    """Segments are cut from the most recent this-many episodes' worth of buffer rows (B-Pref: 100)."""
    sampling: Sampling = "uniform"
    """uniform, disagreement (std of the ensemble's preference probability) or entropy (of its mean)."""
    candidate_factor: int = 10
    """Disagreement/entropy score candidate_factor x num_queries uniform pairs and keep the top ones (B-Pref: 10)."""
    pool: Literal["episodes", "rows"] = "episodes"
    """Where segments come from: ``episodes``, B-Pref's last ``recent_episodes`` complete episodes with
    starts uniform in [0, episode_length - H); ``rows``, the last rows holding that many episodes'
    worth of transitions, unfinished episodes included (this project's earlier rule)."""

    def validate(self, episode_length: int | None = None) -> None:
        _check(self.segment_length >= 1, "query.segment_length", self.segment_length, ">= 1")
        if episode_length is not None:
            _check(
                self.segment_length <= episode_length,
                "query.segment_length",
                self.segment_length,
                f"<= env.episode_length={episode_length}",
            )
        _check(self.recent_episodes >= 1, "query.recent_episodes", self.recent_episodes, ">= 1")
        _check(
            self.sampling in ("uniform", "disagreement", "entropy"),
            "query.sampling",
            self.sampling,
            "uniform, disagreement, entropy",
        )
        _check(self.candidate_factor >= 1, "query.candidate_factor", self.candidate_factor, ">= 1")
        _check(self.pool in ("episodes", "rows"), "query.pool", self.pool, "episodes, rows")


@flax.struct.dataclass
class Segments:
    """N segments of H consecutive steps of one episode each."""

    obs: jax.Array
    """(N, H, obs_size) observations."""
    action: jax.Array
    """(N, H, act_size) actions taken in them."""
    true_reward: jax.Array
    """(N, H) true task rewards (seen only by the teacher and diagnostics)."""
    row: jax.Array | None = None
    """(N, H) int32 buffer rows of the steps (where a segment came from: the human teacher's clips and
    label file read it; unused otherwise, so compiled away)."""
    env: jax.Array | None = None
    """(N, H) int32 buffer environment of the steps (the same along H)."""


def window_rows(buffer: Any, segment_length: int, episode_length: int, recent_episodes: int) -> int:
    """The static number W of most recent buffer rows that queries are drawn from.

    Args:
      buffer: the replay buffer (only its static shapes are read).
      segment_length: H.
      episode_length: control steps per episode.
      recent_episodes: episodes' worth of transitions to keep.

    Returns:
      ``min(T, max(H, ceil(recent_episodes * episode_length / E)))``.
    """
    capacity, num_envs = buffer.episode_step.shape[:2]
    rows = math.ceil(recent_episodes * episode_length / num_envs)
    return min(capacity, max(segment_length, rows))


def window_index(buffer: Any, rows: int) -> jax.Array:
    """Absolute buffer rows of the last ``rows`` written before ``ptr`` (the window), oldest first: (W,) int32."""
    capacity = buffer.episode_step.shape[0]
    return (buffer.ptr - rows + jnp.arange(rows)) % capacity


def valid_starts(buffer: Any, segment_length: int, episode_length: int, recent_episodes: int) -> jax.Array:
    """Which (window row, env) may start a segment.

    Args:
      buffer: the replay buffer.
      segment_length: H.
      episode_length: control steps per episode.
      recent_episodes: see ``QueryConfig.recent_episodes``.

    Returns:
      (W, E) bool; row i of the window is absolute row ``(ptr - W + i) % T``.
    """
    rows = window_rows(buffer, segment_length, episode_length, recent_episodes)
    horizon = segment_length
    index = window_index(buffer, rows)
    steps = buffer.episode_step[index]  # (W, E)
    offset = jnp.arange(rows)
    filled = offset >= rows - buffer.size  # The last `size` rows of the window are written.
    inside = offset + horizon <= rows
    last = jnp.roll(steps, -(horizon - 1), axis=0)  # Row i + H - 1 (wrapped rows are excluded by `inside`).
    continuous = last == steps + (horizon - 1)
    fits = steps + horizon <= episode_length
    return (filled & inside)[:, None] & continuous & fits


def _gather(buffer: Any, time: jax.Array, env: jax.Array) -> Segments:
    """Segments at absolute rows ``time`` (n, H) of environments ``env`` (n, 1)."""
    return Segments(
        obs=buffer.obs[time, env],
        action=buffer.action[time, env],
        true_reward=buffer.true_reward[time, env],
        row=time.astype(jnp.int32),
        env=jnp.broadcast_to(env, time.shape).astype(jnp.int32),
    )


def _draw_flat(key: jax.Array, valid: jax.Array, n: int, low: jax.Array | int = 0) -> jax.Array:
    """n flat indices of ``valid`` (any shape, row-major), uniform over its true entries of rank >= low."""
    cumulative = jnp.cumsum(valid.reshape(-1).astype(jnp.int32))
    count = cumulative[-1]
    low = jnp.clip(jnp.asarray(low, jnp.int32), 0, jnp.maximum(count - 1, 0))
    draws = jax.random.randint(key, (n,), low, jnp.maximum(count, 1))
    flat = jnp.searchsorted(cumulative, draws, side="right")  # The draws-th true entry.
    return jnp.minimum(flat, valid.size - 1)


def sample_row_segments(
    buffer: Any, key: jax.Array, n: int, segment_length: int, episode_length: int, recent_episodes: int
) -> Segments:
    """``pool = "rows"``: n segments uniform (with replacement) among the valid starts of the recent window.

    If no start is valid (too little data) the segments are arbitrary rows.
    """
    valid = valid_starts(buffer, segment_length, episode_length, recent_episodes)
    rows, num_envs = valid.shape
    flat = _draw_flat(key, valid, n)
    start, env = flat // num_envs, flat % num_envs
    index = window_index(buffer, rows)
    time = index[(start[:, None] + jnp.arange(segment_length)) % rows]  # (n, H) absolute rows.
    return _gather(buffer, time, env[:, None])


def episode_ends(buffer: Any, segment_length: int, episode_length: int) -> jax.Array:
    """Which buffer cells (oldest row first) hold the last transition of an episode of >= H steps.

    Returns:
      (T, E) bool over the rows ``window_index(buffer, T)``; only filled rows can be true.
    """
    capacity = buffer.episode_step.shape[0]
    index = window_index(buffer, capacity)
    steps = buffer.episode_step[index]
    flagged = (buffer.terminal[index] + buffer.truncated[index]) > 0
    last = flagged | (steps == episode_length - 1)
    filled = (jnp.arange(capacity) >= capacity - buffer.size)[:, None]
    return last & filled & (steps >= segment_length - 1)


def sample_episode_segments(
    buffer: Any, key: jax.Array, n: int, segment_length: int, episode_length: int, recent_episodes: int
) -> Segments:
    """``pool = "episodes"``: B-Pref's ``get_queries``: n segments from the last complete episodes.

    Each segment picks one of the ``recent_episodes`` most recently completed episodes (by the
    row of their last transition; episodes ending on the same row rank by environment index)
    uniformly with replacement, then a start uniform in ``[0, L - H)`` for an episode of L steps
    (B-Pref: ``np.random.choice(len_traj - size_segment)``, so the last step is never shown).
    Episodes shorter than H are skipped. Before any episode is complete the segments are
    arbitrary rows; ``Config.validate`` makes the first feedback session come after the first episodes.

    Args:
      buffer: the replay buffer (see the module docstring).
      key: PRNG key.
      n: number of segments (static).
      segment_length: H (static).
      episode_length: control steps per episode (static).
      recent_episodes: how many complete episodes are eligible (B-Pref's ``max_size``, 100).

    Returns:
      ``Segments`` of shape (n, H, ...).
    """
    capacity, num_envs = buffer.episode_step.shape
    key_episode, key_start = jax.random.split(key)
    ends = episode_ends(buffer, segment_length, episode_length)
    total = jnp.sum(ends.astype(jnp.int32))
    flat = _draw_flat(key_episode, ends, n, low=total - recent_episodes)
    end, env = flat // num_envs, flat % num_envs  # Window rows, oldest first.
    index = window_index(buffer, capacity)
    length = buffer.episode_step[index[end], env] + 1
    offset = jax.random.randint(key_start, (n,), 0, jnp.maximum(length - segment_length, 1))
    first = end - (length - 1) + offset
    time = index[(first[:, None] + jnp.arange(segment_length)) % capacity]
    return _gather(buffer, time, env[:, None])


def sample_segments(
    buffer: Any,
    key: jax.Array,
    n: int,
    segment_length: int,
    episode_length: int,
    recent_episodes: int,
    pool: str = "rows",
) -> Segments:
    """Cuts n segments of H steps, each inside one episode, from the recent data.

    Args:
      buffer: the replay buffer (see the module docstring).
      key: PRNG key.
      n: number of segments (static).
      segment_length: H (static).
      episode_length: control steps per episode (static).
      recent_episodes: see ``QueryConfig.recent_episodes`` (static).
      pool: ``"episodes"`` (:func:`sample_episode_segments`) or ``"rows"`` (:func:`sample_row_segments`).

    Returns:
      ``Segments`` of shape (n, H, ...).
    """
    _check(pool in ("episodes", "rows"), "query.pool", pool, "episodes, rows")
    sampler = sample_episode_segments if pool == "episodes" else sample_row_segments
    return sampler(buffer, key, n, segment_length, episode_length, recent_episodes)


def sample_pairs(
    buffer: Any,
    key: jax.Array,
    n: int,
    segment_length: int,
    episode_length: int,
    recent_episodes: int,
    pool: str = "rows",
) -> tuple[Segments, Segments]:
    """n independent uniform pairs: ``sample_segments`` of 2n, split into halves.

    Args and Returns: as ``sample_segments``, as a pair ``(seg_a, seg_b)``.
    """
    both = sample_segments(buffer, key, 2 * n, segment_length, episode_length, recent_episodes, pool)
    return jax.tree.map(lambda x: x[:n], both), jax.tree.map(lambda x: x[n:], both)


def disagreement(probs: jax.Array) -> jax.Array:
    """B-Pref's disagreement score: std over ensemble members of the preference probability.

    Args:
      probs: (M, N) member probabilities ``P(seg_b preferred)``.

    Returns:
      (N,) standard deviations.
    """
    return jnp.std(probs, axis=0)


def entropy(probs: jax.Array) -> jax.Array:
    """Entropy (nats) of the ensemble-mean preference probability.

    Args:
      probs: (M, N) member probabilities ``P(seg_b preferred)``.

    Returns:
      (N,) binary entropies of ``mean_m probs``.
    """
    mean = jnp.clip(jnp.mean(probs, axis=0), 1e-7, 1.0 - 1e-7)
    return -(mean * jnp.log(mean) + (1.0 - mean) * jnp.log1p(-mean))


def select_queries(
    cfg: QueryConfig,
    key: jax.Array,
    buffer: Any,
    num_queries: int,
    episode_length: int,
    pref_prob_fn: Callable[[Segments, Segments], jax.Array],
    first_session: bool | jax.Array = False,
) -> tuple[Segments, Segments]:
    """Chooses the pairs to show the teacher.

    ``uniform`` draws ``num_queries`` pairs with ``sample_pairs(buffer, key, num_queries, ...)``.
    ``disagreement`` / ``entropy`` draw ``C = candidate_factor * num_queries`` candidates with
    ``sample_pairs(buffer, key, C, ...)`` and keep the ``num_queries`` with the highest score
    (ties to the earlier candidate). The first feedback session is uniform: the first ``num_queries``
    candidates, which are themselves a uniform sample. ``first_session`` may be a Python bool
    (static) or a traced bool (both scores are computed and one is selected).

    Args:
      cfg: the query settings.
      key: PRNG key, passed unchanged to ``sample_pairs``.
      buffer: the replay buffer.
      num_queries: pairs to return (static).
      episode_length: control steps per episode (static).
      pref_prob_fn: ``(seg_a, seg_b) -> (M, N)`` ensemble member probabilities ``P(seg_b
        preferred)``, e.g. ``functools.partial(reward_model.pref_probs, reward_cfg, params)``.
      first_session: whether this is the first feedback session.

    Returns:
      ``(seg_a, seg_b)`` with ``num_queries`` pairs.

    References:
      Lee, Smith, Abbeel. PEBBLE, ICML 2021 (section 4.2, sampling schemes); B-Pref, 2021.
    """
    sizes = (cfg.segment_length, episode_length, cfg.recent_episodes, cfg.pool)
    uniform_only = cfg.sampling == "uniform" or (isinstance(first_session, bool) and first_session)
    if uniform_only:
        return sample_pairs(buffer, key, num_queries, *sizes)
    num_candidates = cfg.candidate_factor * num_queries
    seg_a, seg_b = sample_pairs(buffer, key, num_candidates, *sizes)
    probs = pref_prob_fn(seg_a, seg_b)
    score = disagreement(probs) if cfg.sampling == "disagreement" else entropy(probs)
    first_come = -jnp.arange(num_candidates, dtype=score.dtype)
    score = jnp.where(first_session, first_come, score)
    _, top = jax.lax.top_k(score, num_queries)
    return jax.tree.map(lambda x: x[top], seg_a), jax.tree.map(lambda x: x[top], seg_b)


def reward_margin(buffer: Any, segment_length: int, episode_length: int, recent_episodes: int) -> jax.Array:
    """The teachers' margin: average true return of a length-H segment in the recent window.

    Equals ``mean episode return * H / episode_length`` for complete episodes; computed as
    ``H * mean true reward`` over the filled rows of the window of ``valid_starts``. (B-Pref
    averages the last 10 training episodes; the query window is used here.)

    Args:
      buffer: the replay buffer.
      segment_length: H.
      episode_length: control steps per episode.
      recent_episodes: see ``QueryConfig.recent_episodes``.

    Returns:
      Scalar margin (0 if nothing is filled).
    """
    rows = window_rows(buffer, segment_length, episode_length, recent_episodes)
    reward = buffer.true_reward[window_index(buffer, rows)]  # (W, E)
    filled = (jnp.arange(rows) >= rows - buffer.size)[:, None]
    total = jnp.sum(jnp.where(filled, reward, 0.0))
    count = jnp.sum(filled) * reward.shape[1]
    return segment_length * total / jnp.maximum(count, 1)
