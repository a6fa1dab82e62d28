"""DrQ-v2 on a pixel task in the scanned round: ``--algo drqv2`` (true reward, no preferences yet).

The same shape as :class:`rebel_jax.train.Trainer`: ``init(key)``, ``round(state, r)`` (one
``lax.scan`` over vector steps, the round index unbatched) and ``evaluate(policy, key)``, so
:func:`rebel_jax.train.compiled` jits and vmaps it over seeds and the CLI's host loop runs it.
Episodes of all environments start together every ``episode_length`` agent steps (a ``lax.cond``
on the unbatched step); ``eval_episodes`` more environments follow the mean action of the policy
frozen at the episode start.

DrQ-v2's schedule (facebookresearch/drqv2 c0c650b, train.py:124-190; SURF's pixel branch
pixel_train_drqv2.py the same), counted in agent steps per seed (one transition, two frames):

- ``train.seed_steps`` agent steps of uniform random actions and no updates (DrQ-v2: 4,000 seed
  frames = 2,000 agent steps, config.yaml:11 and ``num_expl_steps: 2000``, config.yaml:43; drqv2.py:173-174);
- then one update every ``drqv2.update_every`` agent steps (drqv2.py:233): ``num_envs /
  update_every`` updates per vector step, or one every ``update_every / num_envs`` vector steps;
- the exploration std read at the seed's agent-step count (DrQ-v2's ``global_step``).

Transitions go to :mod:`rebel_jax.frame_replay` (each frame once); updates sample DrQ-v2's n-step
transitions from it.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from rebel_jax import frame_replay
from rebel_jax.config import Config
from rebel_jax.drqv2 import DrQV2, DrQV2State
from rebel_jax.envs import State, make_env
from rebel_jax.train import EpisodeStats, _all_finite

METRICS = ("critic_loss", "actor_loss", "q", "target_q", "std")

DEFAULT_CAPACITY = 100_000
"""Replay transitions per seed when ``train.buffer_capacity`` is 0 (at most ``train.total_steps``): 2.13 GB of
84x84 frames per seed (:mod:`rebel_jax.frame_replay`). DrQ-v2 keeps 1M (config.yaml:18), 21 GB per seed."""


@struct.dataclass
class PixelTrainState:
    """Everything one seed carries from round to round.

    Attributes:
      sac: the DrQ-v2 agent's state (named as :class:`rebel_jax.train.TrainState`'s learner).
      buffer: the frame replay of training transitions.
      env: batched env state, ``num_envs`` training then ``eval_episodes`` evaluation envs.
      episodes: running and last true returns.
      key: the PRNG key of the run.
      eval_policy: ``{"encoder": ..., "actor": ...}`` the evaluation environments follow, frozen at
        each episode start.
    """

    sac: DrQV2State
    buffer: frame_replay.FrameBuffer
    env: State
    episodes: EpisodeStats
    key: jax.Array
    eval_policy: Any


def policy_of(agent_state: DrQV2State) -> dict:
    """The deterministic policy's parameters: encoder and actor."""
    return {"encoder": agent_state.encoder_params, "actor": agent_state.actor_params}


