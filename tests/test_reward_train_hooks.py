"""What a method can shape in reward training without copying its loops: the optimiser, a weight per labelled pair,
and the loss terms' own metrics (rebel_jax.preference.reward_train)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from test_qpa_rune import _labelled_state

from rebel_jax.preference import reward_model, reward_train
from rebel_jax.preference.reward_model import RewardConfig

CFG = RewardConfig(ensemble_size=2, hidden=16, depth=2, batch_size=4, lr=1e-2)
COUNT, LENGTH = 10, 5


def _stored():
    """A fresh ensemble with ``COUNT`` labelled pairs of random segments (tests/test_qpa_rune.py's)."""
    return _labelled_state(CFG, COUNT, LENGTH)


def _params(state):
    return jax.tree.leaves(state.params)


@pytest.mark.parametrize("weight_of_slot_3", [0.0, 1.0], ids=["masked", "kept"])
def test_a_pair_of_weight_zero_does_not_move_the_members(weight_of_slot_3):
    """Flipping the label of a masked pair leaves every parameter as it was, bit for bit; of a kept one, not."""
    base = _stored()
    flipped_labels = base.data.labels.at[3].set(1.0 - base.data.labels[3])
    flipped = base.replace(data=base.data.replace(labels=flipped_labels))
    weight = jnp.ones(base.data.capacity).at[3].set(weight_of_slot_3)
    train = jax.jit(lambda s: reward_train.train(CFG, s, jax.random.key(3), max_epochs=3, pair_weight=weight)[0])
    same = all(np.array_equal(a, b) for a, b in zip(_params(train(base)), _params(train(flipped)), strict=True))
    assert same == (weight_of_slot_3 == 0.0)


def test_a_method_s_optimiser_makes_the_step():
    """One step with plain SGD equals ``params - lr * grad`` of the training loss on the step's minibatch."""
    stored, lr, key = _stored(), 0.05, jax.random.key(4)
    sgd = optax.sgd(lr)
    stored = reward_model.new_state(CFG, stored.params, stored.data, optimizer=sgd)
    terms = (reward_model.bt_loss(CFG),)
    trained, _ = reward_train.train_iterations(CFG, stored, key, terms, jnp.int32(1), optimizer=sgd)
    # The first step's minibatch and key, as the loop draws them (train_iterations' docstring).
    key_order, key_loss = jax.random.split(key)
    capacity = stored.data.capacity
    padded = -(-capacity // CFG.batch_size) * CFG.batch_size
    order = reward_train._shuffles(jax.random.fold_in(key_order, 0), CFG.ensemble_size, COUNT, capacity, padded)
    batch = reward_train._minibatch(stored.data, order, jnp.int32(0), CFG.batch_size)
    grad_fn = jax.grad(reward_train.loss_and_logits(CFG, terms), has_aux=True)
    grads, _ = grad_fn(stored.params, batch, jax.random.fold_in(key_loss, 0))
    expected = jax.tree.map(lambda p, g: p - lr * g, stored.params, grads)
    for got, want in zip(_params(trained), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-7)


def test_the_terms_metrics_come_back_as_means_over_the_steps():
    """With the Bradley-Terry term alone the term's ``bt_loss`` is the loop's ``loss``; a second term's metric comes
    back too, as the mean of its per-step values."""
    stored = _stored()

    def constant(params, batch, key):
        del params, key
        return jnp.zeros(()), {"pairs": jnp.sum(batch.weight)}

    terms = (reward_model.bt_loss(CFG), constant)
    _, metrics = reward_train.train_epoch(CFG, stored, jax.random.key(5), terms)
    np.testing.assert_allclose(metrics["bt_loss"], metrics["loss"], rtol=1e-6)
    # Minibatches of 4 over 10 pairs for 2 members: 8, 8 and 4 real pairs, so a mean of 20 / 3 a step.
    expected = np.mean([CFG.ensemble_size * min(CFG.batch_size, COUNT - i) for i in range(0, COUNT, CFG.batch_size)])
    np.testing.assert_allclose(metrics["pairs"], expected, rtol=1e-6)
