"""Unsupervised pre-training reward: state entropy by k-nearest neighbours (PEBBLE; rll-research/BPref@f3ece2e).

During pre-training the critic target uses an intrinsic reward instead of the task reward:
for every observation of the SAC batch, its distance to its k-th nearest neighbour among the
replay buffer's observations (a particle estimate of state entropy, Liu & Abbeel 2021 / PEBBLE
eq. 3), divided by a running standard deviation of these distances. B-Pref takes the
``(k+1)``-th smallest distance (``torch.kthvalue(dists, k + 1)``) because each batch
observation is itself in the buffer at distance 0; ``knn_reward`` does the same.

Distances are computed chunk by chunk over the buffer with a running top-(k+1), so memory is
O(N * chunk) whatever the buffer size; chunks past the last filled row are skipped.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import flax.struct
import jax
import jax.numpy as jnp

from rebel_jax.core.errors import check as _check


@dataclasses.dataclass(frozen=True)
class PretrainConfig:
    """Unsupervised state-entropy exploration (PEBBLE's pre-training phase)."""

    steps: int = 9_000
    """Environment steps of unsupervised pre-training after the seed steps (B-Pref: 9,000)."""
    k: int = 5
    """Neighbour rank: the reward is the distance to the k-th nearest other buffer observation (B-Pref: 5)."""
    chunk_size: int = 4096
    """Buffer observations compared per chunk; bounds memory to batch_size x chunk_size distances."""
    reset_updates: int = 100
    """SAC updates on the relabelled buffer right after the critic is re-initialised at the first
    feedback session (B-Pref's ``reset_update``, 100: ``agent.update_after_reset`` in
    ``train_PEBBLE.py``). 0 skips them (this project's earlier rule)."""
    running_std: Literal["exact", "bpref"] = "exact"
    """The running std the kNN distances are divided by: ``exact``, the standard deviation of every
    distance seen so far (Chan's parallel update); ``bpref``, B-Pref's ``TorchRunningMeanStd`` as
    written (BPref f3ece2e ``utils.py:211-247``): count starts at 1e-4 with variance 1, batch
    variances are unbiased, and the mean update reads ``mean + delta + n / total`` (not ``delta *
    n / total``), so the variance misses the slow drift of the distances and carries an early
    transient (the ``paper`` preset's choice; see notes/bpref_audit.md)."""

    def validate(self) -> None:
        _check(self.steps >= 0, "pretrain.steps", self.steps, ">= 0")
        _check(self.reset_updates >= 0, "pretrain.reset_updates", self.reset_updates, ">= 0")
        _check(self.k >= 1, "pretrain.k", self.k, ">= 1")
        _check(self.chunk_size >= 1, "pretrain.chunk_size", self.chunk_size, ">= 1")
        _check(self.running_std in ("exact", "bpref"), "pretrain.running_std", self.running_std, "exact, bpref")


@flax.struct.dataclass
class RunningStats:
    """Running mean and variance of a scalar stream (parallel/Chan update, as baselines' RunningMeanStd)."""

    mean: jax.Array
    """Mean of everything seen so far."""
    var: jax.Array
    """Population variance of everything seen so far (1 before any data)."""
    count: jax.Array
    """Number of values seen."""


BPREF_COUNT_EPSILON = 1e-4
"""The count B-Pref's ``TorchRunningMeanStd`` starts from (``epsilon=1e-4``, BPref ``utils.py:212-215``)."""


def init_stats(rule: str = "exact") -> RunningStats:
    """Empty statistics: mean 0, variance 1 (``normalize`` is the identity until updated).

    Args:
      rule: ``PretrainConfig.running_std``; ``exact`` starts at count 0, ``bpref`` at count 1e-4 as
        B-Pref's ``TorchRunningMeanStd(epsilon=1e-4)`` (BPref ``utils.py:212-215``).
    """
    count = BPREF_COUNT_EPSILON if rule == "bpref" else 0.0
    return RunningStats(mean=jnp.zeros(()), var=jnp.ones(()), count=jnp.full((), count, jnp.float32))


def update(stats: RunningStats, values: jax.Array) -> RunningStats:
    """Merges a batch of values into the running statistics (Chan et al.'s parallel algorithm).

    Args:
      stats: statistics so far.
      values: (N,) new values.

    Returns:
      Statistics of all values seen, exactly the mean and population variance of their concatenation.
    """
    batch_count = jnp.asarray(values.size, stats.count.dtype)
    batch_mean = jnp.mean(values)
    batch_var = jnp.var(values)
    total = stats.count + batch_count
    delta = batch_mean - stats.mean
    mean = stats.mean + delta * batch_count / total
    m2 = stats.var * stats.count + batch_var * batch_count + delta**2 * stats.count * batch_count / total
    return RunningStats(mean=mean, var=m2 / total, count=total)


def update_bpref(stats: RunningStats, values: jax.Array) -> RunningStats:
    """B-Pref's running statistics update, formula for formula (including its mean update).

    BPref f3ece2e ``utils.py:217-247`` (``TorchRunningMeanStd.update`` and
    ``update_mean_var_count_from_moments``): the batch variance is ``torch.var``'s unbiased one,
    and the new mean is ``mean + delta + n / total``. The variance update is Chan's, but with that
    mean ``delta`` is nearly the difference of consecutive batch means, so the variance tracks the
    batches' own spread rather than the spread of everything seen.

    Args:
      stats: statistics so far (``init_stats("bpref")`` to start as B-Pref).
      values: (N,) new values, N >= 2.

    Returns:
      The statistics after B-Pref's update.
    """
    batch_count = jnp.asarray(values.size, stats.count.dtype)
    batch_mean = jnp.mean(values)
    batch_var = jnp.var(values, ddof=1)  # torch.var (utils.py:220) is unbiased.
    delta = batch_mean - stats.mean  # utils.py:237
    total = stats.count + batch_count  # utils.py:238
    mean = stats.mean + delta + batch_count / total  # utils.py:240, as written.
    m2 = stats.var * stats.count + batch_var * batch_count + delta**2 * stats.count * batch_count / total  # :241-243
    return RunningStats(mean=mean, var=m2 / total, count=total)


def normalize(stats: RunningStats, values: jax.Array) -> jax.Array:
    """Divides by the running standard deviation (not centred, as B-Pref's intrinsic reward).

    Args:
      stats: running statistics.
      values: values to scale.

    Returns:
      ``values / sqrt(var)`` (std floored at 1e-8).
    """
    return values / jnp.maximum(jnp.sqrt(stats.var), 1e-8)


def _sq_distances(batch_obs: jax.Array, chunk: jax.Array) -> jax.Array:
    """Squared Euclidean distances (N, C), with a full-precision matmul (TF32 would blur them)."""
    cross = jnp.matmul(batch_obs, chunk.T, precision=jax.lax.Precision.HIGHEST)
    sq = jnp.sum(batch_obs**2, axis=1)[:, None] + jnp.sum(chunk**2, axis=1)[None, :] - 2.0 * cross
    return jnp.maximum(sq, 0.0)


def smallest(values: jax.Array, rank: int) -> jax.Array:
    """The ``rank`` smallest entries of each row, ascending: ``-lax.top_k(-values, rank)[0]``, equal entries
    counted apart, by ``rank`` passes of ``argmin``, each masking the column it took for the next.

    On a GPU ``lax.top_k`` over a few thousand columns is far slower than a few row reductions; on a CPU it is
    the faster (BENCHMARKS.md, "The kNN reward of pre-training").

    Args:
      values: (N, C) with ``C >= rank``.
      rank: how many (static).

    Returns:
      (N, rank).
    """
    columns = jnp.arange(values.shape[1])[None, :]
    out = []
    for _ in range(rank):
        out.append(jnp.min(values, axis=1))
        values = jnp.where(columns == jnp.argmin(values, axis=1)[:, None], jnp.inf, values)
    return jnp.stack(out, axis=1)


def knn_reward(
    batch_obs: jax.Array,
    buffer_obs: jax.Array,
    valid_mask: jax.Array,
    k: int,
    chunk_size: int = 4096,
    select: Literal["argmin", "top_k"] | None = None,
) -> jax.Array:
    """Distance of each batch observation to its k-th nearest neighbour in the buffer (B-Pref).

    Returns the ``(k+1)``-th smallest distance to the valid buffer observations: the nearest
    one is the observation itself when the batch was sampled from the buffer.

    Args:
      batch_obs: (N, D) observations to reward.
      buffer_obs: (P, D) buffer observations.
      valid_mask: (P,) bool, True for filled buffer rows.
      k: neighbour rank (static).
      chunk_size: buffer observations per chunk (static).
      select: how each chunk's smallest distances are found (static): ``"argmin"`` (:func:`smallest`) or
        ``"top_k"`` (``lax.top_k``); the same numbers either way. Default: ``top_k`` on a CPU, whose ``top_k`` is a
        partial sort and the faster there, else ``argmin``.

    Returns:
      (N,) distances; ``inf`` if fewer than k+1 buffer observations are valid.

    References:
      Liu & Abbeel, APT, 2021; Lee, Smith, Abbeel, PEBBLE, ICML 2021, eq. (3).
    """
    if select is None:
        select = "top_k" if jax.default_backend() == "cpu" else "argmin"
    num, rank = buffer_obs.shape[0], k + 1
    chunk = min(chunk_size, num)

    def body(index, best):
        start = jnp.minimum(index * chunk, num - chunk)  # The last chunk overlaps its predecessor...
        position = start + jnp.arange(chunk)
        fresh = position >= index * chunk  # ...whose rows are masked out here.
        rows = jax.lax.dynamic_slice_in_dim(buffer_obs, start, chunk)
        valid = jax.lax.dynamic_slice_in_dim(valid_mask, start, chunk) & fresh
        sq = jnp.where(valid[None, :], _sq_distances(batch_obs, rows), jnp.inf)
        merged = jnp.concatenate([best, sq], axis=1)
        return smallest(merged, rank) if select == "argmin" else -jax.lax.top_k(-merged, rank)[0]

    # The chunks up to the last valid row: a pre-training buffer fills in order, so most of the run
    # reads only its first chunks (every chunk once the buffer is full).
    last = jnp.max(jnp.where(valid_mask, jnp.arange(num), -1))
    best = jnp.full((batch_obs.shape[0], rank), jnp.inf, batch_obs.dtype)
    best = jax.lax.fori_loop(0, (last + chunk) // chunk, body, best)
    return jnp.sqrt(best[:, k])


def flatten_buffer_obs(buffer: Any) -> tuple[jax.Array, jax.Array]:
    """The buffer's observations as one (T*E, D) array and their validity.

    Args:
      buffer: replay buffer with ``obs`` (T, E, D), ``ptr`` and ``size`` (filled rows, written
        in a ring ending at ``ptr - 1``).

    Returns:
      obs: (T*E, D); valid: (T*E,) bool, True for rows among the ``size`` most recent.
    """
    capacity, num_envs = buffer.obs.shape[:2]
    age = (buffer.ptr - 1 - jnp.arange(capacity)) % capacity  # 0 for the newest row.
    valid = jnp.repeat(age < buffer.size, num_envs)
    return buffer.obs.reshape(capacity * num_envs, -1), valid


def intrinsic_reward(
    cfg: PretrainConfig, stats: RunningStats, batch_obs: jax.Array, buffer: Any
) -> tuple[jax.Array, RunningStats]:
    """PEBBLE's pre-training reward for a SAC batch: kNN distance over its running std.

    The statistics are updated with this batch first, then used to scale it (B-Pref's order,
    ``agent/sac.py:176-177``), by ``update`` or B-Pref's ``update_bpref`` (``cfg.running_std``).

    Args:
      cfg: the pre-training settings.
      stats: running statistics of past kNN distances.
      batch_obs: (N, D) observations of the SAC batch.
      buffer: the replay buffer (see ``flatten_buffer_obs``).

    Returns:
      (N,) rewards and the updated statistics.
    """
    rewards, stats = intrinsic_rewards(cfg, stats, batch_obs[None], buffer)
    return rewards[0], stats


def intrinsic_rewards(
    cfg: PretrainConfig, stats: RunningStats, batches_obs: jax.Array, buffer: Any
) -> tuple[jax.Array, RunningStats]:
    """:func:`intrinsic_reward` of several SAC batches in order: one kNN search for all their observations, then
    batch by batch the statistics updated and the batch scaled (each batch's statistics include the ones before).

    Args:
      batches_obs: (M, N, D) the observations of M batches.

    Returns:
      (M, N) rewards and the statistics after the last batch.
    """
    obs, valid = flatten_buffer_obs(buffer)
    batches, size = batches_obs.shape[:2]
    distances = knn_reward(batches_obs.reshape(batches * size, -1), obs, valid, cfg.k, cfg.chunk_size)

    def scale(stats, distance):
        stats = update_bpref(stats, distance) if cfg.running_std == "bpref" else update(stats, distance)
        return stats, normalize(stats, distance)

    stats, rewards = jax.lax.scan(scale, stats, distances.reshape(batches, size))
    return rewards, stats
