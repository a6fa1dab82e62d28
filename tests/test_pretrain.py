"""kNN state-entropy reward and running statistics against brute-force NumPy."""

from __future__ import annotations

import dataclasses
import functools

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.preference import pretrain


@flax.struct.dataclass
class FakeBuffer:
    """The fields of replay.py's buffer that pre-training reads."""

    obs: jax.Array
    ptr: jax.Array
    size: jax.Array


def _brute_force_knn(batch, points, k):
    dist = np.sqrt(((batch[:, None, :].astype(np.float64) - points[None, :, :]) ** 2).sum(-1))
    return np.sort(dist, axis=1)[:, k]


@pytest.mark.parametrize("select", ["argmin", "top_k"])
@pytest.mark.parametrize("chunk_size", [16, 103, 1000])
@pytest.mark.parametrize("filled", ["scattered", "prefix"])
def test_knn_reward_equals_brute_force(chunk_size, select, filled):
    rng = np.random.default_rng(0)
    points = rng.normal(size=(103, 5)).astype(np.float32)
    # "prefix": a buffer filling in order, whose later chunks are skipped.
    valid = rng.random(103) < 0.7 if filled == "scattered" else np.arange(103) < 37
    batch = np.concatenate([points[valid][:10], rng.normal(size=(6, 5)).astype(np.float32)])
    knn = jax.jit(pretrain.knn_reward, static_argnums=(3, 4, 5))
    got = np.asarray(knn(batch, points, valid, 3, chunk_size, select))
    np.testing.assert_allclose(got, _brute_force_knn(batch, points[valid], 3), rtol=1e-4, atol=1e-5)
    # Batch observations drawn from the buffer skip themselves (distance 0): rank k + 1, as B-Pref.
    assert np.all(got[:10] > 0)


def test_smallest_equals_sorting_with_ties():
    rng = np.random.default_rng(3)
    values = rng.integers(0, 4, size=(9, 12)).astype(np.float32)  # Many equal entries per row.
    values[0, 5:] = np.inf
    got = np.asarray(jax.jit(pretrain.smallest, static_argnums=1)(values, 6))
    np.testing.assert_array_equal(got, np.sort(values, axis=1)[:, :6])


def test_knn_reward_is_inf_without_enough_valid_points():
    points = np.zeros((8, 2), np.float32)
    valid = np.array([True, True] + [False] * 6)
    got = jax.jit(pretrain.knn_reward, static_argnums=(3, 4))(points[:2], points, valid, 2, 4)
    assert np.all(np.isinf(np.asarray(got)))


def test_running_stats_equal_numpy_over_all_batches():
    rng = np.random.default_rng(1)
    batches = [rng.gamma(2.0, size=n).astype(np.float32) for n in (7, 50, 1, 13)]
    update = jax.jit(pretrain.update)
    stats = pretrain.init_stats()
    np.testing.assert_allclose(np.asarray(pretrain.normalize(stats, batches[0])), batches[0])
    for i, batch in enumerate(batches):
        stats = update(stats, batch)
        seen = np.concatenate(batches[: i + 1]).astype(np.float64)
        np.testing.assert_allclose(float(stats.mean), seen.mean(), rtol=1e-5)
        np.testing.assert_allclose(float(stats.var), seen.var(), rtol=1e-4)
        assert int(stats.count) == seen.size
    scaled = np.asarray(pretrain.normalize(stats, batches[1]))
    np.testing.assert_allclose(scaled, batches[1] / np.concatenate(batches).std(), rtol=1e-4)


def _ring_buffer(num_writes, capacity=12, num_envs=3):
    obs = np.full((capacity, num_envs, 2), np.nan, np.float32)
    written = []
    rng = np.random.default_rng(num_writes)
    for time in range(num_writes):
        obs[time % capacity] = rng.normal(size=(num_envs, 2))
        written.append(time % capacity)
    buffer = FakeBuffer(
        obs=jnp.asarray(np.nan_to_num(obs, nan=0.0)),
        ptr=jnp.asarray(num_writes % capacity, jnp.int32),
        size=jnp.asarray(min(num_writes, capacity), jnp.int32),
    )
    return buffer, sorted(set(written)), obs


@pytest.mark.parametrize("num_writes", [5, 12, 30])
def test_flatten_buffer_obs_marks_exactly_the_written_rows(num_writes):
    buffer, rows, _ = _ring_buffer(num_writes)
    obs, valid = jax.jit(pretrain.flatten_buffer_obs)(buffer)
    expected = np.zeros((12, 3), bool)
    expected[rows] = True
    np.testing.assert_array_equal(np.asarray(valid), expected.reshape(-1))
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(buffer.obs).reshape(36, 2))


