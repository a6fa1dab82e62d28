"""Reward-model terms of REBEL (agent preference) and SURF (temporal crops, pseudo-labels), and the sigmoid head."""

from __future__ import annotations

import dataclasses
import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.methods import rebel as agent_preference
from rebel_jax.methods import surf
from rebel_jax.preference import reward_model as rm
from rebel_jax.preference import reward_train as rt
from rebel_jax.preference.queries import Segments

OBS, ACT, H = 3, 2, 6
TRUE_W = np.array([1.0, -0.5, 0.8, 0.6, -0.4], np.float32)
TINY = rm.RewardConfig(ensemble_size=2, hidden=4, depth=1)
SMALL = rm.RewardConfig(
    ensemble_size=2, hidden=16, depth=1, lr=3e-3, batch_size=16, max_epochs=8, stop_accuracy=1.0, label_capacity=64
)

_init = jax.jit(rm.init, static_argnums=(0, 2, 3, 4))
_add_labels = jax.jit(rm.add_labels)
_train = jax.jit(rt.train, static_argnums=0)


def _segments(seed, n, length=H):
    """Smooth synthetic segments: a random state-action per segment plus small per-step noise."""
    rng = np.random.default_rng(seed)
    obs = (rng.normal(size=(n, 1, OBS)) + 0.2 * rng.normal(size=(n, length, OBS))).astype(np.float32)
    action = np.clip(rng.uniform(-1.0, 1.0, (n, 1, ACT)) + 0.1 * rng.normal(size=(n, length, ACT)), -1, 1)
    action = action.astype(np.float32)
    return Segments(obs=obs, action=action, true_reward=np.concatenate([obs, action], -1) @ TRUE_W)


def _state_with_labels(cfg, seed, n, length=H):
    """A fresh ensemble with n oracle-labelled pairs of segments of the given stored length."""
    seg_a, seg_b = _segments(2 * seed, n, length), _segments(2 * seed + 1, n, length)
    labels = (seg_b.true_reward.sum(1) > seg_a.true_reward.sum(1)).astype(np.float32)
    state = _init(cfg, jax.random.key(seed), OBS, ACT, length)
    return _add_labels(state, seg_a, seg_b, labels, np.ones(n, np.float32))


def _numpy_rewards(params, obs, action, output="tanh"):
    """Per-member rewards of a depth-1 ensemble, by hand in float64: (M, ...)."""
    layers = jax.tree.map(lambda x: np.asarray(x, np.float64), params)["params"]
    x = np.concatenate([obs, action], -1).astype(np.float64)
    rewards = []
    for m in range(layers["Dense_0"]["kernel"].shape[0]):
        hidden = x @ layers["Dense_0"]["kernel"][m] + layers["Dense_0"]["bias"][m]
        hidden = np.where(hidden > 0, hidden, 0.01 * hidden)  # Flax's leaky_relu slope.
        z = (hidden @ layers["Dense_1"]["kernel"][m] + layers["Dense_1"]["bias"][m])[..., 0]
        rewards.append(np.tanh(z) if output == "tanh" else 1.0 / (1.0 + np.exp(-z)))
    return np.stack(rewards)


def _numpy_ce(logits, labels):
    return -(labels * np.log(1 / (1 + np.exp(-logits))) + (1 - labels) * np.log(1 / (1 + np.exp(logits))))


def _tiny_params(cfg=TINY, seed=0):
    return _init(cfg, jax.random.key(seed), OBS, ACT, H).params


def _empty_batch(members=2, size=4):
    zeros = rm.Steps(jnp.zeros((members, size, H, OBS)), jnp.zeros((members, size, H, ACT)))
    return rm.PrefBatch(zeros, zeros, jnp.zeros((members, size)), jnp.ones((members, size)), jnp.arange(members))


# Reward head.


@pytest.mark.parametrize("output", ["tanh", "sigmoid"])
def test_reward_head_matches_hand_computation(output):
    cfg = dataclasses.replace(TINY, output=output)
    params = _tiny_params(cfg)
    seg = _segments(1, 5)
    got = np.asarray(jax.jit(rm.predict, static_argnums=0)(cfg, params, seg.obs, seg.action))
    np.testing.assert_allclose(got, _numpy_rewards(params, seg.obs, seg.action, output), rtol=1e-5, atol=1e-6)
    if output == "sigmoid":
        assert got.min() > 0 and got.max() < 1
    assert rm.RewardConfig().output == "tanh"


