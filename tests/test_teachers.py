"""B-Pref scripted teachers against a plain-Python reference of the same rules."""

from __future__ import annotations

import dataclasses
import math

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.preference import teachers
from rebel_jax.preference.queries import Segments

N, H = 4000, 10
MARGIN = 3.0
_label = jax.jit(teachers.label, static_argnums=0)


@jax.jit
def _uniforms(key):
    """The draws ``label`` documents: split into (answer, mistake) keys, N uniforms each."""
    key_answer, key_mistake = jax.random.split(key)
    return jax.random.uniform(key_answer, (N,)), jax.random.uniform(key_mistake, (N,))


def _segments(seed, mean=0.1):
    reward = mean + 0.5 * np.random.default_rng(seed).normal(size=(N, H))
    return _constant_segments(reward.astype(np.float32))


def _pairs(seed=0):
    return _segments(2 * seed), _segments(2 * seed + 1)


def _constant_segments(reward):
    return Segments(obs=np.zeros(reward.shape + (1,)), action=np.zeros(reward.shape + (1,)), true_reward=reward)


def _reference_label(cfg, rewards_a, rewards_b, margin, u_answer, u_mistake):
    """One pair, B-Pref's order: skip, equal (plain returns), myopic, stochastic, mistake; equal last."""
    sum_a, sum_b = sum(rewards_a), sum(rewards_b)
    if cfg.eps_skip > 0 and max(sum_a, sum_b) <= margin * cfg.eps_skip:
        return 0.0, 0.0
    horizon = len(rewards_a)
    myopic_a = sum(cfg.gamma ** (horizon - 1 - t) * rewards_a[t] for t in range(horizon))
    myopic_b = sum(cfg.gamma ** (horizon - 1 - t) * rewards_b[t] for t in range(horizon))
    if math.isinf(cfg.beta):
        answer = 1.0 if myopic_a < myopic_b else 0.0
    else:
        prob_b = math.exp(cfg.beta * myopic_b) / (math.exp(cfg.beta * myopic_a) + math.exp(cfg.beta * myopic_b))
        answer = 1.0 if u_answer < prob_b else 0.0
    if u_mistake < cfg.eps_mistake:
        answer = 1.0 - answer
    if abs(sum_a - sum_b) < margin * cfg.eps_equal:
        answer = 0.5
    return answer, 1.0


COMBINED = teachers.TeacherConfig(beta=2.0, gamma=0.9, eps_mistake=0.1, eps_skip=0.1, eps_equal=0.1)
CASES = {**teachers.PRESETS, "combined": COMBINED}


@pytest.mark.parametrize("name", sorted(CASES))
def test_teacher_matches_python_reference(name):
    cfg = CASES[name]
    seg_a, seg_b = _pairs()
    key = jax.random.key(7)
    labels, mask, info = jax.jit(teachers.label, static_argnums=0)(cfg, key, seg_a, seg_b, MARGIN)
    u_answer, u_mistake = np.asarray(_uniforms(key), np.float64)
    rewards_a = np.asarray(seg_a.true_reward, np.float64)
    rewards_b = np.asarray(seg_b.true_reward, np.float64)
    expected = [
        _reference_label(cfg, list(rewards_a[i]), list(rewards_b[i]), MARGIN, u_answer[i], u_mistake[i])
        for i in range(N)
    ]
    expected_labels, expected_mask = np.array(expected).T
    np.testing.assert_array_equal(np.asarray(mask), expected_mask)
    np.testing.assert_array_equal(np.asarray(labels), expected_labels)
    assert int(info["num_skipped"]) == int(np.sum(expected_mask == 0))
    assert int(info["num_equal"]) == int(np.sum((expected_labels == 0.5) & (expected_mask == 1)))
    # Each knob actually acts on this data, so the comparison exercises it.
    if cfg.eps_skip > 0:
        assert 0 < int(info["num_skipped"]) < N
    if cfg.eps_equal > 0:
        assert 0 < int(info["num_equal"]) < N
    if cfg.gamma < 1 or cfg.eps_mistake > 0 or not math.isinf(cfg.beta):
        oracle, _, _ = _label(teachers.PRESETS["oracle"], key, seg_a, seg_b, MARGIN)
        assert np.any(np.asarray(oracle) != np.asarray(labels))


def test_oracle_prefers_the_higher_return_and_ties_answer_seg_a():
    seg_a, seg_b = _pairs(1)
    labels, mask, _ = _label(teachers.PRESETS["oracle"], jax.random.key(0), seg_a, seg_b, MARGIN)
    higher_b = np.sum(np.asarray(seg_b.true_reward), 1) > np.sum(np.asarray(seg_a.true_reward), 1)
    np.testing.assert_array_equal(np.asarray(labels), higher_b.astype(np.float32))
    np.testing.assert_array_equal(np.asarray(mask), 1.0)
    tie, _, _ = _label(teachers.PRESETS["oracle"], jax.random.key(0), seg_a, seg_a, MARGIN)
    np.testing.assert_array_equal(np.asarray(tie), 0.0)