def test_intrinsic_reward_is_knn_over_the_updated_std():
    cfg = pretrain.PretrainConfig(k=2, chunk_size=8)
    buffer, rows, obs = _ring_buffer(7)
    points = obs[rows].reshape(-1, 2)
    batch = points[[0, 4, 9, 13]]
    stats = pretrain.update(pretrain.init_stats(), jnp.array([0.5, 1.5, 2.5]))
    reward_fn = jax.jit(functools.partial(pretrain.intrinsic_reward, cfg))
    reward, new_stats = reward_fn(stats, batch, buffer)
    distance = _brute_force_knn(batch, points, 2)
    seen = np.concatenate([[0.5, 1.5, 2.5], distance])
    np.testing.assert_allclose(np.asarray(reward), distance / seen.std(), rtol=1e-4)
    assert int(new_stats.count) == 7


def test_vmap_over_seeds_equals_separate_calls():
    buffers = [_ring_buffer(n)[0] for n in (7, 30)]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *buffers)
    batch = np.random.default_rng(3).normal(size=(2, 5, 2)).astype(np.float32)
    cfg = pretrain.PretrainConfig(k=3, chunk_size=10)
    stats = jax.tree.map(lambda x: jnp.stack([x, x]), pretrain.init_stats())
    fn = functools.partial(pretrain.intrinsic_reward, cfg)
    batched, _ = jax.jit(jax.vmap(fn))(stats, batch, stacked)
    for i in range(2):
        alone, _ = jax.jit(fn)(pretrain.init_stats(), batch[i], buffers[i])
        np.testing.assert_allclose(np.asarray(batched[i]), np.asarray(alone), rtol=1e-6)


@pytest.mark.parametrize("field,value", [("steps", -1), ("k", 0), ("chunk_size", 0)])
def test_validate_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"pretrain.{field}"):
        dataclasses.replace(pretrain.PretrainConfig(), **{field: value}).validate()
    pretrain.PretrainConfig().validate()


class _BPrefRunningMeanStd:
    """NumPy transcription of B-Pref's ``TorchRunningMeanStd`` (BPref f3ece2e ``utils.py:211-247``), in float64."""

    def __init__(self, epsilon=1e-4):
        self.mean, self.var, self.count = 0.0, 1.0, epsilon

    def update(self, x):
        batch_mean, batch_var, batch_count = x.mean(), x.var(ddof=1), x.shape[0]
        delta = batch_mean - self.mean
        tot_count = self.count + batch_count
        new_mean = self.mean + delta + batch_count / tot_count
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / tot_count
        self.mean, self.var, self.count = new_mean, m2 / tot_count, tot_count

    @property
    def std(self):
        return np.sqrt(self.var)


def _drifting_batches(seed=4, sizes=(64, 64, 32, 64, 64, 64)):
    """kNN-like distances whose mean shrinks batch by batch (as the buffer fills)."""
    rng = np.random.default_rng(seed)
    return [rng.gamma(4.0, (3.0 - 0.4 * i) / 4.0, size=n).astype(np.float32) for i, n in enumerate(sizes)]


def test_bpref_running_std_follows_bprefs_formula_not_the_exact_one():
    reference, stats, exact = _BPrefRunningMeanStd(), pretrain.init_stats("bpref"), pretrain.init_stats()
    update_bpref, update = jax.jit(pretrain.update_bpref), jax.jit(pretrain.update)
    for batch in _drifting_batches():
        reference.update(batch.astype(np.float64))
        stats, exact = update_bpref(stats, batch), update(exact, batch)
        np.testing.assert_allclose(float(stats.mean), reference.mean, rtol=1e-5)
        np.testing.assert_allclose(float(stats.var), reference.var, rtol=1e-4)
        np.testing.assert_allclose(float(stats.count), reference.count, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(pretrain.normalize(stats, batch)), batch / reference.std, rtol=1e-4)
    # The exact running std (the `exact` rule) is measurably another number on the same stream.
    assert abs(float(jnp.sqrt(exact.var)) / reference.std - 1.0) > 0.02


@pytest.mark.parametrize("rule", ["exact", "bpref"])
def test_intrinsic_reward_uses_the_configured_running_std(rule):
    cfg = pretrain.PretrainConfig(k=2, chunk_size=8, running_std=rule)
    buffer, rows, obs = _ring_buffer(9)
    points = obs[rows].reshape(-1, 2)
    reward_fn = jax.jit(functools.partial(pretrain.intrinsic_reward, cfg))
    reference, stats, seen = _BPrefRunningMeanStd(), pretrain.init_stats(rule), []
    for batch_rows in ([0, 4, 9, 13], [1, 2, 20, 25, 26], [3, 7]):
        batch = points[batch_rows]
        reward, stats = reward_fn(stats, batch, buffer)
        distance = _brute_force_knn(batch, points, 2)
        reference.update(distance)
        seen.append(distance)
        std = reference.std if rule == "bpref" else np.concatenate(seen).std()
        np.testing.assert_allclose(np.asarray(reward), distance / std, rtol=1e-4)


def test_paper_preset_uses_bprefs_running_std():
    from rebel_jax.config import PRESETS

    assert PRESETS["paper"].pretrain.running_std == "bpref"
    with pytest.raises(ValueError, match="pretrain.running_std"):
        pretrain.PretrainConfig(running_std="torch").validate()