# REBEL: agent-preference term.


@pytest.mark.parametrize("estimator", ["discounted", "mean"])
@pytest.mark.parametrize("output", ["tanh", "sigmoid"])
def test_agent_value_term_equals_hand_computation(estimator, output):
    cfg = dataclasses.replace(TINY, output=output)
    params = _tiny_params(cfg, seed=1)
    seg = _segments(2, 3, length=5)
    lam, gamma = 0.7, 0.9
    term = jax.jit(agent_preference.agent_value_term(cfg, lam, seg.obs, seg.action, gamma, estimator))
    loss, metrics = term(params, _empty_batch(), jax.random.key(0))

    rewards = _numpy_rewards(params, seg.obs, seg.action, output)  # (M, N, H)
    values = []
    for m in range(cfg.ensemble_size):
        if estimator == "discounted":
            returns = [sum(gamma**h * rewards[m, n, h] for h in range(5)) for n in range(3)]
            values.append(sum(returns) / 3)
        else:
            values.append(rewards[m].sum() / 15 / (1 - gamma))
    np.testing.assert_allclose(float(loss), lam * sum(values), rtol=1e-5)
    np.testing.assert_allclose(float(metrics["agent_term"]), lam * sum(values), rtol=1e-5)
    np.testing.assert_allclose(float(metrics["agent_value"]), np.mean(values), rtol=1e-5)


def test_agent_value_term_gradients_reach_only_the_reward_params():
    params = _tiny_params(seed=2)
    seg = _segments(3, 4)
    obs, action = jnp.asarray(seg.obs), jnp.asarray(seg.action)
    batch, key, lam, gamma = _empty_batch(), jax.random.key(0), -0.3, 0.95

    def loss(params, lam, obs, action):
        return agent_preference.agent_value_term(TINY, lam, obs, action, gamma)(params, batch, key)[0]

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2, 3)))(params, lam, obs, action)
    value_grads = jax.grad(lambda p: jnp.sum(agent_preference.agent_value(TINY, p, obs, action, gamma, "discounted")))(
        params
    )
    chex.assert_trees_all_close(grads[0], jax.tree.map(lambda g: lam * g, value_grads), rtol=1e-5, atol=1e-7)
    assert np.abs(np.asarray(jax.tree.leaves(value_grads)[0])).max() > 0
    total_value = float(jnp.sum(agent_preference.agent_value(TINY, params, obs, action, gamma, "discounted")))
    np.testing.assert_allclose(float(grads[1]), total_value, rtol=1e-5)  # d loss / d lambda = sum_m V_m.
    np.testing.assert_array_equal(np.asarray(grads[2]), 0.0)
    np.testing.assert_array_equal(np.asarray(grads[3]), 0.0)

    lams = jnp.array([-1.0, 0.0, 2.0])
    losses = jax.jit(jax.vmap(loss, in_axes=(None, 0, None, None)))(params, lams, obs, action)
    np.testing.assert_allclose(np.asarray(losses), np.asarray(lams) * total_value, rtol=1e-5)


@jax.jit
def _session_with_lambda(state, key, lam, agent_obs, agent_action):
    """A BT + REBEL session with lambda traced: one compilation serves every lambda."""
    terms = [rm.bt_loss(SMALL), agent_preference.agent_value_term(SMALL, lam, agent_obs, agent_action, 0.99)]
    return rt.train(SMALL, state, key, terms)


def test_zero_lambda_adds_an_exactly_zero_gradient_and_trains_like_bt_alone():
    """lambda 0 adds nothing: the term's loss and gradient are exactly 0, and a session trains as BT alone, bit for
    bit (two XLA programs: conftest.py keeps the CPU's rounding independent of how each is fused)."""
    state = _state_with_labels(SMALL, 0, 40)
    agent = _segments(50, 8)
    key = jax.random.key(1)
    term = agent_preference.agent_value_term(SMALL, 0.0, agent.obs, agent.action, 0.99)
    loss, grads = jax.jit(jax.value_and_grad(lambda p: term(p, _empty_batch(), key)[0]))(state.params)
    assert float(loss) == 0.0
    assert all(not np.any(g) for g in jax.tree.leaves(grads))
    alone, alone_metrics = _train(SMALL, state, key)
    both, both_metrics = _session_with_lambda(state, key, 0.0, agent.obs, agent.action)
    assert int(both_metrics["epochs"]) == int(alone_metrics["epochs"]) > 0
    chex.assert_trees_all_equal((alone.params, alone.opt_state), (both.params, both.opt_state))


