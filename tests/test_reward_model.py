"""Reward ensemble: Bradley-Terry loss by hand, label store, early-stopping loop, a small learning run."""

from __future__ import annotations

import dataclasses
import functools
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.preference import reward_model as rm
from rebel_jax.preference import reward_train as rt
from rebel_jax.preference.queries import Segments

OBS, ACT, H = 4, 2, 6
TRUE_W = np.array([1.0, -0.5, 0.8, 0.3, 0.6, -0.4], np.float32)
SMALL = rm.RewardConfig(
    ensemble_size=2, hidden=16, depth=2, lr=3e-3, batch_size=32, max_epochs=40, stop_accuracy=0.9, label_capacity=256
)


def _segments(seed, n):
    """Smooth synthetic segments: a random state-action per segment plus small per-step noise."""
    rng = np.random.default_rng(seed)
    obs = (rng.normal(size=(n, 1, OBS)) + 0.2 * rng.normal(size=(n, H, OBS))).astype(np.float32)
    action = np.clip(rng.uniform(-1.0, 1.0, (n, 1, ACT)) + 0.1 * rng.normal(size=(n, H, ACT)), -1, 1)
    action = action.astype(np.float32)
    reward = np.concatenate([obs, action], -1) @ TRUE_W
    return Segments(obs=obs, action=action, true_reward=reward)


def _labelled(seed, n, mistake=0.0):
    """Oracle labels ``P(seg_b preferred)`` (1 if R_b > R_a), flipped with probability ``mistake``."""
    seg_a, seg_b = _segments(2 * seed, n), _segments(2 * seed + 1, n)
    labels = (seg_b.true_reward.sum(1) > seg_a.true_reward.sum(1)).astype(np.float32)
    flip = np.random.default_rng(seed + 1000).random(n) < mistake
    labels = np.where(flip, 1.0 - labels, labels).astype(np.float32)
    return seg_a, seg_b, labels, np.ones(n, np.float32)


_init = jax.jit(rm.init, static_argnums=(0, 2, 3, 4))
_add_labels = jax.jit(rm.add_labels)
_predict = jax.jit(rm.predict, static_argnums=0)
_accuracy = jax.jit(rm.accuracy, static_argnums=0)


def _state_with_labels(cfg, seed, n, mistake=0.0):
    state = _init(cfg, jax.random.key(seed), OBS, ACT, H)
    return _add_labels(state, *_labelled(100 + seed, n, mistake))


def _assert_trees_close(a, b, rtol=1e-5, atol=1e-6):
    chex.assert_trees_all_close(a, b, rtol=rtol, atol=atol)


def test_bt_cross_entropy_hand_values():
    logits = jnp.array([0.0, 2.0, 2.0, 2.0, -1.0])
    labels = jnp.array([1.0, 1.0, 0.0, 0.5, 1.0])
    expected = [
        math.log(2.0),
        math.log(1.0 + math.exp(-2.0)),
        math.log(1.0 + math.exp(2.0)),
        0.5 * (math.log(1.0 + math.exp(-2.0)) + math.log(1.0 + math.exp(2.0))),
        math.log(1.0 + math.exp(1.0)),
    ]
    np.testing.assert_allclose(np.asarray(rm.bt_cross_entropy(logits, labels)), expected, rtol=1e-6)


def _hand_params(scales):
    """depth 1, hidden 2: member m computes r = tanh(scales[m] * obs[0]) for obs[0] >= 0."""
    members = len(scales)
    kernel0 = np.zeros((members, OBS + ACT, 2), np.float32)
    kernel0[:, 0, 0] = scales
    kernel1 = np.zeros((members, 2, 1), np.float32)
    kernel1[:, 0, 0] = 1.0
    return {
        "params": {
            "Dense_0": {"kernel": jnp.asarray(kernel0), "bias": jnp.zeros((members, 2))},
            "Dense_1": {"kernel": jnp.asarray(kernel1), "bias": jnp.zeros((members, 1))},
        }
    }


