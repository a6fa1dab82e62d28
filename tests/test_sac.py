"""SAC on probe environments with known optimal values, and its pure-function contracts."""

from __future__ import annotations

import dataclasses
import functools

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from rebel_jax.agents.networks import MLP, Actor, sample_action
from rebel_jax.agents.sac import (
    SAC,
    Transition,
    gradient_step,
    make_actor_loss,
    make_alpha_loss,
    make_critic_loss,
    update_flops,
)
from rebel_jax.config import SACConfig

# One config and one compiled training loop serve all four probes (CPU compiles are slow).
# The temperature is nearly fixed and tiny, so soft values equal the hard ones to ~1e-4.
GAMMA = 0.9
PROBE = SACConfig(
    hidden=32,
    depth=2,
    batch_size=64,
    actor_lr=1e-3,
    critic_lr=3e-3,
    alpha_lr=1e-9,
    init_temperature=1e-5,
    gamma=GAMMA,
    tau=0.05,
    target_every=1,
)
PROBE_OBS, PROBE_ACT, PROBE_STEPS = 2, 1, 1500
TOL = 0.05
S0, S1 = np.array([1.0, 0.0]), np.array([0.0, 1.0])


@functools.cache
def _probe_agent() -> SAC:
    return SAC(PROBE, PROBE_OBS, PROBE_ACT)


@functools.cache
def _probe_run():
    agent = _probe_agent()

    @jax.jit
    def run(key, batches):
        key_init, key_steps = jax.random.split(key)
        keys = jax.random.split(key_steps, PROBE_STEPS)
        return jax.lax.scan(lambda state, xs: agent.update(state, *xs), agent.init(key_init), (batches, keys))

    return run


def _train(make_batch, seed=0):
    """Runs PROBE_STEPS updates on batches from ``make_batch(key, n)``; returns the SAC state."""
    key_batches, key_run = jax.random.split(jax.random.key(seed))
    keys = jax.random.split(key_batches, PROBE_STEPS)
    batches = jax.vmap(lambda k: make_batch(k, PROBE.batch_size))(keys)
    batches = jax.tree.map(lambda x: np.asarray(x, np.float32), batches)  # Strong dtypes: one compile for all.
    state, metrics = _probe_run()(key_run, batches)
    assert np.all(np.isfinite(metrics["critic_loss"]))
    return state


def _signs(key, n):
    return jnp.where(jax.random.bernoulli(key, 0.5, (n,)), 1.0, -1.0)


def _uniform_actions(key, n, action_size=PROBE_ACT):
    return jax.random.uniform(key, (n, action_size), minval=-1.0, maxval=1.0)


def _q(state, obs, action):
    q1, q2 = _probe_agent().q_values(state.critic_params, jnp.asarray(obs), jnp.asarray(action))
    return np.asarray(q1), np.asarray(q2)


ACTIONS = np.array([[-0.9], [0.0], [0.9]])


def test_probe_constant_reward_terminal():
    """One step, reward 1, terminal: Q = 1 everywhere."""

    def batch(key, n):
        obs = jnp.broadcast_to(jnp.asarray(S0), (n, PROBE_OBS))
        return Transition(obs, _uniform_actions(key, n), jnp.ones(n), obs, jnp.zeros(n))

    q1, q2 = _q(_train(batch), np.tile(S0, (3, 1)), ACTIONS)
    np.testing.assert_allclose(q1, 1.0, atol=TOL)
    np.testing.assert_allclose(q2, 1.0, atol=TOL)


def test_probe_reward_equals_observation():
    """One step, obs = (s, 0) with s in {-1, +1}, reward = s, terminal: Q(s, .) = s."""

    def batch(key, n):
        key_obs, key_act = jax.random.split(key)
        s = _signs(key_obs, n)
        obs = jnp.stack([s, jnp.zeros(n)], axis=-1)
        return Transition(obs, _uniform_actions(key_act, n), s, obs, jnp.zeros(n))

    state = _train(batch)
    for s in (-1.0, 1.0):
        q1, q2 = _q(state, np.tile([s, 0.0], (3, 1)), ACTIONS)
        np.testing.assert_allclose(q1, s, atol=TOL)
        np.testing.assert_allclose(q2, s, atol=TOL)