def test_lambda_sign_moves_the_agents_reward():
    """lambda < 0 raises the learned reward on the agent's segments, lambda > 0 lowers it (eq. taken literally)."""
    state = _state_with_labels(SMALL, 3, 40)
    agent = _segments(51, 8)
    key = jax.random.key(4)
    rewards = {}
    for lam in (0.3, 0.0, -0.3):
        trained, _ = _session_with_lambda(state, key, lam, agent.obs, agent.action)
        rewards[lam] = float(jnp.mean(rm.mean_reward(SMALL, trained.params, agent.obs, agent.action)))
    assert rewards[0.3] < rewards[0.0] - 0.05 and rewards[-0.3] > rewards[0.0] + 0.05, rewards


# SURF: temporal crops.


def test_crop_masks_match_a_python_reference_with_the_same_draws():
    key, shape, stored, crop = jax.random.key(5), (3, 7), 14, 3
    central = stored - 2 * crop
    mask_a, mask_b = jax.jit(rm.crop_masks, static_argnums=(1, 2, 3))(key, shape, stored, crop)

    @jax.jit
    def draws(key):  # The documented draws: one length per pair, then a start per segment.
        key_length, key_a, key_b = jax.random.split(key, 3)
        lengths = jax.random.randint(key_length, shape, central - crop, central + crop + 1)
        starts = [jax.random.randint(k, shape, 0, stored - lengths + 1) for k in (key_a, key_b)]
        return lengths, starts

    lengths, starts_ab = jax.tree.map(np.asarray, draws(key))
    for starts, mask in zip(starts_ab, (mask_a, mask_b), strict=True):
        expected = np.zeros(shape + (stored,), np.float32)
        for i in range(shape[0]):
            for j in range(shape[1]):
                expected[i, j, starts[i, j] : starts[i, j] + lengths[i, j]] = 1.0
        np.testing.assert_array_equal(np.asarray(mask), expected)


def test_crop_masks_are_single_runs_of_allowed_lengths_covering_all_crops():
    shape, stored, crop = (4000,), 12, 2
    central = stored - 2 * crop
    masks = np.stack(jax.jit(rm.crop_masks, static_argnums=(1, 2, 3))(jax.random.key(6), shape, stored, crop))
    assert set(np.unique(masks)) == {0.0, 1.0}
    edges = np.diff(np.pad(masks, ((0, 0), (0, 0), (1, 1))), axis=-1)
    assert np.all((edges == 1).sum(-1) == 1) and np.all((edges == -1).sum(-1) == 1)  # One contiguous run.
    lengths = masks.sum(-1)
    np.testing.assert_array_equal(lengths[0], lengths[1])  # Both segments of a pair keep as many steps.
    assert set(lengths[0].astype(int)) == set(range(central - crop, central + crop + 1))
    starts = np.argmax(masks, axis=-1)
    for length in range(central - crop, central + crop + 1):  # Every start in [0, L - length] occurs.
        assert set(starts[0][lengths[0] == length]) == set(range(stored - length + 1))
    full = jax.jit(rm.crop_masks, static_argnums=(1, 2, 3))(jax.random.key(7), (2, 3), 5, 0)
    np.testing.assert_array_equal(np.stack(full), 1.0)


def _surf_batch(seed, members, size, stored):
    """A minibatch of (M, B) labelled pairs of segments of the stored length, soft and padded pairs included."""
    seg_a, seg_b = _segments(seed, members * size, stored), _segments(seed + 1, members * size, stored)
    labels = (seg_b.true_reward.sum(1) > seg_a.true_reward.sum(1)).astype(np.float32)
    labels[1] = 0.5
    weight = np.ones(members * size, np.float32)
    weight[-1] = 0.0

    def split(x):
        return jnp.asarray(x.reshape((members, size) + x.shape[1:]))

    a, b = rm.Steps(split(seg_a.obs), split(seg_a.action)), rm.Steps(split(seg_b.obs), split(seg_b.action))
    return rm.PrefBatch(a, b, split(labels), split(weight), members=jnp.arange(members))


_with_rewards = jax.jit(rm.with_rewards, static_argnums=0)


