"""MRN: its hypergradient against the closed form of one SGD step's, its schedule against the original's loop, and
a tiny run on the probe task."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_preference_train import MICRO_PEBBLE

from rebel_jax.agents.replay import Transition
from rebel_jax.agents.sac import SAC
from rebel_jax.config import PRESETS, ConfigError, FeedbackConfig, SACConfig, TrainConfig
from rebel_jax.methods import mrn
from rebel_jax.preference import budget, reward_model
from rebel_jax.preference.pretrain import PretrainConfig
from rebel_jax.train import Trainer, compiled, seed_keys

OBS, ACT, B, LR, WEIGHT = 3, 2, 6, 0.1, 0.1


SAC_NET = SAC(SACConfig(hidden=8, depth=1, precision="highest"), OBS, ACT)
REWARD = reward_model.RewardConfig(ensemble_size=2, hidden=8, depth=1, label_capacity=5)
LABELS, MASK = np.array([1.0, 0.0, 1.0, 1.0]), np.array([1.0, 1.0, 0.0, 1.0])


@jax.jit
def _problem(key):
    """A tiny critic and reward ensemble, a minibatch, and a label store of 5 slots holding 3 pairs (of 4 asked)."""
    keys = jax.random.split(key, 8)
    state = SAC_NET.init(keys[0])
    state = state.replace(target_critic_params=jax.tree.map(lambda x: 0.9 * x, state.critic_params))
    reward = reward_model.init(REWARD, keys[2], OBS, ACT, 4)
    obs, next_obs = jax.random.normal(keys[3], (2, B, OBS))
    action = jax.random.uniform(keys[4], (B, ACT), minval=-1)
    batch = Transition(obs, action, jnp.zeros(B), next_obs, jnp.array([1.0] * 5 + [0.0]))
    seg = reward_model.Steps(jax.random.normal(keys[5], (4, 4, OBS)), jax.random.uniform(keys[6], (4, 4, ACT)))
    seg_b = jax.tree.map(lambda x: x[::-1] * 0.5, seg)
    reward = reward_model.add_labels(reward, seg, seg_b, jnp.asarray(LABELS), jnp.asarray(MASK))
    return state, reward, batch, mrn.soft_value(SAC_NET, state, batch.next_obs, keys[7]), seg, seg_b


def test_hypergradient_against_closed_form():
    sac, rcfg, labels, kept = SAC_NET, REWARD, LABELS, np.flatnonzero(MASK)
    state, reward, batch, value, seg, seg_b = _problem(jax.random.PRNGKey(3))
    pairs = mrn.last_pairs(reward.data, 4)  # 3 stored: the first of the 4 slots is padding
    np.testing.assert_array_equal(pairs[3], [0, 1, 1, 1])
    np.testing.assert_array_equal(pairs[0].obs[1:], seg.obs[kept, 0])
    np.testing.assert_array_equal(pairs[1].action[1:], seg_b.action[kept, 0])
    theta, phi = state.critic_params, reward.params

    def r(phi, obs, action):  # one sample's ensemble-mean reward, member by member
        return sum(rcfg.network().apply(jax.tree.map(lambda x, m=m: x[m], phi), obs, action) for m in (0, 1)) / 2

    def inner(theta):  # the critic's loss, sample by sample
        def one(obs, action, discount, v):
            y = r(phi, obs, action) + discount * sac.cfg.gamma * v
            q1, q2 = sac.critic.apply(theta, obs, action)
            return (q1 - y) ** 2 + (q2 - y) ** 2

        return jnp.mean(jax.vmap(one)(batch.obs, batch.action, batch.discount, value))

    def outer(theta):  # torch's CrossEntropyLoss, integer labels, over [Q_j(first sa of seg 1), Q_j(... seg 2)]
        q_a = jnp.stack(sac.critic.apply(theta, seg.obs[kept, 0], seg.action[kept, 0]))  # (2 heads, K)
        q_b = jnp.stack(sac.critic.apply(theta, seg_b.obs[kept, 0], seg_b.action[kept, 0]))
        logits = jnp.stack([q_a, q_b], axis=-1)
        chosen = jnp.take_along_axis(logits, np.asarray(labels, int)[kept][None, :, None], axis=-1)[..., 0]
        return WEIGHT * jnp.sum(jnp.mean(jax.nn.logsumexp(logits, axis=-1) - chosen, axis=1))

    @jax.jit
    def reference(theta, phi):
        theta_new = jax.tree.map(lambda p, g: p - LR * g, theta, jax.grad(inner)(theta))
        # dL/dphi = (2 lr / B) sum_i <grad_theta (Q1 + Q2)(s_i, a_i), grad L_out(theta')> grad_phi r(s_i, a_i): the
        # mixed derivative of the inner loss (quadratic in the reward) at theta, through theta'.
        g_out = jax.grad(outer)(theta_new)

        def c(obs, action):
            return jax.jvp(lambda th: sum(sac.critic.apply(th, obs, action)), (theta,), (g_out,))[1]

        weights = jax.vmap(c)(batch.obs, batch.action)  # (B,)
        grads = jax.vmap(jax.grad(r), in_axes=(None, 0, 0))(phi, batch.obs, batch.action)  # leaves (B, ...)
        return outer(theta_new), jax.tree.map(lambda g: 2 * LR / B * jnp.tensordot(weights, g, 1), grads)

    loss_fn = jax.jit(jax.value_and_grad(mrn.outer_loss, argnums=2), static_argnums=(0, 1))
    loss, grad = loss_fn(sac, rcfg, phi, theta, batch, value, pairs, LR, WEIGHT)
    expected_loss, expected = reference(theta, phi)
    np.testing.assert_allclose(loss, expected_loss, rtol=1e-5)
    assert max(float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(grad)) > 1e-6  # not trivially zero
    for got, want in zip(jax.tree.leaves(grad), jax.tree.leaves(expected), strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-3, atol=1e-7)


def original_meta_steps(cfg, total: int) -> tuple[list[int], np.ndarray]:
    """The env steps of MRN's bilevel steps, by the original's loop (RyanLiu112/MRN@ef67eaf:train_MRN.py:349-417),
    and the labels asked by each step's update (B-Pref's ``total_feedback``, the corner case included)."""
    f, start = cfg.feedback, cfg.feedback_start
    total_feedback, interact, steps, asked = 0, 0, [], np.zeros(total, np.int64)
    for step in range(total):
        if step == start:
            total_feedback, interact = min(f.queries, f.labels), 0
        elif step > start:
            if total_feedback < f.labels and interact == f.interval:
                total_feedback, interact = total_feedback + min(f.queries, f.labels - total_feedback), 0
            if step % cfg.mrn.meta_period == 0 and total_feedback < f.labels:
                steps.append(step)
        asked[step] = total_feedback
        interact += 1
    return steps, asked


def _micro(feedback: FeedbackConfig):
    train = dataclasses.replace(MICRO_PEBBLE.train, total_steps=280)
    return dataclasses.replace(MICRO_PEBBLE, algo="mrn", feedback=feedback, train=train, mrn=mrn.MRNConfig(10))


@pytest.mark.parametrize(
    "cfg",
    [
        dataclasses.replace(PRESETS["paper"], algo="mrn", train=TrainConfig(total_steps=300_000)),
        _micro(FeedbackConfig(labels=50, per_session=16, interval=40)),  # the last session asks 2 pairs
        _micro(FeedbackConfig(labels=50, per_session=16, interval=40, budget="asked")),
    ],
)
def test_schedule_against_original_loop(cfg):
    total, n = cfg.train.total_steps, cfg.env.num_envs
    expected, asked = original_meta_steps(cfg, total)
    t = np.arange(total // n)
    stored = asked[t * n]  # the oracle skips nothing: the labels stored are those asked
    due = np.asarray(mrn.meta_due(cfg.validate(), n, jnp.asarray(t), jnp.asarray(stored)))
    assert list(t[due] * n) == expected and expected
    assert max(expected) < np.argmax(asked >= cfg.feedback.labels)  # none once the budget is spent
    if cfg.feedback.budget == "asked":  # the unbatched condition alone decides
        np.testing.assert_array_equal(np.asarray(mrn.scheduled(cfg, n, jnp.asarray(t))), due)
    for step in range(cfg.feedback_start, total, cfg.feedback.interval // 2):  # the budget's own count
        held = (step - cfg.feedback_start) // cfg.feedback.interval + 1
        want = budget.remaining_budget(cfg.feedback, asked[step], held)
        assert mrn.remaining(cfg, asked[step], step) == want


def test_config_checks():
    with pytest.raises(ConfigError, match="mrn.meta_period=15 is invalid"):
        dataclasses.replace(MICRO_PEBBLE, algo="mrn", mrn=mrn.MRNConfig(meta_period=15)).validate()
    with pytest.raises(ConfigError, match="mrn.outer_weight"):
        mrn.MRNConfig(outer_weight=-1.0).validate(2)


def test_run_meta_steps_on_the_probe_task():
    # Sessions at env steps 80 and 160 (16 labels each): bilevel steps in rounds 2 (after its session) and 3 (none
    # there), none after the budget is spent at 160. No pre-training (80 random steps instead): a smaller program.
    cfg = dataclasses.replace(
        MICRO_PEBBLE,
        algo="mrn",
        train=dataclasses.replace(MICRO_PEBBLE.train, seed_steps=80),
        pretrain=PretrainConfig(steps=0),
        feedback=FeedbackConfig(labels=32, per_session=16, interval=80),
        mrn=mrn.MRNConfig(meta_period=10),
    )
    trainer = Trainer(cfg)
    init, round_fn, _ = compiled(trainer)
    state, per_round = init(seed_keys(0, 2)), cfg.train.steps_per_round
    expected, _ = original_meta_steps(cfg, cfg.train.total_steps)
    sessions = {r for r in range(cfg.train.num_rounds) if trainer.session_due(r)[0]}
    for r in range(cfg.train.num_rounds):
        before = jax.device_get(state.reward.params)
        state, m = round_fn(state, jnp.int32(r))
        ran = any(r * per_round <= s < (r + 1) * per_round for s in expected)
        np.testing.assert_array_equal(m["mrn/meta_step"], [1.0, 1.0] if ran else [np.nan, np.nan])
        assert np.all(np.isfinite(m["mrn/outer_loss"])) == ran
        assert np.all(m["diverged"] == 0.0)
        changed = [
            np.any(np.asarray(a != b).reshape(2, -1), axis=1)
            for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(state.reward.params), strict=True)
        ]
        if r not in sessions:  # only a bilevel step moves the reward, in every seed
            assert np.all(np.all(changed, axis=0)) == ran
        if ran and r not in sessions:  # the replay relabelled by the last one: every row has the current reward
            learned = jax.vmap(lambda p, o, a: reward_model.mean_reward(trainer.reward_cfg, p, o, a))(
                state.reward.params, state.buffer.obs, state.buffer.action
            )
            np.testing.assert_allclose(state.buffer.learned_reward, learned, rtol=1e-5, atol=1e-6)
