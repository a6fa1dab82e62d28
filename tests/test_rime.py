"""RIME (methods/rime.py) against NumPy transcriptions of its original (CJReinforce/RIME_ICML2024@4ad03f4), and one
tiny run on the probe task."""

from __future__ import annotations

import dataclasses
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_preference_train import MICRO_PEBBLE

from rebel_jax.agents import replay
from rebel_jax.methods.rime import (
    RIME,
    RIMEConfig,
    init_rime_state,
    select,
    selection_losses,
    training_store,
    update_stats,
    warmup_factor,
)
from rebel_jax.preference import pretrain, reward_model
from rebel_jax.preference.reward_model import PairStore, RewardConfig
from rebel_jax.train import Trainer, compiled, seed_keys


def original_selection(returns_a, returns_b, labels, x, var, update_step, rime: RIMEConfig):
    """reward_model_RIME.py:50-51, 60-99, 107 in NumPy: the CE of the ensemble-mean softmax, the two thresholds,
    the trusted and flipped indices and the training index (trusted then flipped)."""
    logits = np.stack([returns_a, returns_b], -1).astype(np.float64)  # (M, N, 2)
    p = np.exp(logits - logits.max(-1, keepdims=True))
    p = (p / p.sum(-1, keepdims=True)).mean(0)
    target = np.eye(2)[labels.astype(int)]
    kl = (-target * np.log(p)).sum(1)
    baseline = -np.log(x + 1e-8) + rime.alpha * x
    beta = max(rime.beta_min, -(rime.beta_init - rime.beta_min) / rime.decay_epochs * update_step + rime.beta_init)
    threshold = baseline + min(beta * var, 3.0)
    trusted, flipped = kl < threshold, kl > -np.log(rime.flip_tau)
    train_idx = np.concatenate([np.where(trusted)[0], np.where(flipped)[0]])
    return kl, threshold, trusted, flipped, train_idx