def test_one_uncropped_copy_is_bt_loss_exactly():
    """The crop path with crop 0 and one copy (masks of ones) gives the whole segments' loss and gradient."""
    params = _init(SMALL, jax.random.key(8), OBS, ACT, H).params
    batch, key = _surf_batch(9, 2, 5, H), jax.random.key(10)
    value_and_grad = functools.partial(jax.value_and_grad, has_aux=True)
    plain = jax.jit(value_and_grad(rt.loss_and_logits(SMALL, [rm.bt_loss(SMALL)])))(params, batch, key)
    copied = jax.jit(value_and_grad(rt.loss_and_logits(SMALL, [rm.bt_loss(SMALL, 0, copies=1)])))(params, batch, key)
    chex.assert_trees_all_equal(plain, copied)


def test_cropped_bt_loss_sums_each_member_over_its_own_crops():
    surf_cfg = surf.SURFConfig(crop=2)
    stored = H + 2 * surf_cfg.crop
    params = _tiny_params(seed=12)
    batch, key = _surf_batch(13, 2, 5, stored), jax.random.key(14)
    loss, metrics = jax.jit(rm.bt_loss(TINY, surf_cfg.crop))(params, _with_rewards(TINY, params, batch), key)
    mask_a, mask_b = map(
        np.asarray, jax.jit(rm.crop_masks, static_argnums=(1, 2, 3))(key, (2, 5), stored, surf_cfg.crop)
    )
    assert not np.array_equal(mask_a[0], mask_a[1])  # Members see different crops.
    expected = 0.0
    for m in range(2):
        rewards_a = _numpy_rewards(params, np.asarray(batch.a.obs[m]), np.asarray(batch.a.action[m]))[m]
        rewards_b = _numpy_rewards(params, np.asarray(batch.b.obs[m]), np.asarray(batch.b.action[m]))[m]
        logits = (rewards_b * mask_b[m]).sum(-1) - (rewards_a * mask_a[m]).sum(-1)
        weight = np.asarray(batch.weight[m])
        expected += (_numpy_ce(logits, np.asarray(batch.labels[m])) * weight).sum() / weight.sum()
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["bt_loss"]), expected, rtol=1e-5)


# SURF: pseudo-labels.


def test_pseudo_labels_match_numpy():
    logits = np.array([-3.0, -0.5, -1e-3, 0.0, 1e-3, 0.4, 1.2, 2.5, 6.0], np.float32)
    for threshold in (0.5, 0.6, 0.9, 0.99):
        labels, confident = jax.jit(surf.pseudo_labels)(logits, threshold)
        prob = 1.0 / (1.0 + np.exp(-logits.astype(np.float64)))
        np.testing.assert_array_equal(np.asarray(labels), (prob > 0.5).astype(np.float32))
        np.testing.assert_array_equal(
            np.asarray(confident), (np.maximum(prob, 1 - prob) >= threshold).astype(np.float32)
        )


def _pool(seed, size, stored):
    seg_a, seg_b = _segments(seed, size, stored), _segments(seed + 1, size, stored)
    a, b = (
        rm.Steps(jnp.asarray(seg_a.obs), jnp.asarray(seg_a.action)),
        rm.Steps(jnp.asarray(seg_b.obs), jnp.asarray(seg_b.action)),
    )
    return rm.PairStore(a, b, jnp.zeros(size), jnp.zeros((), jnp.int32), jnp.asarray(size, jnp.int32))


