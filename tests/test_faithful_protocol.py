"""B-Pref's and SURF's protocol: the reward init, query segments from complete episodes,
SURF's step count and growing pool, the reset update and frozen-policy evaluation."""

from __future__ import annotations

import collections
import dataclasses
import math

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.config import Config, ConfigError, EnvConfig, FeedbackConfig, SACConfig, TrainConfig
from rebel_jax.methods import rebel as agent_preference
from rebel_jax.methods import surf
from rebel_jax.methods.rebel import AgentPreferenceConfig
from rebel_jax.preference import queries, reward_train
from rebel_jax.preference import reward_model as rm
from rebel_jax.preference.pretrain import PretrainConfig
from rebel_jax.preference.queries import QueryConfig
from rebel_jax.preference.reward_model import RewardConfig
from rebel_jax.train import Trainer

# -- the reward network's initial weights -------------------------------------------------------


def test_torch_init_is_uniform_within_one_over_sqrt_fan_in_and_narrower_than_lecun():
    cfg = RewardConfig(hidden=256, depth=3)
    obs, act = 24, 6
    params = rm.init(cfg, jax.random.key(0), obs, act, 5).params["params"]
    fan_ins = [obs + act, 256, 256, 256]
    layers = [params[f"Dense_{i}"] for i in range(4)]
    for layer, fan_in in zip(layers, fan_ins, strict=True):
        bound = 1.0 / math.sqrt(fan_in)
        for name in ("kernel", "bias"):
            x = np.asarray(layer[name])
            assert np.abs(x).max() <= bound
            if x.size >= 200:  # U(-b, b): std b / sqrt(3); the bias of the last layer has 3 values.
                np.testing.assert_allclose(x.std(), bound / math.sqrt(3), rtol=0.1)
    # The per-step reward spread at init: PyTorch's default gives a much narrower one than lecun-normal.
    x = jax.random.normal(jax.random.key(1), (4096, obs + act))
    spread = {}
    for init in ("torch", "lecun"):
        c = dataclasses.replace(cfg, init=init)
        p = rm.init(c, jax.random.key(0), obs, act, 5).params
        spread[init] = float(jnp.std(rm.predict(c, p, x[:, :obs], x[:, obs:])))
    assert spread["lecun"] > 3 * spread["torch"]


# -- query segments from the last complete episodes --------------------------------------------


@flax.struct.dataclass
class _Buffer:
    obs: jax.Array
    action: jax.Array
    true_reward: jax.Array
    terminal: jax.Array
    truncated: jax.Array
    episode_step: jax.Array
    ptr: jax.Array
    size: jax.Array


def _history(num_writes, num_envs, episode_length, seed=0):
    """A buffer where env 1 terminates early at random; obs = (time, env, episode id, step)."""
    rng = np.random.default_rng(seed)
    rows = num_writes + 7  # Unwritten rows at the end.
    obs = np.zeros((rows, num_envs, 4), np.float32)
    steps = np.zeros((rows, num_envs), np.int32)
    ends = np.zeros((rows, num_envs), np.float32)
    step, episode, episodes = [0] * num_envs, [0] * num_envs, []
    for t in range(num_writes):
        for e in range(num_envs):
            obs[t, e] = (t, e, episode[e] * 10 + e, step[e])
            steps[t, e] = step[e]
            last = step[e] == episode_length - 1 or (e == 1 and rng.random() < 0.04)
            if last:
                ends[t, e] = 1.0
                episodes.append((t, e, episode[e] * 10 + e, step[e] + 1))  # (end row, env, id, length)
                step[e], episode[e] = 0, episode[e] + 1
            else:
                step[e] += 1
    buffer = _Buffer(
        obs=jnp.asarray(obs),
        action=jnp.asarray(obs[..., :2]),
        true_reward=jnp.asarray(obs[..., 3]),
        terminal=jnp.asarray(ends),
        truncated=jnp.zeros_like(jnp.asarray(ends)),
        episode_step=jnp.asarray(steps),
        ptr=jnp.asarray(num_writes, jnp.int32),
        size=jnp.asarray(num_writes, jnp.int32),
    )
    return buffer, episodes