class PixelTrainer:
    """Builds the pure functions of one seed's DrQ-v2 run from a :class:`Config` (``algo='drqv2'``)."""

    def __init__(self, cfg: Config):
        self.cfg = cfg.validate()
        if cfg.algo != "drqv2":
            raise ValueError(f"PixelTrainer runs --algo drqv2, not {cfg.algo!r}")
        self.env = make_env(cfg.env.task, solver=cfg.env.solver, episode_length=cfg.env.episode_length)
        self.agent = DrQV2(cfg.drqv2, self.env.observation_shape, self.env.action_size)
        self.num_train = cfg.env.num_envs
        self.num_all = cfg.env.num_envs + cfg.train.eval_episodes
        self.episode_length = self.env.episode_length  # agent steps
        self.steps_per_round = cfg.train.steps_per_round // cfg.env.num_envs  # vector steps
        every = cfg.drqv2.update_every
        self.updates_per_step = max(1, self.num_train // every)
        self.update_period = max(1, every // self.num_train)  # vector steps between updates
        self.capacity = cfg.train.buffer_capacity or min(cfg.train.total_steps, DEFAULT_CAPACITY)
        self.trace_count = 0

    def policy_params(self, ts: PixelTrainState) -> dict:
        """What :meth:`evaluate` takes: the encoder and the actor."""
        return policy_of(ts.sac)

    def init(self, key: jax.Array) -> PixelTrainState:
        """A fresh run of one seed."""
        key, key_agent, key_env = jax.random.split(key, 3)
        agent = self.agent.init(key_agent)
        height, width, _ = self.env.observation_shape
        buffer = frame_replay.init(
            self.capacity,
            self.num_train,
            (height, width, 3),
            self.env.action_size,
            self.episode_length,
            self.env.frames,
        )
        return PixelTrainState(
            sac=agent,
            buffer=buffer,
            env=self._reset_envs(key_env),
            episodes=EpisodeStats(jnp.zeros(self.num_all), *[jnp.full((), jnp.nan, jnp.float32)] * 2),
            key=key,
            eval_policy=policy_of(agent),
        )

    def _reset_envs(self, key: jax.Array) -> State:
        return jax.vmap(self.env.reset)(jax.random.split(key, self.num_all))

    def _mean_action(self, policy: dict, obs: jax.Array) -> jax.Array:
        return self.agent.actor.apply(policy["actor"], self.agent.encoder.apply(policy["encoder"], obs))

    def _act(self, ts: PixelTrainState, t: jax.Array, key: jax.Array) -> jax.Array:
        key_policy, key_random = jax.random.split(key)
        obs, n = ts.env.obs, self.num_train
        explore = self.agent.act(ts.sac, obs[:n], key_policy, t * n)
        random = jax.random.uniform(key_random, explore.shape, minval=-1.0, maxval=1.0)
        train_action = jnp.where(t * n < self.cfg.train.seed_steps, random, explore)
        return jnp.concatenate([train_action, self._mean_action(ts.eval_policy, obs[n:])])

    def _record(self, ts: PixelTrainState, nxt: State, action: jax.Array, t: jax.Array):
        n = self.num_train
        truncated = nxt.info["truncation"]
        step = frame_replay.FrameStep(
            obs=ts.env.obs[:n],
            action=action[:n],
            next_obs=nxt.obs[:n],
            reward=nxt.reward[:n],
            terminal=(nxt.done - truncated)[:n],
            truncated=truncated[:n],
            episode_step=(t % self.episode_length).astype(jnp.int32),
        )
        episodes = ts.episodes.after_step(nxt.reward, nxt.done, n)
        return frame_replay.add(ts.buffer, step), episodes

    def _updates(self, agent: DrQV2State, buffer: frame_replay.FrameBuffer, key: jax.Array, agent_step: jax.Array):
        cfg = self.cfg.drqv2

        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            batch = frame_replay.sample(buffer, key_sample, cfg.batch_size, cfg.nstep, cfg.gamma)
            return self.agent.update(state, batch, key_update, agent_step)

        agent, metrics = jax.lax.scan(one, agent, jax.random.split(key, self.updates_per_step))
        return agent, jax.tree.map(jnp.mean, metrics)

    def vector_step(self, ts: PixelTrainState, t: jax.Array) -> tuple[PixelTrainState, dict]:
        """One step of every environment, then DrQ-v2's updates due at this step.

        Args:
          ts: one seed's state.
          t: the vector-step index in the run, the same for every seed (unbatched).
        """
        key, key_reset, key_act, key_update = jax.random.split(ts.key, 4)
        new_episode = (t % self.episode_length == 0) & (t > 0)
        env_state, eval_policy = jax.lax.cond(
            new_episode,
            lambda: (self._reset_envs(key_reset), policy_of(ts.sac)),
            lambda: (ts.env, ts.eval_policy),
        )
        ts = ts.replace(env=env_state, key=key, eval_policy=eval_policy)
        action = self._act(ts, t, key_act)
        nxt = jax.vmap(self.env.step)(ts.env, action)
        buffer, episodes = self._record(ts, nxt, action, t)
        # DrQ-v2 updates from its first step past seeding, when the step is a multiple of update_every.
        learning = (t * self.num_train >= self.cfg.train.seed_steps) & (t % self.update_period == 0)
        zeros = {k: jnp.zeros(()) for k in METRICS}
        agent, metrics = jax.lax.cond(
            learning,
            lambda: self._updates(ts.sac, buffer, key_update, t * self.num_train),
            lambda: (ts.sac, zeros),
        )
        ts = ts.replace(sac=agent, buffer=buffer, env=nxt, episodes=episodes)
        return ts, dict(metrics, learning=learning.astype(jnp.float32))

    def round(self, ts: PixelTrainState, round_index: jax.Array) -> tuple[PixelTrainState, dict]:
        """``steps_per_round`` agent steps per seed with their updates, as one ``lax.scan``.

        Returns:
          The new state and the round's metrics: DrQ-v2's losses averaged over the round's updates,
          the last finished training and evaluation returns, and ``diverged``.
        """
        self.trace_count += 1  # Python side effect: counts traces, not calls.
        before = ts.episodes
        t0 = round_index * self.steps_per_round
        ts, metrics = jax.lax.scan(self.vector_step, ts, t0 + jnp.arange(self.steps_per_round))
        learning = metrics.pop("learning")
        weight = learning / jnp.maximum(learning.sum(), 1.0)
        summary = {k: jnp.sum(v * weight) for k, v in metrics.items()}
        summary["train_return"] = ts.episodes.train_return
        summary["eval_return"] = ts.episodes.eval_return
        returns_ok = [
            jnp.isfinite(new) | (jnp.isnan(new) & jnp.isnan(old))
            for new, old in (
                (ts.episodes.train_return, before.train_return),
                (ts.episodes.eval_return, before.eval_return),
            )
        ]
        finite = _all_finite(({k: summary[k] for k in METRICS}, ts.sac, ts.episodes.running))
        summary["diverged"] = 1.0 - (finite & returns_ok[0] & returns_ok[1]).astype(jnp.float32)
        return ts, summary

    def evaluate(self, policy: dict, key: jax.Array, random_actions: bool | jax.Array = False) -> jax.Array:
        """Mean true return of ``eval_episodes`` episodes of the mean action of ``policy`` (:func:`policy_of`),
        or of uniform random actions on the same initial states (as :meth:`Trainer.evaluate`)."""
        key_reset, key_actions = jax.random.split(key)
        state = jax.vmap(self.env.reset)(jax.random.split(key_reset, self.cfg.train.eval_episodes))

        def body(carry, key):
            state, total = carry
            uniform = jax.random.uniform(key, (state.obs.shape[0], self.env.action_size), minval=-1.0, maxval=1.0)
            action = jnp.where(random_actions, uniform, self._mean_action(policy, state.obs))
            state = jax.vmap(self.env.step)(state, action)
            return (state, total + state.reward), None

        keys = jax.random.split(key_actions, self.episode_length)
        (_, total), _ = jax.lax.scan(body, (state, jnp.zeros(state.reward.shape)), keys)
        return total.mean()