def test_pseudo_label_term_matches_a_numpy_reference_with_the_same_draws():
    surf_cfg = surf.SURFConfig(threshold=0.6, weight=0.5, ratio=3, crop=2)
    stored = H + 2 * surf_cfg.crop
    params = _init(TINY, jax.random.key(15), OBS, ACT, stored).params
    params = jax.tree.map(lambda x: 3.0 * x, params)  # Sharper preferences: some pairs pass the threshold.
    pool = _pool(16, 30, stored)
    batch, key = _surf_batch(17, 2, 4, stored), jax.random.key(18)
    term = surf.pseudo_label_term(TINY, surf_cfg, pool)
    (loss, metrics), grads = jax.jit(jax.value_and_grad(term, has_aux=True))(params, batch, key)

    @jax.jit
    def draws(key):  # The documented draws: pool indices, then crops.
        key_index, key_crop = jax.random.split(key)
        return jax.random.randint(key_index, (2, 12), 0, 30), *rm.crop_masks(key_crop, (2, 12), stored, surf_cfg.crop)

    index, mask_a, mask_b = map(np.asarray, draws(key))
    expected, confident_count, fixed_labels, fixed_confident = 0.0, 0, [], []
    for m in range(2):
        obs_a, act_a, obs_b, act_b = (
            np.asarray(x)[index[m]] for x in (pool.a.obs, pool.a.action, pool.b.obs, pool.b.action)
        )
        rewards_a, rewards_b = _numpy_rewards(params, obs_a, act_a)[m], _numpy_rewards(params, obs_b, act_b)[m]
        central = slice(surf_cfg.crop, surf_cfg.crop + H)
        prob = 1.0 / (1.0 + np.exp(-(rewards_b[:, central].sum(-1) - rewards_a[:, central].sum(-1))))
        assert np.all(np.abs(np.maximum(prob, 1 - prob) - surf_cfg.threshold) > 1e-4)  # No float32 borderline case.
        labels = (prob > 0.5).astype(np.float64)
        confident = (np.maximum(prob, 1 - prob) >= surf_cfg.threshold).astype(np.float64)
        logits = (rewards_b * mask_b[m]).sum(-1) - (rewards_a * mask_a[m]).sum(-1)
        expected += surf_cfg.weight * np.mean(_numpy_ce(logits, labels) * confident)
        confident_count += confident.sum()
        fixed_labels.append(labels)
        fixed_confident.append(confident)
    assert 0 < confident_count < 24  # Both confident and unconfident pairs are drawn.
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["pseudo_loss"]), expected, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["pseudo_fraction"]), confident_count / 24, rtol=1e-6)

    # The pseudo-labels carry no gradient: the term's gradient is that of CE with the labels held fixed.
    fixed_labels, fixed_confident = jnp.asarray(np.stack(fixed_labels)), jnp.asarray(np.stack(fixed_confident))

    def fixed_loss(params):
        def one(member_params, member_index, member_mask_a, member_mask_b):
            reward_a = TINY.network().apply(member_params, pool.a.obs[member_index], pool.a.action[member_index])
            reward_b = TINY.network().apply(member_params, pool.b.obs[member_index], pool.b.action[member_index])
            return jnp.sum(reward_b * member_mask_b, -1) - jnp.sum(reward_a * member_mask_a, -1)

        logits = jax.vmap(one)(params, jnp.asarray(index), jnp.asarray(mask_a), jnp.asarray(mask_b))
        return surf_cfg.weight * jnp.sum(jnp.mean(rm.bt_cross_entropy(logits, fixed_labels) * fixed_confident, axis=1))

    chex.assert_trees_all_close(grads, jax.jit(jax.grad(fixed_loss))(params), rtol=1e-4, atol=1e-6)


@pytest.mark.heavy  # make test runs SURF's sessions jitted and vmapped inside the round (test_preference_train.py)
def test_surf_session_runs_under_jit_and_vmap_over_keys():
    surf_cfg = surf.SURFConfig(threshold=0.7, ratio=2, crop=2)
    stored = H + 2 * surf_cfg.crop
    state = _state_with_labels(SMALL, 19, 40, stored)
    terms = [rm.bt_loss(SMALL, surf_cfg.crop), surf.pseudo_label_term(SMALL, surf_cfg, _pool(20, 50, stored))]
    session = functools.partial(rt.train, SMALL, terms=terms)
    keys = jax.random.split(jax.random.key(21), 2)
    batched, batched_metrics = jax.jit(jax.vmap(session, in_axes=(None, 0)))(state, keys)
    assert np.all(np.asarray(batched_metrics["epochs"]) == SMALL.max_epochs)
    assert np.all(np.isfinite(np.asarray(batched_metrics["loss"])))
    for i in range(2):
        alone, metrics = jax.jit(session)(state, keys[i])
        np.testing.assert_allclose(float(batched_metrics["loss"][i]), float(metrics["loss"]), rtol=1e-5)
        column = jax.tree.map(lambda x, i=i: x[i], batched.params)
        chex.assert_trees_all_close(alone.params, column, rtol=1e-4, atol=1e-6)


# Validation.


@pytest.mark.parametrize(
    "field,value",
    [("lam", float("nan")), ("estimator", "max"), ("num_segments", 0), ("segment_length", 0), ("gamma", 1.5)],
)
def test_agent_preference_validate_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"rebel.{field}"):
        dataclasses.replace(agent_preference.AgentPreferenceConfig(), **{field: value}).validate()
    with pytest.raises(ValueError, match="rebel.gamma"):
        agent_preference.AgentPreferenceConfig(estimator="mean", gamma=1.0).validate()
    agent_preference.AgentPreferenceConfig().validate()
    agent_preference.AgentPreferenceConfig(gamma=1.0).validate()