def test_probe_two_step_chain():
    """s0 -> s1 (reward 0) -> end (reward 1): Q(s1, .) = 1, Q(s0, .) = gamma (entropy term ~1e-4)."""

    def batch(key, n):
        key_obs, key_act = jax.random.split(key)
        first = _signs(key_obs, n) > 0
        obs = jnp.where(first[:, None], S0, S1)
        reward = jnp.where(first, 0.0, 1.0)
        discount = jnp.where(first, 1.0, 0.0)
        return Transition(obs, _uniform_actions(key_act, n), reward, jnp.broadcast_to(S1, obs.shape), discount)

    state = _train(batch)
    q1_s1, q2_s1 = _q(state, np.tile(S1, (3, 1)), ACTIONS)
    q1_s0, q2_s0 = _q(state, np.tile(S0, (3, 1)), ACTIONS)
    np.testing.assert_allclose(np.minimum(q1_s1, q2_s1), 1.0, atol=TOL)
    np.testing.assert_allclose(np.minimum(q1_s0, q2_s0), GAMMA, atol=TOL)


def test_probe_action_reward():
    """One step, reward = action: Q(s, a) = a and the deterministic action goes to +1."""

    def batch(key, n):
        obs = jnp.broadcast_to(jnp.asarray(S0), (n, PROBE_OBS))
        action = _uniform_actions(key, n)
        return Transition(obs, action, action[:, 0], obs, jnp.zeros(n))

    state = _train(batch)
    q1, q2 = _q(state, np.tile(S0, (3, 1)), ACTIONS)
    np.testing.assert_allclose(q1, ACTIONS[:, 0], atol=TOL)
    np.testing.assert_allclose(q2, ACTIONS[:, 0], atol=TOL)
    action = _probe_agent().act_deterministic(state.actor_params, jnp.asarray(S0[None]))
    assert float(action[0, 0]) > 0.9


def test_alpha_loss_moves_temperature_towards_target_entropy():
    """Eq. 18: entropy above the target (-|A|) lowers alpha, below raises it."""
    loss = make_alpha_loss(action_size=2)
    grad = jax.grad(lambda log_alpha, entropy: loss(log_alpha, None, None, entropy=entropy)[0])
    assert float(grad(jnp.log(0.1), jnp.asarray(0.0))) > 0  # H = 0 > -2: descent lowers log alpha.
    assert float(grad(jnp.log(0.1), jnp.asarray(-3.0))) < 0
    np.testing.assert_allclose(float(grad(jnp.log(0.1), jnp.asarray(0.0))), 0.1 * 2.0, rtol=1e-6)


def _random_batch(seed, n, obs_size=3, action_size=2):
    rng = np.random.default_rng(seed)
    return Transition(
        obs=rng.normal(size=(n, obs_size)).astype(np.float32),
        action=rng.uniform(-1.0, 1.0, (n, action_size)).astype(np.float32),
        reward=rng.normal(size=n).astype(np.float32),
        next_obs=rng.normal(size=(n, obs_size)).astype(np.float32),
        discount=(rng.uniform(size=n) < 0.9).astype(np.float32),
    )


def _stack(trees):
    return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


SMALL = SACConfig(hidden=16, depth=2, batch_size=8, target_every=3, tau=0.5)


@functools.cache
def _small():
    """A small agent with its jitted init and update, shared by the tests below."""
    agent = SAC(SMALL, 3, 2)
    return agent, jax.jit(agent.init), jax.jit(agent.update)