def test_bt_loss_equals_hand_computation_with_soft_and_masked_pairs():
    cfg = rm.RewardConfig(ensemble_size=2, hidden=2, depth=1)
    scales = [0.5, 2.0]
    params = _hand_params(scales)
    rng = np.random.default_rng(0)
    members, batch = 2, 4
    obs_a = rng.uniform(0, 1, (members, batch, 3, OBS)).astype(np.float32)
    obs_b = rng.uniform(0, 1, (members, batch, 3, OBS)).astype(np.float32)
    act = np.zeros((members, batch, 3, ACT), np.float32)
    labels = np.array([[1.0, 0.0, 0.5, 1.0], [0.0, 0.5, 1.0, 1.0]], np.float32)
    weight = np.array([[1.0, 1.0, 1.0, 0.0], [1.0, 1.0, 1.0, 0.0]], np.float32)
    a, b = rm.Steps(jnp.asarray(obs_a), jnp.asarray(act)), rm.Steps(jnp.asarray(obs_b), jnp.asarray(act))
    pref = rm.PrefBatch(a, b, jnp.asarray(labels), jnp.asarray(weight), members=jnp.arange(members))
    pref = jax.jit(rm.with_rewards, static_argnums=0)(cfg, params, pref)
    loss, metrics = jax.jit(rm.bt_loss(cfg))(params, pref, jax.random.key(0))

    expected, correct, hard = 0.0, 0, 0
    for m in range(members):
        total = 0.0
        for i in range(3):  # The fourth pair has weight 0.
            ret_a = sum(math.tanh(scales[m] * float(obs_a[m, i, t, 0])) for t in range(3))
            ret_b = sum(math.tanh(scales[m] * float(obs_b[m, i, t, 0])) for t in range(3))
            p_b = math.exp(ret_b) / (math.exp(ret_a) + math.exp(ret_b))
            y = float(labels[m, i])
            total += -(y * math.log(p_b) + (1 - y) * math.log(1 - p_b))
            if y != 0.5:
                hard += 1
                correct += int((ret_b > ret_a) == (y == 1.0))
        expected += total / 3
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["bt_accuracy"]), correct / hard, rtol=1e-6)


def test_total_loss_sums_terms_and_merges_metrics():
    cfg = SMALL
    state = _state_with_labels(cfg, 0, 40)
    minibatch = jax.jit(rt._minibatch, static_argnums=3)
    pref = minibatch(state.data, jnp.tile(jnp.arange(64), (2, 1)), jnp.asarray(0), 32)
    pref = jax.jit(rm.with_rewards, static_argnums=0)(cfg, state.params, pref)

    def extra(params, batch, key):
        del batch, key  # Unused.
        value = 0.25 * jnp.mean(rm.predict(cfg, params, jnp.ones(OBS), jnp.ones(ACT)))
        return value, {"extra": value}

    bt, _ = jax.jit(rm.bt_loss(cfg))(state.params, pref, jax.random.key(0))
    total, metrics = jax.jit(rm.total_loss((rm.bt_loss(cfg), extra)))(state.params, pref, jax.random.key(0))
    np.testing.assert_allclose(float(total), float(bt) + float(metrics["extra"]), rtol=1e-6)
    assert set(metrics) == {"bt_loss", "bt_accuracy", "extra", "loss"}


def test_add_labels_drops_skipped_pairs_and_wraps_like_a_ring():
    cfg = dataclasses.replace(SMALL, label_capacity=5)
    state = _init(cfg, jax.random.key(0), OBS, ACT, H)
    ring = []  # Python reference: list of (obs_a[0, 0], label), oldest overwritten first.
    ptr = 0
    for step, mask in enumerate([[1, 0, 1, 1], [1, 1, 1, 1], [0, 0, 0, 0], [0, 1, 0, 1]]):
        seg_a, seg_b, labels, _ = _labelled(step, 4)
        state = _add_labels(state, seg_a, seg_b, labels, np.asarray(mask, np.float32))
        for i in np.flatnonzero(mask):
            item = (float(seg_a.obs[i, 0, 0]), float(seg_b.action[i, 1, 1]), float(labels[i]))
            if len(ring) < 5:
                ring.append(item)
            else:
                ring[ptr] = item
            ptr = (ptr + 1) % 5
        assert int(state.data.count) == len(ring) and int(state.data.ptr) == ptr
        stored = [
            (float(state.data.a.obs[j, 0, 0]), float(state.data.b.action[j, 1, 1]), float(state.data.labels[j]))
            for j in range(len(ring))
        ]
        assert stored == ring