@pytest.mark.parametrize(
    "field,value", [("threshold", 1.5), ("weight", -1.0), ("ratio", 0), ("pool_size", 0), ("crop", -1)]
)
def test_surf_validate_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"surf.{field}"):
        dataclasses.replace(surf.SURFConfig(), **{field: value}).validate()
    with pytest.raises(ValueError, match="surf.crop"):
        surf.SURFConfig(crop=5).validate(segment_length=5)
    surf.SURFConfig().validate(segment_length=50)


def test_scale_free_value_term_matches_a_numpy_reference():
    params = _init(TINY, jax.random.key(21), OBS, ACT, H).params
    seg = _segments(22, 4)
    batch = _surf_batch(23, 2, 5, H)  # The last pair is padding: excluded from the spread.
    lam, gamma = -0.3, 0.95
    term = agent_preference.agent_value_term(TINY, lam, seg.obs, seg.action, gamma, "discounted", normalize=True)
    loss, _ = jax.jit(term)(params, _with_rewards(TINY, params, batch), jax.random.key(0))
    rewards = _numpy_rewards(params, seg.obs, seg.action)  # (M, N, H)
    values = (rewards * gamma ** np.arange(H)).sum(-1).mean(-1)
    expected = 0.0
    for m in range(2):
        w = np.asarray(batch.weight[m]) > 0
        labelled = np.concatenate(
            [
                _numpy_rewards(params, np.asarray(batch.a.obs[m])[w], np.asarray(batch.a.action[m])[w])[m],
                _numpy_rewards(params, np.asarray(batch.b.obs[m])[w], np.asarray(batch.b.action[m])[w])[m],
            ]
        )
        expected += lam * values[m] / labelled.std()
    np.testing.assert_allclose(float(loss), expected, rtol=1e-4)
    # Scale-free: scaling the reward network's output layer scales V and its spread alike (before tanh
    # saturates), so the term barely moves, where the literal term scales with it.
    small = jax.tree.map(lambda x: x, params)
    small["params"]["Dense_1"] = jax.tree.map(lambda x: 0.01 * x, params["params"]["Dense_1"])
    literal = agent_preference.agent_value_term(TINY, lam, seg.obs, seg.action, gamma, "discounted")
    batch_small, batch = _with_rewards(TINY, small, batch), _with_rewards(TINY, params, batch)
    ratio_free = float(term(small, batch_small, None)[0]) / float(term(params, batch, None)[0])
    ratio_literal = float(literal(small, batch, None)[0]) / float(literal(params, batch, None)[0])
    assert abs(ratio_literal) < 0.2 and abs(ratio_free - 1.0) < abs(ratio_literal - 1.0)


def test_value_term_gradient_reaches_only_the_reward_parameters():
    params = _init(TINY, jax.random.key(24), OBS, ACT, H).params
    seg = _segments(25, 3)

    def loss_of_inputs(obs, action):
        return agent_preference.agent_value_term(TINY, 0.7, obs, action, 0.9)(params, None, None)[0]

    grad_obs, grad_action = jax.grad(loss_of_inputs, argnums=(0, 1))(jnp.asarray(seg.obs), jnp.asarray(seg.action))
    assert not np.any(np.asarray(grad_obs)) and not np.any(np.asarray(grad_action))
    grads = jax.grad(
        lambda p: agent_preference.agent_value_term(TINY, 0.7, seg.obs, seg.action, 0.9)(p, None, None)[0]
    )(params)
    assert any(np.any(np.asarray(g)) for g in jax.tree.leaves(grads))


# REBEL: the un-relaxed penalty (eq. "bilevel_rlhf_fo") and the lower bound's r >= 0.


def _store(cfg, seed, pairs, capacity):
    """A label store of ``capacity`` slots holding ``pairs`` random pairs (labels do not matter here)."""
    state = _init(dataclasses.replace(cfg, label_capacity=capacity), jax.random.key(seed), OBS, ACT, H)
    seg_a, seg_b = _segments(seed + 1, pairs), _segments(seed + 2, pairs)
    return _add_labels(state, seg_a, seg_b, np.ones(pairs, np.float32), np.ones(pairs, np.float32)).data