@pytest.mark.parametrize("x, var, update_step", [(0.0, 1.0, 0), (0.8, 0.4, 30), (2.5, 2.0, 100)])
def test_selection_matches_the_original(x, var, update_step):
    rime, rng = RIMEConfig(), np.random.default_rng(update_step)
    members, capacity, count = 3, 64, 50
    shared = rng.normal(0, 8, (2, 1, capacity))  # members that mostly agree, some pairs far apart
    returns_a, returns_b = (shared + rng.normal(0, 1, (2, members, capacity))).astype(np.float32)
    labels = rng.integers(0, 2, capacity).astype(np.float32)
    kl, threshold, trusted, flipped, train_idx = original_selection(
        returns_a[:, :count], returns_b[:, :count], labels[:count], x, var, update_step, rime
    )
    state = init_rime_state().replace(kl_max=jnp.float32(x), kl_var=jnp.float32(var), epochs=jnp.int32(update_step))
    ce = selection_losses(jnp.asarray(returns_b - returns_a), jnp.asarray(labels))
    valid = jnp.arange(capacity) < count
    got_trusted, got_flipped, tau = select(rime, state, ce, valid)
    np.testing.assert_allclose(np.asarray(ce)[:count], kl, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(float(tau), threshold, rtol=1e-5)
    clear = np.abs(kl - threshold) > 1e-3  # away from the bound, where float32 and float64 agree
    np.testing.assert_array_equal(np.asarray(got_trusted)[:count][clear], trusted[clear])
    np.testing.assert_array_equal(np.asarray(got_flipped)[:count], flipped)
    assert not np.any(np.asarray(got_trusted | got_flipped)[count:])  # empty slots never chosen
    assert flipped.any() and trusted.any()  # the data exercise both rules
    # The epoch's training set: the original's train_idx (duplicates included), each with its flipped label.
    flipped_labels = jnp.where(got_flipped, 1.0 - labels, labels)
    slots, labels_in = jnp.arange(capacity), jnp.asarray(labels)
    store = PairStore(a=slots, b=slots, labels=labels_in, ptr=jnp.int32(0), count=jnp.int32(count))
    packed = training_store(store, flipped_labels, got_trusted, got_flipped)
    if clear.all():
        assert int(packed.count) == len(train_idx)
        np.testing.assert_array_equal(np.asarray(packed.a)[: len(train_idx)], train_idx)
        original_labels = np.where(flipped, 1 - labels[:count], labels[:count])
        np.testing.assert_array_equal(np.asarray(packed.labels)[: len(train_idx)], original_labels[train_idx])


class OriginalRunningMeanStd:
    """utils.py:195-227, ``RunningMeanStd(mode='fixed', lr=0.1)`` as RIME makes it (reward_model_RIME.py:35)."""

    def __init__(self):
        self.mean, self.var, self.max, self.count, self.lr = 0, 1.0, 0, 0, 0.1

    def update(self, data):
        batch_mean, batch_var, batch_count = np.mean(data), np.var(data), len(data)
        delta, total = batch_mean - self.mean, self.count + batch_count
        self.mean, self.max = self.mean + delta * self.lr, self.max + (np.max(data) - self.max) * self.lr
        m2 = self.var * self.count + batch_var * batch_count + delta**2 * self.count * batch_count / total
        self.var, self.count = m2 / total, total


def test_stats_update_matches_the_original():
    rime, rng = RIMEConfig(), np.random.default_rng(1)
    reference, state = OriginalRunningMeanStd(), init_rime_state()
    for step in range(6):
        ce = rng.exponential(0.5, 40).astype(np.float32)
        trusted = rng.random(40) < (0.0 if step == 3 else 0.7)  # step 3: none trusted, the statistics unchanged
        state = update_stats(rime, state, jnp.asarray(ce), jnp.asarray(trusted))
        if trusted.any():
            reference.update(ce[trusted].astype(np.float64))
        got = [float(state.kl_mean), float(state.kl_var), float(state.kl_max), float(state.kl_count)]
        np.testing.assert_allclose(got, [reference.mean, reference.var, reference.max, reference.count], rtol=1e-5)


def test_lr_warmup_is_the_constant_schedule_with_warmup():
    """transformers' ``get_constant_schedule_with_warmup`` lambda, stepped once per reward epoch from 0."""
    for warmup in (0, 1, 50):
        original = [float(s) / float(max(1.0, warmup)) if s < warmup else 1.0 for s in range(80)]
        np.testing.assert_allclose(np.asarray(warmup_factor(jnp.arange(80), warmup)), original, rtol=1e-6)


def _pretrain_inputs(warm_steps: int):
    rcfg = RewardConfig(hidden=16, depth=2)
    cfg = dataclasses.replace(MICRO_PEBBLE, algo="rime", rime=RIMEConfig(warm_steps=warm_steps))
    trainer = types.SimpleNamespace(cfg=cfg, reward_cfg=rcfg, num_train=1)
    trainer.reward_optimizer = RIME().reward_optimizer(trainer)
    rng = np.random.default_rng(2)
    ent = rng.gamma(2.0, 0.3, (1, 32)).astype(np.float32)
    stats = pretrain.RunningStats(mean=jnp.float32(0.7), var=jnp.float32(0.09), count=jnp.float32(500.0))
    obs, action = rng.normal(size=(1, 32, 4)).astype(np.float32), rng.normal(size=(1, 32, 2)).astype(np.float32)
    batches = replay.Transition(*map(jnp.asarray, (obs, action, ent / 0.3, obs, np.ones((1, 32), np.float32))))
    reward = reward_model.init(rcfg, jax.random.key(0), 4, 2, 8, trainer.reward_optimizer)
    method = init_rime_state().replace(ent_min=jnp.float32(0.2), ent_max=jnp.float32(0.9))
    ts = types.SimpleNamespace(entropy_stats=stats, method=method, reward=reward)
    return trainer, ts, batches, ent


def test_warm_start_target_and_intrinsic_reward():
    """train_RIME.py:326-334 (target, members' MSE summed) and agent/sac_RIME.py:180-197 (min/max, SAC's reward)."""
    trainer, ts, batches, ent = _pretrain_inputs(warm_steps=1)
    out, reward, state, metrics = RIME().pretrain_step(trainer, ts, batches, jax.random.key(1))
    mean, std = 0.7, 0.3
    low, high = min(0.2, ent.min()), max(0.9, ent.max())
    target = (ent - mean) / std / np.abs((np.array([low, high]) - mean) / std).max()
    pred = np.asarray(reward_model.predict(trainer.reward_cfg, ts.reward.params, batches.obs[0], batches.action[0]))
    np.testing.assert_allclose([float(state.ent_min), float(state.ent_max)], [low, high], rtol=1e-6)
    np.testing.assert_allclose(float(metrics["warm_target"]), target.mean(), rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(float(metrics["warm_loss"]), ((pred - target[0]) ** 2).mean(-1).sum(), rtol=1e-4)
    np.testing.assert_allclose(np.asarray(out.reward), np.clip((ent - mean) / (3 * std), -1, 1), rtol=1e-5, atol=1e-6)
    assert not jax.tree.all(jax.tree.map(jnp.array_equal, reward.params, ts.reward.params))  # one step taken
    _, unchanged, _, _ = RIME().pretrain_step(*_pretrain_inputs(warm_steps=0)[:3], jax.random.key(1))
    assert jax.tree.all(jax.tree.map(jnp.array_equal, unchanged.params, ts.reward.params))


@pytest.fixture(scope="module")
def rime_run():
    """Two seeds, 4 rounds: two of pre-training, then a session at each of rounds 2 and 3."""
    cfg = dataclasses.replace(
        MICRO_PEBBLE,
        algo="rime",
        train=dataclasses.replace(MICRO_PEBBLE.train, total_steps=160),
        reward=dataclasses.replace(MICRO_PEBBLE.reward, max_epochs=4),
        rime=RIMEConfig(warm_steps=1, least_epochs=1, warmup_epochs=3),
    ).validate()
    trainer = Trainer(cfg)
    init, round_fn, _ = compiled(trainer)
    state = init(seed_keys(0, 2))
    metrics = []
    for r in range(cfg.train.num_rounds):
        state, m = round_fn(state, jnp.int32(r))
        metrics.append(jax.device_get(m))
    return trainer, state, metrics


def test_rime_end_to_end(rime_run):
    trainer, state, metrics = rime_run
    rime, lr = trainer.cfg.rime, trainer.reward_cfg.lr
    sessions = [bool(np.all(m["session"] == 1.0)) for m in metrics]
    assert sessions == [False, False, True, True]
    before = np.zeros(2)
    for m, session in zip(metrics, sessions, strict=True):
        own = ("trusted", "flipped", "tau_lower", "lr")
        assert all(np.all(np.isfinite(m[f"rime/{k}"]) == session) for k in own)
        assert np.all(np.isfinite(m["rime/warm_loss"]) != session)  # the warm start in the pre-training rounds
        if session:  # the last epoch's lr: the warm-up's factor at the epochs run before it
            last = before + m["reward_epochs"] - 1
            expected = [lr * (s / rime.warmup_epochs if s < rime.warmup_epochs else 1.0) for s in last]
            np.testing.assert_allclose(m["rime/lr"], expected, rtol=1e-6)
            before += m["reward_epochs"]
    method = jax.device_get(state.method)
    np.testing.assert_array_equal(method.epochs, before)  # one per reward epoch, across sessions
    assert np.all(method.kl_count > 0) and np.all(method.ent_min < method.ent_max)
    learnt = (state.agent, state.reward, state.method, state.entropy_stats)  # (the oracle's beta is inf)
    assert all(np.all(np.isfinite(x)) for x in jax.tree.leaves(learnt) if jnp.issubdtype(x.dtype, jnp.floating))
    assert not RIME().resets_critic(trainer.cfg)
