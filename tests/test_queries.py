"""Segment cutting and query selection against brute-force Python enumeration."""

from __future__ import annotations

import collections
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.agents import replay
from rebel_jax.preference import queries

EPISODE_LENGTH, NUM_ENVS, CAPACITY, H = 12, 3, 60, 5
_sample_pairs = jax.jit(queries.sample_pairs, static_argnums=(2, 3, 4, 5))
_select = jax.jit(queries.select_queries, static_argnums=(0, 3, 4, 5))


def _fill(num_writes, seed=0):
    """Writes num_writes vector steps; obs = (global time, env, episode id, feature).

    Envs start out of phase; env 2 also terminates early at random, so its episodes vary in length.
    """
    rng = np.random.default_rng(seed)
    obs = np.zeros((CAPACITY, NUM_ENVS, 4), np.float32)
    steps = np.zeros((CAPACITY, NUM_ENVS), np.int32)
    reward = np.zeros((CAPACITY, NUM_ENVS), np.float32)
    history = {}  # (time, env) -> (episode id, episode step)
    step = [0, 4, 9]
    episode = [0, 0, 0]
    for time in range(num_writes):
        row = time % CAPACITY
        for env in range(NUM_ENVS):
            feature = rng.normal()
            obs[row, env] = (time, env, episode[env], feature)
            steps[row, env] = step[env]
            reward[row, env] = rng.normal()
            history[(time, env)] = (episode[env], step[env])
            step[env] += 1
            early = env == 2 and rng.random() < 0.15
            if step[env] == EPISODE_LENGTH or early:
                step[env], episode[env] = 0, episode[env] + 1
    action = obs[..., :2] * 10.0
    buffer = replay.Buffer(
        obs=jnp.asarray(obs),
        action=jnp.asarray(action),
        next_obs=jnp.asarray(obs),
        true_reward=jnp.asarray(reward),
        learned_reward=jnp.zeros_like(jnp.asarray(reward)),
        terminal=jnp.zeros((CAPACITY, NUM_ENVS), bool),
        truncated=jnp.zeros((CAPACITY, NUM_ENVS), bool),
        episode_step=jnp.asarray(steps),
        ptr=jnp.asarray(num_writes % CAPACITY, jnp.int32),
        size=jnp.asarray(min(num_writes, CAPACITY), jnp.int32),
    )
    return buffer, history