def test_accuracy_matches_numpy():
    state = _state_with_labels(SMALL, 1, 8)
    seg_a, seg_b, labels, mask = _labelled(11, 50)
    labels[:5] = 0.5
    mask[5:10] = 0.0
    got = _accuracy(SMALL, state.params, seg_a, seg_b, labels, mask)
    rewards_a = np.asarray(_predict(SMALL, state.params, seg_a.obs, seg_a.action)).sum(-1)
    rewards_b = np.asarray(_predict(SMALL, state.params, seg_b.obs, seg_b.action)).sum(-1)
    counted = (np.asarray(labels) != 0.5) & (np.asarray(mask) == 1)
    right = ((rewards_b > rewards_a) == (np.asarray(labels) == 1.0))[:, counted]
    np.testing.assert_allclose(float(got), right.mean(), rtol=1e-6)


def _python_loop(cfg, state, key):
    epoch_fn = jax.jit(rt.train_epoch, static_argnums=0)
    for epoch in range(cfg.max_epochs):
        state, metrics = epoch_fn(cfg, state, jax.random.fold_in(key, epoch))
        if float(metrics["accuracy"]) > cfg.stop_accuracy:
            return state, epoch + 1
    return state, cfg.max_epochs


def test_early_stopping_stops_where_a_python_loop_does():
    state = _state_with_labels(SMALL, 2, 100)
    key = jax.random.key(3)
    trained, metrics = jax.jit(rt.train, static_argnums=0)(SMALL, state, key)
    expected_state, expected_epochs = _python_loop(SMALL, state, key)
    assert 1 < expected_epochs < SMALL.max_epochs  # Stops early, but not at once.
    assert int(metrics["epochs"]) == expected_epochs
    assert float(metrics["train_accuracy"]) > SMALL.stop_accuracy
    _assert_trees_close(trained.params, expected_state.params)
    _assert_trees_close(trained.opt_state, expected_state.opt_state)


def test_vmap_over_seeds_with_different_stop_epochs_equals_each_run():
    states = [_state_with_labels(SMALL, 4, 100), _state_with_labels(SMALL, 5, 100, mistake=0.2)]
    keys = jax.random.split(jax.random.key(6), 2)
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *states)
    train = functools.partial(rt.train, SMALL)
    batched, batched_metrics = jax.jit(jax.vmap(train))(stacked, keys)
    epochs = []
    for i in range(2):
        alone, metrics = jax.jit(train)(states[i], keys[i])
        epochs.append(int(metrics["epochs"]))
        assert int(batched_metrics["epochs"][i]) == epochs[-1]
        _assert_trees_close(jax.tree.map(lambda x, i=i: x[i], batched.params), alone.params)
    assert epochs[0] != epochs[1]


def test_no_labels_no_training():
    state = _init(SMALL, jax.random.key(0), OBS, ACT, H)
    trained, metrics = jax.jit(rt.train, static_argnums=0)(SMALL, state, jax.random.key(1))
    assert int(metrics["epochs"]) == 0
    _assert_trees_close(trained.params, state.params, rtol=0, atol=0)


def test_learns_a_linear_reward_from_an_oracle():
    cfg = dataclasses.replace(SMALL, ensemble_size=3, hidden=32, stop_accuracy=0.99, max_epochs=60, label_capacity=400)
    state = _state_with_labels(cfg, 7, 400)
    state, metrics = jax.jit(rt.train, static_argnums=0)(cfg, state, jax.random.key(8))
    seg_a, seg_b, labels, mask = _labelled(9, 500)
    held_out = float(_accuracy(cfg, state.params, seg_a, seg_b, labels, mask))
    assert held_out > 0.9, held_out
    seg = _segments(10, 200)
    learned = np.asarray(jax.jit(rm.mean_reward, static_argnums=0)(cfg, state.params, seg.obs, seg.action)).ravel()
    corr = np.corrcoef(learned, np.asarray(seg.true_reward).ravel())[0, 1]
    assert corr > 0.8, corr
    chex.assert_shape(_predict(cfg, state.params, seg.obs, seg.action), (cfg.ensemble_size, 200, H))