@pytest.mark.heavy  # make test checks vmapped seeds on whole runs (test_train.py)
def test_update_vmapped_over_seeds_equals_separate_calls():
    agent, init, update = _small()
    keys = jax.random.split(jax.random.key(0), 3)
    batches = [_random_batch(i, 8) for i in range(3)]
    update_keys = jax.random.split(jax.random.key(2), 3)
    states = [init(key) for key in keys]
    batched = jax.jit(jax.vmap(agent.update))(_stack(states), _stack(batches), update_keys)
    for i in range(3):
        single = update(states[i], batches[i], update_keys[i])
        jax.tree.map(lambda b, s, i=i: np.testing.assert_allclose(b[i], s, rtol=1e-5, atol=1e-6), batched, single)


def _tree_np(tree):
    return jax.tree.map(np.asarray, tree)


def test_target_moves_only_every_target_every_steps():
    _, init, update = _small()
    state = init(jax.random.key(0))
    moved = []
    for i in range(7):
        before = _tree_np(state.target_critic_params)
        state, _ = update(state, _random_batch(100 + i, 8), jax.random.key(i))
        after, online = _tree_np(state.target_critic_params), _tree_np(state.critic_params)
        moved.append(all(np.any(a != b) for a, b in zip(jax.tree.leaves(after), jax.tree.leaves(before), strict=True)))
        expected = jax.tree.map(lambda t, o: t + SMALL.tau * (o - t), before, online) if moved[-1] else before
        jax.tree.map(lambda a, e: np.testing.assert_allclose(a, e, rtol=1e-6, atol=1e-7), after, expected)
    assert moved == [True, False, False, True, False, False, True]
    assert int(state.steps) == 7


def test_gradient_step_zero_loss_leaves_params_unchanged():
    params = {"w": jnp.arange(6.0).reshape(2, 3), "b": jnp.ones(3)}
    optimizer = optax.adam(1e-2)

    def zero_loss(p, batch, key):
        del batch, key  # Unused.
        value = 0.0 * sum(jnp.sum(x) for x in jax.tree.leaves(p))
        return value, {"loss": value}

    step = jax.jit(gradient_step, static_argnums=(0, 1))
    new, _, metrics = step(zero_loss, optimizer, params, optimizer.init(params), None, jax.random.key(0))
    jax.tree.map(np.testing.assert_array_equal, new, params)
    assert float(metrics["loss"]) == 0.0

    def square_loss(p, batch, key):
        del batch, key  # Unused.
        value = jnp.sum(jnp.square(p["w"])) + jnp.sum(jnp.square(p["b"]))
        return value, {"loss": value}

    moved, _, _ = step(square_loss, optimizer, params, optimizer.init(params), None, jax.random.key(0))
    assert float(jnp.sum(jnp.square(moved["b"]))) < float(jnp.sum(jnp.square(params["b"])))