@pytest.mark.parametrize("k", [3, 10])
def test_best_segments_are_the_highest_learned_returns_of_either_side(k):
    params = _tiny_params(seed=30)
    data = _store(TINY, 31, pairs=3, capacity=8)  # 6 stored segments among 16 slots.
    best, valid = jax.jit(agent_preference.best_segments, static_argnums=(0, 3))(TINY, params, data, k)
    obs, action = best.obs, best.action
    candidates_obs = np.concatenate([np.asarray(data.a.obs)[:3], np.asarray(data.b.obs)[:3]])
    candidates_act = np.concatenate([np.asarray(data.a.action)[:3], np.asarray(data.b.action)[:3]])
    returns = _numpy_rewards(params, candidates_obs, candidates_act).mean(0).sum(-1)  # Ensemble mean, summed.
    order = sorted(range(6), key=lambda i: -returns[i])[: min(k, 6)]
    chex.assert_shape([obs], (k, H, OBS))
    np.testing.assert_array_equal(np.asarray(valid), [1.0] * len(order) + [0.0] * (k - len(order)))
    np.testing.assert_array_equal(np.asarray(obs)[: len(order)], candidates_obs[order])
    np.testing.assert_array_equal(np.asarray(action)[: len(order)], candidates_act[order])


@pytest.mark.parametrize("estimator", ["discounted", "mean"])
@pytest.mark.parametrize("normalize", [False, True])
def test_value_gap_term_matches_a_numpy_reference(estimator, normalize):
    params = _tiny_params(seed=32)
    agent, best = _segments(33, 3, length=7), _segments(34, 4)
    valid = np.array([1.0, 1.0, 1.0, 0.0], np.float32)  # The last one is an empty slot: ignored.
    batch = _with_rewards(TINY, params, _surf_batch(35, 2, 5, H))
    lam, gamma = 0.7, 0.9
    best_steps = rm.Steps(jnp.asarray(best.obs), jnp.asarray(best.action))
    term = agent_preference.value_gap_term(
        TINY, lam, agent.obs, agent.action, best_steps, valid, gamma, estimator, normalize
    )
    loss, metrics = jax.jit(term)(params, batch, jax.random.key(0))

    agent_rewards = _numpy_rewards(params, agent.obs, agent.action)  # (M, 3, 7)
    best_rewards = _numpy_rewards(params, best.obs[:3], best.action[:3])  # (M, 3, H), valid ones only
    expected, values, optimal = 0.0, [], []
    for m in range(TINY.ensemble_size):
        if estimator == "discounted":
            value = np.mean([sum(gamma**t * agent_rewards[m, n, t] for t in range(7)) for n in range(3)])
            best_value = best_rewards[m].mean() * sum(gamma**t for t in range(7))  # Over V's horizon, 7 steps.
        else:
            value = agent_rewards[m].mean() / (1 - gamma)
            best_value = best_rewards[m].mean() / (1 - gamma)
        if normalize:
            w = np.asarray(batch.weight[m]) > 0
            labelled = np.concatenate(
                [
                    _numpy_rewards(params, np.asarray(batch.a.obs[m])[w], np.asarray(batch.a.action[m])[w])[m],
                    _numpy_rewards(params, np.asarray(batch.b.obs[m])[w], np.asarray(batch.b.action[m])[w])[m],
                ]
            )
            value, best_value = value / labelled.std(), best_value / labelled.std()
        values.append(value)
        optimal.append(best_value)
        expected += lam * (best_value - value)
    np.testing.assert_allclose(float(loss), expected, rtol=1e-4)
    np.testing.assert_allclose(float(metrics["agent_term"]), expected, rtol=1e-4)
    np.testing.assert_allclose(float(metrics["agent_value"]), np.mean(values), rtol=1e-4)
    np.testing.assert_allclose(float(metrics["optimal_value"]), np.mean(optimal), rtol=1e-4)


def test_value_gap_term_gradient_reaches_only_the_reward_parameters():
    params = _tiny_params(seed=36)
    agent, best = _segments(37, 3), _segments(38, 2)
    valid = jnp.ones(2)

    def loss(params, obs, action, best_obs, best_action):
        best = rm.Steps(best_obs, best_action)
        return agent_preference.value_gap_term(TINY, 0.5, obs, action, best, valid, 0.9)(params, None, None)[0]

    inputs = tuple(map(jnp.asarray, (agent.obs, agent.action, best.obs, best.action)))
    grads = jax.grad(loss, argnums=(0, 1, 2, 3, 4))(params, *inputs)
    assert all(not np.any(np.asarray(g)) for g in grads[1:])

    def total(fn, *args):
        return jax.grad(lambda p: jnp.sum(fn(TINY, p, *args)))(params)

    best_steps = rm.Steps(jnp.asarray(best.obs), jnp.asarray(best.action))
    optimal = total(agent_preference.optimal_value, best_steps, valid, 0.9, "discounted", H)
    value = total(agent_preference.agent_value, agent.obs, agent.action, 0.9, "discounted")
    expected = jax.tree.map(lambda a, b: 0.5 * (a - b), optimal, value)
    chex.assert_trees_all_close(grads[0], expected, rtol=1e-5, atol=1e-7)