def test_pref_probs_are_sigmoid_of_return_differences():
    state = _state_with_labels(SMALL, 12, 4)
    seg_a, seg_b = _segments(13, 5), _segments(14, 5)
    probs = np.asarray(jax.jit(rm.pref_probs, static_argnums=0)(SMALL, state.params, seg_a, seg_b))
    ret_a = np.asarray(_predict(SMALL, state.params, seg_a.obs, seg_a.action), np.float64).sum(-1)
    ret_b = np.asarray(_predict(SMALL, state.params, seg_b.obs, seg_b.action), np.float64).sum(-1)
    np.testing.assert_allclose(probs, 1 / (1 + np.exp(ret_a - ret_b)), rtol=1e-5)


@pytest.mark.parametrize(
    "field,value",
    [
        ("ensemble_size", 0),
        ("lr", 0.0),
        ("batch_size", 0),
        ("stop_accuracy", 1.5),
        ("label_capacity", 0),
        ("output", "relu"),
    ],
)
def test_validate_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"reward.{field}"):
        dataclasses.replace(rm.RewardConfig(), **{field: value}).validate()
    rm.RewardConfig().validate()


@pytest.mark.parametrize("crop", [0, 2])
def test_one_bt_loss_reads_the_batchs_rewards_alike_for_state_and_frame_segments(crop):
    """``bt_loss`` is one term for both networks: on a batch of state segments and on one of frame segments with
    the same members' per-step rewards it gives the same loss, and that loss is NumPy's soft cross-entropy of the
    (cropped) return differences, each member's weighted mean, summed over members."""
    from rebel_jax.preference.pixel_reward import PixelRewardConfig, SegmentFrames  # noqa: PLC0415

    rng = np.random.default_rng(3)
    members, pairs, steps = 3, 5, 8
    rewards_a, rewards_b = (jnp.asarray(rng.uniform(-1, 1, (members, pairs, steps)), jnp.float32) for _ in "ab")
    labels = jnp.asarray(rng.choice([0.0, 0.5, 1.0], (members, pairs)), jnp.float32)
    weight = jnp.asarray(rng.uniform(size=(members, pairs)) < 0.8, jnp.float32).at[:, 0].set(1.0)
    states = rm.Steps(jnp.zeros((members, pairs, steps, OBS)), jnp.zeros((members, pairs, steps, ACT)))
    frames = SegmentFrames(
        jnp.zeros((members, pairs, steps + 2, 4, 4, 3), jnp.uint8), jnp.zeros((members, pairs, steps, 1))
    )
    key, losses = jax.random.key(4), []
    for cfg, segments in ((rm.RewardConfig(ensemble_size=members), states), (PixelRewardConfig(), frames)):
        batch = rm.PrefBatch(segments, segments, labels, weight, jnp.arange(members), rewards_a, rewards_b)
        losses.append(jax.jit(rm.bt_loss(cfg, crop))(None, batch, key))
    chex.assert_trees_all_equal(*losses)
    masks = np.ones((2, members, pairs, steps))
    if crop:  # the term's draws: one crop length per pair, a start per segment (``crop_masks``)
        masks = np.stack(rm.crop_masks(key, (members, pairs), steps, crop))
        assert np.any(masks.sum(-1) < steps)
    logits = (np.asarray(rewards_b, np.float64) * masks[1]).sum(-1) - (
        np.asarray(rewards_a, np.float64) * masks[0]
    ).sum(-1)
    y, w = np.asarray(labels, np.float64), np.asarray(weight, np.float64)
    ce = y * np.log1p(np.exp(-logits)) + (1 - y) * np.log1p(np.exp(logits))
    expected = np.sum((ce * w).sum(1) / w.sum(1))
    np.testing.assert_allclose(float(losses[0][0]), expected, rtol=1e-5)