def test_segments_come_from_the_last_complete_episodes_as_bpref_get_queries():
    episode_length, num_envs, horizon, recent = 30, 3, 6, 7
    buffer, episodes = _history(200, num_envs, episode_length)
    # B-Pref's rule in plain Python: the most recent `recent` complete episodes of length >= H, then a
    # start uniform in [0, L - H). Episodes ending on the same row rank by env.
    eligible = sorted([ep for ep in episodes if ep[3] >= horizon], key=lambda ep: (ep[0], ep[1]))[-recent:]
    allowed = {(ep[2], s) for ep in eligible for s in range(max(ep[3] - horizon, 1))}
    n = 6000
    sample = jax.jit(queries.sample_segments, static_argnums=(2, 3, 4, 5, 6))
    seg = sample(buffer, jax.random.key(3), n, horizon, episode_length, recent, "episodes")
    obs = np.asarray(seg.obs)
    episode_id, step = obs[..., 2], obs[..., 3].astype(int)
    np.testing.assert_array_equal(episode_id, np.repeat(episode_id[:, :1], horizon, 1))  # One episode each...
    np.testing.assert_array_equal(step - step[:, :1], np.broadcast_to(np.arange(horizon), step.shape))  # in order.
    drawn = collections.Counter(zip(episode_id[:, 0].tolist(), step[:, 0].tolist(), strict=True))
    assert set(drawn) == allowed  # Only B-Pref's (episode, start) pairs, and all of them.
    per_episode = collections.Counter(episode_id[:, 0].tolist())
    assert min(per_episode.values()) > 0.6 * n / recent and max(per_episode.values()) < 1.4 * n / recent
    np.testing.assert_array_equal(np.asarray(seg.true_reward), step.astype(np.float32))


def test_episode_pool_needs_a_complete_episode_by_the_first_session():
    cfg = Config(algo="pebble", env=EnvConfig(num_envs=40))
    with pytest.raises(ConfigError, match="env.num_envs=40 is invalid: allowed <= 10 with query.pool='episodes'"):
        cfg.validate()
    dataclasses.replace(cfg, query=QueryConfig(pool="rows")).validate()  # The earlier rule has no such limit.


# -- SURF's session -----------------------------------------------------------------------------


def _labelled_state(cfg, count, stored, pool_capacity, seed=0):
    rng = np.random.default_rng(seed)
    state = rm.init(cfg, jax.random.key(seed), 3, 2, stored)
    if pool_capacity:
        state = state.replace(pool=rm.init_pool(pool_capacity, stored, 3, 2))

    def seg(n):
        return queries.Segments(
            obs=jnp.asarray(rng.normal(size=(n, stored, 3)), jnp.float32),
            action=jnp.asarray(rng.normal(size=(n, stored, 2)), jnp.float32),
            true_reward=jnp.zeros((n, stored)),
        )

    labels = jnp.asarray(rng.integers(0, 2, count), jnp.float32)
    return rm.add_labels(state, seg(count), seg(count), labels, jnp.ones(count)), seg


@pytest.mark.parametrize("count", [10, 100, 300])
def test_surf_session_runs_ceil_reward_update_times_labels_over_batch_steps(count):
    assert int(reward_train.steps_per_label(1000, jnp.asarray(count), 128, jnp.asarray(10))) == math.ceil(
        1000 * count / 128
    )
    # No new pair (the budget is spent): SURF holds no session, so no step runs.
    assert int(reward_train.steps_per_label(1000, jnp.asarray(count), 128, jnp.asarray(0))) == 0
    cfg = RewardConfig(hidden=8, depth=1, batch_size=128, label_capacity=400)
    state, _ = _labelled_state(cfg, count, 4, 0)
    steps = reward_train.steps_per_label(
        7, state.data.count, cfg.batch_size, jnp.asarray(1)
    )  # Few steps: a quick test.
    train = jax.jit(lambda state, key, steps: reward_train.train_iterations(cfg, state, key, (rm.bt_loss(cfg),), steps))
    trained, metrics = train(state, jax.random.key(1), steps)
    assert int(metrics["epochs"]) == math.ceil(7 * count / 128)
    pairs = zip(jax.tree.leaves(state.params), jax.tree.leaves(trained.params), strict=True)
    assert any(not np.array_equal(np.asarray(a), np.asarray(b)) for a, b in pairs)