@pytest.mark.parametrize("output", ["sigmoid", "tanh"])
def test_the_lower_bound_holds_with_sigmoid_rewards_and_can_fail_with_tanh(output):
    """Eq. "bilevel_rlhf_fo_lb" bounds eq. "bilevel_rlhf_fo" because V(pi_theta) >= 0 when r >= 0.

    As minimised losses, with lambda >= 0: penalty ``lambda (V* - V)`` <= lower bound ``lambda V*``.
    The output layer is pushed negative so that tanh rewards are negative everywhere.
    """
    cfg = dataclasses.replace(TINY, output=output)
    params = _tiny_params(cfg, seed=39)
    params["params"]["Dense_1"]["bias"] = params["params"]["Dense_1"]["bias"] - 3.0
    agent, best = _segments(40, 3), _segments(41, 2)
    lam = 0.5
    best_steps = rm.Steps(jnp.asarray(best.obs), jnp.asarray(best.action))
    term = agent_preference.value_gap_term(cfg, lam, agent.obs, agent.action, best_steps, jnp.ones(2), 0.9)
    penalty, metrics = term(params, None, None)
    lower_bound = lam * cfg.ensemble_size * float(metrics["optimal_value"])  # lambda * sum_m V*_m
    rewards = _numpy_rewards(params, agent.obs, agent.action, output)
    if output == "sigmoid":
        assert rewards.min() > 0 and float(metrics["agent_value"]) > 0
        assert float(penalty) <= lower_bound
    else:
        assert rewards.max() < 0 and float(metrics["agent_value"]) < 0
        assert float(penalty) > lower_bound


def test_rebel_form_validates():
    with pytest.raises(ValueError, match="rebel.form"):
        agent_preference.AgentPreferenceConfig(form="exact").validate()
    with pytest.raises(ValueError, match="rebel.best_segments"):
        agent_preference.AgentPreferenceConfig(form="penalty", best_segments=0).validate()
    agent_preference.AgentPreferenceConfig(form="penalty").validate()


@pytest.mark.parametrize("estimator", ["discounted", "mean"])
def test_a_constant_shift_of_the_reward_moves_the_lower_bound_and_not_the_penalty(estimator):
    """The BT loss cannot see a constant shift c of the reward (RESULTS.md, question 2).

    The lower bound ``lambda sum_m V_m`` moves by ``lambda M c sum_{t<T} gamma^t`` (``discounted``) or
    ``lambda M c / (1 - gamma)`` (``mean``), so its gradient pushes the reward along c; the penalty
    ``lambda sum_m (V*_m - V_m)`` sums both values over as many steps and does not move.
    """
    params = _tiny_params(seed=42)
    agent, best = _segments(43, 3, length=7), _segments(44, 4)
    lam, gamma, shift = 0.3, 0.9, 0.7

    def predict(c):
        return lambda p, obs, action: rm.predict(TINY, p, obs, action) + c

    def losses(c):
        lower = agent_preference.agent_value_term(
            TINY, lam, agent.obs, agent.action, gamma, estimator, predict_fn=predict(c)
        )(params, None, None)[0]
        penalty = agent_preference.value_gap_term(
            TINY, lam, agent.obs, agent.action, rm.Steps(best.obs, best.action), jnp.ones(4), gamma, estimator,
            predict_fn=predict(c), best_predict_fn=lambda p, seg: predict(c)(p, seg.obs, seg.action),
        )(params, None, None)[0]  # fmt: skip
        return float(lower), float(penalty)

    (lower_0, penalty_0), (lower_c, penalty_c) = losses(0.0), losses(shift)
    steps = sum(gamma**t for t in range(7)) if estimator == "discounted" else 1 / (1 - gamma)
    np.testing.assert_allclose(lower_c - lower_0, lam * TINY.ensemble_size * shift * steps, rtol=1e-4)
    np.testing.assert_allclose(penalty_c, penalty_0, atol=1e-5)
    assert abs(penalty_0) > 1e-3  # the penalty itself is not trivially zero