def _valid_starts_brute_force(history, num_writes, recent_episodes):
    rows = min(CAPACITY, max(H, -(-recent_episodes * EPISODE_LENGTH // NUM_ENVS)))
    first = max(0, num_writes - rows, num_writes - CAPACITY)
    valid = set()
    for time in range(first, num_writes - H + 1):
        for env in range(NUM_ENVS):
            episodes = {history[(time + t, env)][0] for t in range(H)}
            if len(episodes) == 1 and history[(time, env)][1] + H <= EPISODE_LENGTH:
                valid.add((time, env))
    return valid


@pytest.mark.parametrize("num_writes,recent_episodes", [(40, 8), (40, 100), (20, 8), (150, 8), (150, 100)])
def test_segments_stay_in_one_episode_of_filled_recent_rows(num_writes, recent_episodes):
    buffer, history = _fill(num_writes)
    n = 3000
    sample = jax.jit(queries.sample_segments, static_argnums=(2, 3, 4, 5))
    seg = sample(buffer, jax.random.key(1), n, H, EPISODE_LENGTH, recent_episodes)
    assert seg.obs.shape == (n, H, 4) and seg.action.shape == (n, H, 2) and seg.true_reward.shape == (n, H)
    obs = np.asarray(seg.obs)
    time, env, episode = obs[..., 0].astype(int), obs[..., 1].astype(int), obs[..., 2]
    np.testing.assert_array_equal(time - np.arange(H), np.repeat(time[:, :1], H, 1))  # Consecutive steps...
    np.testing.assert_array_equal(env, np.repeat(env[:, :1], H, 1))  # ...of one env...
    np.testing.assert_array_equal(episode, np.repeat(episode[:, :1], H, 1))  # ...and one episode.
    np.testing.assert_array_equal(np.asarray(seg.action), obs[..., :2] * 10.0)
    rows = time % CAPACITY
    np.testing.assert_array_equal(np.asarray(seg.true_reward), np.asarray(buffer.true_reward)[rows, env])
    sampled = collections.Counter(zip(time[:, 0].tolist(), env[:, 0].tolist(), strict=True))
    valid = _valid_starts_brute_force(history, num_writes, recent_episodes)
    assert valid  # The case is not vacuous.
    assert set(sampled) == valid  # Only valid starts, and all of them.
    expected = n / len(valid)
    assert min(sampled.values()) > 0.4 * expected and max(sampled.values()) < 1.8 * expected


def test_valid_starts_equals_brute_force():
    num_writes, recent = 150, 8
    buffer, history = _fill(num_writes, seed=3)
    valid = np.asarray(jax.jit(queries.valid_starts, static_argnums=(1, 2, 3))(buffer, H, EPISODE_LENGTH, recent))
    rows = valid.shape[0]
    got = {(num_writes - rows + i, e) for i, e in zip(*np.nonzero(valid), strict=True)}
    assert got == _valid_starts_brute_force(history, num_writes, recent)


def _pref_prob_fn(seg_a, seg_b):
    """Four members with different sensitivities to the random feature: (4, N)."""
    diff = jnp.sum(seg_b.obs[..., 3], -1) - jnp.sum(seg_a.obs[..., 3], -1)
    scales = jnp.array([0.1, 0.5, 1.0, 3.0])[:, None]
    offsets = jnp.array([0.0, 0.3, -0.2, 0.1])[:, None]
    return jax.nn.sigmoid(scales * diff + offsets)


def _brute_force_top(probs, sampling, k):
    probs = np.asarray(probs, np.float64)
    if sampling == "disagreement":
        score = probs.std(axis=0)
    else:
        mean = probs.mean(axis=0)
        score = -(mean * np.log(mean) + (1 - mean) * np.log(1 - mean))
    return np.argsort(-score, kind="stable")[:k]


@pytest.mark.parametrize("sampling", ["disagreement", "entropy"])
def test_active_selection_keeps_exactly_the_top_scored_candidates(sampling):
    buffer, _ = _fill(150)
    cfg = queries.QueryConfig(segment_length=H, recent_episodes=8, sampling=sampling, candidate_factor=10, pool="rows")
    key, k = jax.random.key(5), 7
    seg_a, seg_b = _select(cfg, key, buffer, k, EPISODE_LENGTH, _pref_prob_fn, False)
    cand_a, cand_b = _sample_pairs(buffer, key, 10 * k, H, EPISODE_LENGTH, 8)
    top = _brute_force_top(_pref_prob_fn(cand_a, cand_b), sampling, k)
    np.testing.assert_array_equal(np.asarray(seg_a.obs), np.asarray(cand_a.obs)[top])
    np.testing.assert_array_equal(np.asarray(seg_b.obs), np.asarray(cand_b.obs)[top])
    # The selection is not just the first candidates.
    assert not np.array_equal(np.sort(top), np.arange(k))


def test_first_session_is_uniform_static_or_traced():
    buffer, _ = _fill(150)
    cfg = queries.QueryConfig(
        segment_length=H, recent_episodes=8, sampling="disagreement", candidate_factor=4, pool="rows"
    )
    key, k = jax.random.key(6), 5
    select_static = jax.jit(queries.select_queries, static_argnums=(0, 3, 4, 5, 6))
    static = select_static(cfg, key, buffer, k, EPISODE_LENGTH, _pref_prob_fn, True)
    np.testing.assert_array_equal(
        np.asarray(static[0].obs), np.asarray(_sample_pairs(buffer, key, k, H, EPISODE_LENGTH, 8)[0].obs)
    )
    cand_a, cand_b = _sample_pairs(buffer, key, 4 * k, H, EPISODE_LENGTH, 8)
    first_a, first_b = _select(cfg, key, buffer, k, EPISODE_LENGTH, _pref_prob_fn, jnp.asarray(True))
    np.testing.assert_array_equal(np.asarray(first_a.obs), np.asarray(cand_a.obs)[:k])
    np.testing.assert_array_equal(np.asarray(first_b.obs), np.asarray(cand_b.obs)[:k])
    later_a, _ = _select(cfg, key, buffer, k, EPISODE_LENGTH, _pref_prob_fn, jnp.asarray(False))
    top = _brute_force_top(_pref_prob_fn(cand_a, cand_b), "disagreement", k)
    np.testing.assert_array_equal(np.asarray(later_a.obs), np.asarray(cand_a.obs)[top])


def test_select_queries_vmaps_over_seeds():
    buffers = [_fill(150, seed=s)[0] for s in (0, 1)]
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *buffers)
    keys = jax.random.split(jax.random.key(8), 2)
    cfg = queries.QueryConfig(segment_length=H, recent_episodes=8, sampling="entropy", candidate_factor=3)

    def select(key, buffer):
        return queries.select_queries(cfg, key, buffer, 4, EPISODE_LENGTH, _pref_prob_fn, False)

    batched = jax.jit(jax.vmap(select))(keys, stacked)
    for i in range(2):
        alone = jax.jit(select)(keys[i], buffers[i])
        np.testing.assert_array_equal(np.asarray(batched[0].obs[i]), np.asarray(alone[0].obs))


@pytest.mark.parametrize("num_writes", [20, 150])
def test_reward_margin_is_h_times_mean_reward_of_the_window(num_writes):
    buffer, _ = _fill(num_writes)
    rows = min(CAPACITY, max(H, -(-8 * EPISODE_LENGTH // NUM_ENVS)))
    times = range(max(0, num_writes - rows), num_writes)
    rewards = np.asarray(buffer.true_reward)[[t % CAPACITY for t in times]]
    expected = H * rewards.mean()
    margin = jax.jit(queries.reward_margin, static_argnums=(1, 2, 3))(buffer, H, EPISODE_LENGTH, 8)
    np.testing.assert_allclose(float(margin), expected, rtol=1e-5)


@pytest.mark.parametrize(
    "field,value", [("segment_length", 0), ("recent_episodes", 0), ("sampling", "kcenter"), ("candidate_factor", 0)]
)
def test_validate_names_the_field(field, value):
    with pytest.raises(ValueError, match=f"query.{field}"):
        dataclasses.replace(queries.QueryConfig(), **{field: value}).validate()
    with pytest.raises(ValueError, match="query.segment_length"):
        queries.QueryConfig(segment_length=60).validate(episode_length=50)
    queries.QueryConfig().validate(episode_length=1000)