def test_surf_pool_grows_by_each_session_and_keeps_the_older_pairs():
    cfg = RewardConfig(hidden=8, depth=1)
    state, seg = _labelled_state(cfg, 4, 4, pool_capacity=12)
    first_a, first_b, second_a, second_b = seg(5), seg(5), seg(5), seg(5)
    state = surf.add_unlabelled(state, first_a, first_b)
    state = surf.add_unlabelled(state, second_a, second_b, keep=jnp.asarray(False))  # A no-op session adds none.
    assert int(state.pool.count) == 5
    state = surf.add_unlabelled(state, second_a, second_b)
    assert int(state.pool.count) == 10 and int(state.pool.ptr) == 10
    np.testing.assert_array_equal(np.asarray(state.pool.a.obs[:5]), np.asarray(first_a.obs))
    np.testing.assert_array_equal(np.asarray(state.pool.b.action[5:10]), np.asarray(second_b.action))
    state = surf.add_unlabelled(state, first_a, first_b)  # Full: wraps over the oldest, as SURF's ring.
    assert int(state.pool.count) == 12 and int(state.pool.ptr) == 3


# -- the reset update and frozen-policy evaluation (on the probe task) ---------------------------

MICRO = Config(
    algo="pebble",
    env=EnvConfig(task="probe_point", num_envs=2, episode_length=20),
    sac=SACConfig(hidden=16, batch_size=16, utd=0.5),
    train=TrainConfig(total_steps=120, seed_steps=20, steps_per_round=40, eval_every=40, eval_episodes=2),
    feedback=FeedbackConfig(labels=8, per_session=4, interval=40),
    reward=RewardConfig(hidden=16, depth=1, batch_size=8),
    query=QueryConfig(segment_length=5),
    pretrain=PretrainConfig(steps=20, chunk_size=32, reset_updates=100),
)


@pytest.fixture(scope="module")
def micro():
    trainer = Trainer(MICRO)
    return trainer, jax.jit(trainer.init)(jax.random.key(0))


def test_reset_update_runs_exactly_the_configured_sac_updates_on_a_fresh_critic(micro):
    trainer, ts = micro
    reset = jax.jit(trainer.feedback._reset_critic)
    for updates in (100, 0):
        trainer.cfg = dataclasses.replace(MICRO, pretrain=dataclasses.replace(MICRO.pretrain, reset_updates=updates))
        new = reset(ts.agent, ts.buffer, jax.random.key(1))
        reset = jax.jit(trainer.feedback._reset_critic)  # Retrace with the next count.
        assert int(new.steps) - int(ts.agent.steps) == updates
    trainer.cfg = MICRO
    fresh = trainer.agent.reset_critic(ts.agent, jax.random.split(jax.random.key(1))[0])
    # With no updates the critic is just re-initialised; with 100 the actor has moved too.
    np.testing.assert_array_equal(
        np.asarray(jax.tree.leaves(new.critic_params)[0]), np.asarray(jax.tree.leaves(fresh.critic_params)[0])
    )