def test_noisy_teacher_frequency_follows_bradley_terry():
    beta, diff = 1.0, 0.7
    reward_b = np.zeros((N, H), np.float32)
    reward_b[:, -1] = diff
    seg_a, seg_b = _constant_segments(np.zeros((N, H), np.float32)), _constant_segments(reward_b)
    labels, _, _ = _label(teachers.TeacherConfig(beta=beta), jax.random.key(3), seg_a, seg_b, MARGIN)
    expected = 1.0 / (1.0 + math.exp(-beta * diff))
    assert abs(float(np.mean(np.asarray(labels))) - expected) < 4 * math.sqrt(expected * (1 - expected) / N)


def test_mistake_teacher_flips_about_eps_of_the_answers():
    seg_a, seg_b = _pairs(2)
    key = jax.random.key(4)
    oracle, _, _ = _label(teachers.PRESETS["oracle"], key, seg_a, seg_b, MARGIN)
    noisy, _, _ = _label(teachers.PRESETS["mistake"], key, seg_a, seg_b, MARGIN)
    flipped = float(np.mean(np.asarray(oracle) != np.asarray(noisy)))
    assert abs(flipped - 0.1) < 4 * math.sqrt(0.1 * 0.9 / N)


def test_myopic_weights_favour_recent_steps():
    early, late = np.zeros((1, H), np.float32), np.zeros((1, H), np.float32)
    early[0, 0], late[0, -1] = 1.0, 0.9
    seg_early, seg_late = _constant_segments(early), _constant_segments(late)
    key = jax.random.key(0)
    oracle, _, _ = _label(teachers.PRESETS["oracle"], key, seg_late, seg_early, MARGIN)
    myopic, _, _ = _label(teachers.PRESETS["myopic"], key, seg_late, seg_early, MARGIN)
    assert float(oracle[0]) == 1.0  # 1.0 > 0.9: the early segment (seg_b) wins.
    assert float(myopic[0]) == 0.0  # 0.9**9 < 0.9: the late segment (seg_a) wins.
    np.testing.assert_allclose(jax.jit(teachers.myopic_returns)(early, 0.9), [0.9**9], rtol=1e-6)


def test_no_skip_when_eps_skip_is_zero_even_for_negative_returns():
    seg_a, seg_b = _segments(5, mean=-1.0), _segments(6, mean=-1.0)
    _, mask, info = _label(teachers.PRESETS["oracle"], jax.random.key(0), seg_a, seg_b, MARGIN)
    np.testing.assert_array_equal(np.asarray(mask), 1.0)
    assert int(info["num_skipped"]) == 0


def test_vmap_over_seeds_and_traced_knobs_equals_separate_calls():
    seg_a, seg_b = _pairs(3)
    keys = jax.random.split(jax.random.key(9), 3)
    betas = np.array([0.5, 1.0, np.inf], np.float32)

    def run(key, beta):
        cfg = dataclasses.replace(COMBINED, beta=beta)
        return teachers.label(cfg, key, seg_a, seg_b, MARGIN)[0]

    batched = jax.jit(jax.vmap(run))(keys, betas)
    for i, beta in enumerate([0.5, 1.0, math.inf]):
        alone = _label(dataclasses.replace(COMBINED, beta=beta), keys[i], seg_a, seg_b, MARGIN)[0]
        np.testing.assert_array_equal(np.asarray(batched[i]), np.asarray(alone))


def test_vmap_over_stacked_preset_knobs_equals_each_preset_alone():
    """What ``--teacher-grid`` runs: ``knobs`` of several presets stacked, one teacher per column."""
    seg_a, seg_b = _pairs(4)
    key = jax.random.key(11)
    cases = CASES  # B-Pref's six presets and one teacher with every knob on
    names = sorted(cases)
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *[teachers.knobs(cases[n]) for n in names])
    chex.assert_shape(list(stacked.values()), (len(names),))
    chex.assert_type(list(stacked.values()), jnp.float32)

    def run(knobs):
        return teachers.label(teachers.TeacherConfig(**knobs), key, seg_a, seg_b, MARGIN)

    labels, mask, info = jax.jit(jax.vmap(run))(stacked)
    for i, name in enumerate(names):
        alone = _label(cases[name], key, seg_a, seg_b, MARGIN)
        np.testing.assert_array_equal(np.asarray(labels[i]), np.asarray(alone[0]), err_msg=name)
        np.testing.assert_array_equal(np.asarray(mask[i]), np.asarray(alone[1]), err_msg=name)
        for k in alone[2]:
            assert int(info[k][i]) == int(alone[2][k]), (name, k)
    # The teachers answer differently on these pairs, so a column reading another's knobs would fail.
    distinct = {np.asarray(labels[i]).tobytes() + np.asarray(mask[i]).tobytes() for i in range(len(names))}
    assert len(distinct) == len(names)


@pytest.mark.parametrize(
    "field,value", [("beta", 0.0), ("gamma", 1.5), ("eps_mistake", -0.1), ("eps_skip", -1.0), ("eps_equal", math.inf)]
)
def test_validate_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"teacher.{field}"):
        dataclasses.replace(teachers.TeacherConfig(), **{field: value}).validate()
    teachers.TeacherConfig().validate()