def test_sample_action_log_prob_matches_naive_formula():
    key_mean, key_std, key_sample = jax.random.split(jax.random.key(0), 3)
    mean = jax.random.normal(key_mean, (1000, 3))
    log_std = jax.random.uniform(key_std, (1000, 3), minval=-2.0, maxval=0.5)
    action, log_prob = sample_action(mean, log_std, key_sample)
    eps = np.asarray(jax.random.normal(key_sample, mean.shape), np.float64)
    mean, std = np.asarray(mean, np.float64), np.exp(np.asarray(log_std, np.float64))
    u = mean + std * eps
    gaussian = -0.5 * eps**2 - np.log(std) - 0.5 * np.log(2 * np.pi)
    naive = np.sum(gaussian - np.log(1 - np.tanh(u) ** 2), axis=-1)  # Float64: no saturation at |u| < 9.
    np.testing.assert_allclose(action, np.tanh(u), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(log_prob, naive, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("precision", ["tf32", "highest", "bf16"])
def test_actor_log_std_bounded_and_float32(precision):
    actor = Actor(16, 2, 2, log_std_min=-5.0, log_std_max=2.0, precision=precision)
    obs = 100.0 * jax.random.normal(jax.random.key(1), (64, 3))
    params = actor.init(jax.random.key(0), obs)
    mean, log_std = actor.apply(params, obs)
    assert mean.dtype == log_std.dtype == jnp.float32
    assert float(log_std.min()) >= -5.0 and float(log_std.max()) <= 2.0


def test_reset_critic_keeps_actor_and_alpha():
    agent, init, update = _small()
    state, _ = update(init(jax.random.key(0)), _random_batch(1, 8), jax.random.key(2))
    reset = jax.jit(agent.reset_critic)(state, jax.random.key(3))
    jax.tree.map(np.testing.assert_array_equal, reset.actor_params, state.actor_params)
    np.testing.assert_array_equal(reset.log_alpha, state.log_alpha)
    jax.tree.map(np.testing.assert_array_equal, reset.target_critic_params, reset.critic_params)
    assert not np.allclose(jax.tree.leaves(reset.critic_params)[1], jax.tree.leaves(state.critic_params)[1]), (
        "critic was not re-initialised"
    )


def test_update_flops_bpref_size():
    """B-Pref walker sizes: about 35 GFLOP per update (2 x 1024 MLPs, batch 1024)."""
    flops = update_flops(SACConfig(), obs_size=24, action_size=6)
    assert 34e9 < flops < 37e9


class _SharedInputDoubleCritic(nn.Module):
    """The twin critic before the update was reshaped: both members read one shared input
    (``in_axes=None``), which XLA merges into one wide first layer. Kept as the reference."""

    hidden: int
    depth: int
    precision: str = "tf32"

    @nn.compact
    def __call__(self, obs, action):
        twin = nn.vmap(
            MLP, variable_axes={"params": 0}, split_rngs={"params": True}, in_axes=None, out_axes=0, axis_size=2
        )
        q = twin(self.hidden, self.depth, 1, self.precision)(jnp.concatenate([obs, action], axis=-1))
        return q[0, ..., 0], q[1, ..., 0]


def _reference_sac(cfg: SACConfig, obs_size: int, action_size: int) -> SAC:
    """A :class:`SAC` whose losses use :class:`_SharedInputDoubleCritic` (the previous formulation)."""
    ref = SAC(cfg, obs_size, action_size)
    ref.critic = _SharedInputDoubleCritic(cfg.hidden, cfg.depth, cfg.precision)
    ref.critic_loss = make_critic_loss(ref.actor, ref.critic, cfg.gamma)
    ref.actor_loss = make_actor_loss(ref.actor, ref.critic)
    return ref


@pytest.mark.parametrize("precision", ["tf32", "highest"])
def test_update_equals_previous_formulation(precision):
    """Seven updates (the target moves on three) from one state give the previous update's states
    and metrics; the parameters (and so checkpoints) have the same structure and initial values."""
    cfg = dataclasses.replace(SMALL, precision=precision)
    agent, ref = SAC(cfg, 3, 2), _reference_sac(cfg, 3, 2)
    state = jax.jit(agent.init)(jax.random.key(0))
    ref_state = jax.jit(ref.init)(jax.random.key(0))
    assert jax.tree.structure(state) == jax.tree.structure(ref_state)
    jax.tree.map(np.testing.assert_array_equal, state, ref_state)
    update, ref_update = jax.jit(agent.update), jax.jit(ref.update)
    for i in range(7):
        batch, key = _random_batch(200 + i, 8), jax.random.key(10 + i)
        state, metrics = update(state, batch, key)
        ref_state, ref_metrics = ref_update(ref_state, batch, key)
        close = functools.partial(np.testing.assert_allclose, rtol=1e-5, atol=1e-6)
        jax.tree.map(close, (state, metrics), (ref_state, ref_metrics))
    assert int(state.steps) == 7