def test_evaluation_envs_follow_the_actor_frozen_at_the_episode_start(micro):
    trainer, ts = micro
    step = jax.jit(trainer.vector_step)
    changed = jax.tree.map(lambda x: x + 0.5, ts.agent.actor_params)
    ts = ts.replace(agent=ts.agent.replace(actor_params=changed))  # The actor changes mid-episode (t = 7)...
    mid, _ = step(ts, jnp.int32(7))
    assert jax.tree.all(jax.tree.map(jnp.array_equal, mid.eval_policy, ts.eval_policy))  # ...evaluation keeps its own.
    acts = jax.jit(trainer._act)(ts, jnp.int32(7), jax.random.key(2))[trainer.num_train :]
    frozen = trainer.agent.act_deterministic(ts.eval_policy, ts.env.obs[trainer.num_train :])
    live = trainer.agent.act_deterministic(changed, ts.env.obs[trainer.num_train :])
    np.testing.assert_allclose(np.asarray(acts), np.asarray(frozen), rtol=1e-6)
    assert not np.allclose(np.asarray(acts), np.asarray(live))
    boundary, _ = step(ts, jnp.int32(MICRO.env.episode_length))  # A new episode takes the current actor.
    np.testing.assert_array_equal(
        np.asarray(jax.tree.leaves(boundary.eval_policy)[0]), np.asarray(jax.tree.leaves(changed)[0])
    )


# -- REBEL's on-policy V ---------------------------------------------------------------


@pytest.mark.parametrize("size", [(0, 0), pytest.param((1, 5), marks=pytest.mark.heavy)])  # (1, 5): make test-heavy
def test_onpolicy_value_is_the_discounted_return_of_the_last_evaluation_episode(size):
    episodes, horizon = size  # (0, 0): every evaluation episode, whole; else the first `horizon` steps of one.
    rebel = AgentPreferenceConfig(lam=-0.1, gamma=0.9, episodes=episodes, horizon=horizon)
    cfg = dataclasses.replace(MICRO, algo="rebel", rebel=rebel)
    trainer = Trainer(cfg)
    ts = jax.jit(trainer.init)(jax.random.key(4))
    step, length, n = jax.jit(trainer.vector_step), cfg.env.episode_length, trainer.num_train
    after = []  # The evaluation environments' observation after each step of the second episode.
    for t in range(2 * length):
        if t == length:
            frozen = ts.agent.actor_params  # The second episode's evaluation policy.
        ts, _ = step(ts, jnp.int32(t))
        if t >= length:
            after.append(np.asarray(ts.env.obs[n:]))
    obs, actions, _ = trainer.method.value_trajectories(trainer, ts, jax.random.key(0), None)
    kept, steps = episodes or cfg.train.eval_episodes, horizon or length
    assert obs.shape[:2] == (kept, steps)
    # A trajectory of the environment: each observation is the one the previous step led to...
    np.testing.assert_array_equal(np.swapaxes(np.asarray(obs), 0, 1)[1:], np.stack(after)[: steps - 1, :kept])
    # ...under the policy frozen at the episode's start (its mean action).
    expected = trainer.agent.act_deterministic(frozen, obs)
    np.testing.assert_allclose(np.asarray(actions), np.asarray(expected), rtol=1e-5, atol=1e-6)
    # V: the paper's discounted sum over the horizon (default the whole episode), as a plain loop over steps.
    params = ts.reward.params
    values = np.zeros(cfg.reward.ensemble_size)
    for h in range(steps):
        values += 0.9**h * np.asarray(rm.predict(cfg.reward, params, obs[:, h], actions[:, h])).mean(axis=1)
    got = agent_preference.agent_value(cfg.reward, params, obs, actions, 0.9, "discounted")
    np.testing.assert_allclose(np.asarray(got), values, rtol=1e-5)


def test_onpolicy_value_needs_a_complete_evaluation_episode_by_the_first_session():
    cfg = Config(algo="rebel", env=EnvConfig(num_envs=20), query=QueryConfig(pool="rows"))
    with pytest.raises(ConfigError, match="with rebel.source='onpolicy'"):
        cfg.validate()
    dataclasses.replace(cfg, rebel=AgentPreferenceConfig(source="replay")).validate()
