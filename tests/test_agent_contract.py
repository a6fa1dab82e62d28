"""The Agent interface (``rebel_jax.agents.base``): SAC and DrQ-v2 driven through one generic code path, as the trainer
drives them, give what their own networks and update steps give when called directly; their update schedules
match Python loops of B-Pref's and DrQ-v2's rules."""

from __future__ import annotations

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.agents.base import Agent, UpdateSchedule
from rebel_jax.agents.drqv2 import DrQV2, DrQV2Config, PixelTransition, std_schedule, truncated_sample
from rebel_jax.agents.networks import mode_action, sample_action
from rebel_jax.agents.replay import Transition
from rebel_jax.agents.sac import SAC
from rebel_jax.config import SACConfig

OBS, ACTIONS, BATCH, FRAMES = 5, 2, 8, (16, 16, 9)


def _sac() -> Agent:
    return SAC(SACConfig(hidden=16, depth=2, batch_size=BATCH), OBS, ACTIONS)


def _drqv2() -> Agent:
    return DrQV2(DrQV2Config(feature_dim=8, hidden=16, batch_size=BATCH, std_steps=100), FRAMES, ACTIONS)


def _batch(pixels: bool, key: jax.Array):
    keys = jax.random.split(key, 5)
    action = jax.random.uniform(keys[1], (BATCH, ACTIONS), minval=-1, maxval=1)
    reward, discount = jax.random.normal(keys[2], (BATCH,)), jnp.ones(BATCH)
    if pixels:
        obs, nxt = (jax.random.randint(k, (BATCH, *FRAMES), 0, 256).astype(jnp.uint8) for k in keys[3:5])
        return PixelTransition(obs=obs, action=action, reward=reward, discount=discount, next_obs=nxt)
    obs, nxt = (jax.random.normal(k, (BATCH, OBS)) for k in keys[3:5])
    return Transition(obs=obs, action=action, reward=reward, next_obs=nxt, discount=discount)


def generic(agent: Agent, key: jax.Array, batch, step: jax.Array) -> dict:
    """The calls the trainer makes, through the interface only."""
    key_init, key_act, key_update, key_reset = jax.random.split(key, 4)
    state = agent.init(key_init)
    updated, metrics = agent.update(state, batch, key_update, step)
    return {
        "state": state,
        "act": agent.act(state, batch.obs, key_act, step),
        "mean": agent.mean_action(agent.policy(state), batch.obs),
        "updated": updated,
        "metrics": {k: metrics[k] for k in agent.metric_names},
        "reset": agent.reset_critic(updated, key_reset),
    }


def direct_sac(sac, key: jax.Array, batch) -> dict:
    """SAC's own networks and update (the calls the state trainer made before the interface)."""
    key_init, key_act, key_update, key_reset = jax.random.split(key, 4)
    state = sac.init(key_init)
    mean, log_std = sac.actor.apply(state.actor_params, batch.obs)
    updated, metrics = sac.update(state, batch, key_update)
    critic = sac._init_critic(key_reset)
    reset = updated.replace(critic_params=critic, target_critic_params=critic, critic_opt=sac.critic_opt.init(critic))
    return {
        "state": state,
        "act": sample_action(mean, log_std, key_act)[0],
        "mean": mode_action(sac.actor.apply(state.actor_params, batch.obs)[0]),
        "updated": updated,
        "metrics": metrics,
        "reset": reset,
    }


def direct_drqv2(drq, key: jax.Array, batch, step: jax.Array) -> dict:
    """DrQ-v2's own networks and update (the calls the pixel trainer made before the interface)."""
    key_init, key_act, key_update, key_reset = jax.random.split(key, 4)
    state = drq.init(key_init)
    features = drq.encoder.apply(state.encoder_params, batch.obs)
    mean = drq.actor.apply(state.actor_params, features)
    updated, metrics = drq.update(state, batch, key_update, step)
    critic = drq._init_critic(key_reset)
    reset = updated.replace(critic_params=critic, target_critic_params=critic, critic_opt=drq.optimizer.init(critic))
    return {
        "state": state,
        "act": truncated_sample(mean, std_schedule(drq.cfg, step), key_act, None),
        "mean": mean,
        "updated": updated,
        "metrics": metrics,
        "reset": reset,
    }


@pytest.mark.parametrize("pixels", [False, True], ids=["sac", "drqv2"])
def test_both_agents_through_the_interface_equal_their_direct_calls(pixels):
    agent = _drqv2() if pixels else _sac()
    assert isinstance(agent, Agent)
    key, step = jax.random.key(3), jnp.int32(40)
    batch = _batch(pixels, jax.random.key(4))
    got = jax.jit(lambda key, batch, step: generic(agent, key, batch, step))(key, batch, step)
    if pixels:
        expected = jax.jit(lambda key, batch, step: direct_drqv2(agent, key, batch, step))(key, batch, step)
    else:
        expected = jax.jit(lambda key, batch: direct_sac(agent, key, batch))(key, batch)
    chex.assert_trees_all_equal(got, expected)
    assert got["act"].shape == (BATCH, ACTIONS) and bool(jnp.all(jnp.abs(got["act"]) <= 1))
    assert int(got["updated"].steps) == 1 and set(got["metrics"]) == set(agent.metric_names)


def _learning_loop(t: int, num_envs: int, seed_steps: int, pixels: bool, utd: float, every: int) -> tuple[bool, int]:
    """(whether vector step t updates, how many updates): B-Pref's SAC updates ``utd`` times per env step once
    ``step >= num_seed_steps`` counting the step taken; DrQ-v2 updates every ``update_every`` agent steps once
    ``global_step >= num_seed_frames`` counting the steps before (drqv2.py:233, train.py:173-185)."""
    if not pixels:
        return (t + 1) * num_envs >= seed_steps, max(1, round(utd * num_envs))
    updates = sum(1 for s in range(t * num_envs, (t + 1) * num_envs) if s % every == 0)
    return t * num_envs >= seed_steps and updates > 0, updates


@pytest.mark.parametrize("pixels,num_envs,every", [(False, 3, 1), (True, 1, 2), (True, 2, 2), (True, 4, 2)])
def test_update_schedules_follow_their_originals(pixels, num_envs, every):
    if pixels:
        agent = DrQV2(DrQV2Config(update_every=every), FRAMES, ACTIONS)
    else:
        agent = _sac()
    schedule = agent.schedule(num_envs)
    assert isinstance(schedule, UpdateSchedule)
    for t in range(12):
        learning, updates = _learning_loop(t, num_envs, 8, pixels, agent.cfg.utd if not pixels else 1.0, every)
        assert bool(schedule.learning(jnp.int32(t), num_envs, 8)) == learning, t
        if learning:
            assert schedule.per_step == updates, t
    np.testing.assert_array_equal(schedule.period, max(1, every // num_envs) if pixels else 1)
