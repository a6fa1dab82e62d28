"""The composition: init, the scanned training round, evaluation and the host loop.

One seed's run is a pure function of a PRNG key: ``init(key)`` then ``round(state, r)``
for r = 0, 1, ... Each round is a single ``lax.scan`` over vector env steps, each step
followed by its SAC updates; ``jax.vmap`` runs many seeds at once and
:mod:`rebel_jax.sweep` shards the seed axis over devices. A Python loop over rounds
drives progress, logging and checkpoints (``python -m rebel_jax.train``).

Episodes of all environments (training and evaluation, all seeds) start together: every
``episode_length`` vector steps all environments reset at once. The vector-step index
is the same for every seed, so it is passed *unbatched* and the reset is a real
``lax.cond`` even under ``vmap`` (a per-environment auto-reset would become a select
that pays for a reset every step).

Evaluation runs inside the same batch: ``eval_episodes`` extra environments follow the
deterministic policy (the mean action) next to the ``num_envs`` training environments,
so evaluation costs no extra env-step latency. Their returns are those of the policy
*as it learns during the episode*, not of one frozen snapshot; :func:`evaluate` gives
the frozen-policy figure (used for the final evaluation).
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
from flax import struct

from rebel_jax import replay
from rebel_jax.config import Config
from rebel_jax.envs import DMCEnv, State, make_env
from rebel_jax.sac import SAC, SACState


@struct.dataclass
class EpisodeStats:
    """Running true returns of the current episodes and the last finished ones.

    Attributes:
      running: (num_envs + eval_episodes,) return so far of each environment's episode.
      train_return: () mean return of the last finished training episodes (NaN before any).
      eval_return: () mean return of the last finished evaluation episodes (NaN before any).
    """

    running: jax.Array
    train_return: jax.Array
    eval_return: jax.Array


@struct.dataclass
class TrainState:
    """Everything one seed carries from round to round (all of it is checkpointed).

    Attributes:
      sac: networks, optimisers, temperature.
      buffer: the replay buffer of training transitions.
      env: batched env state, ``num_envs`` training then ``eval_episodes`` evaluation envs.
      episodes: running and last returns.
      key: the PRNG key of the run.
    """

    sac: SACState
    buffer: replay.Buffer
    env: State
    episodes: EpisodeStats
    key: jax.Array


class Trainer:
    """Builds the pure functions of one seed's run from a :class:`Config`."""

    def __init__(self, cfg: Config):
        self.cfg = cfg.validate()
        self.env: DMCEnv = make_env(cfg.env.task, solver=cfg.env.solver, episode_length=cfg.env.episode_length)
        self.sac = SAC(cfg.sac, self.env.observation_size, self.env.action_size)
        self.num_train = cfg.env.num_envs
        self.num_all = cfg.env.num_envs + cfg.train.eval_episodes
        self.steps_per_round = cfg.train.steps_per_round // cfg.env.num_envs  # vector steps
        self.updates_per_step = max(1, round(cfg.sac.utd * cfg.env.num_envs))
        self.use_learned_reward = cfg.algo != "sac"  # the preference methods train on the learned reward
        self.trace_count = 0

    # -- init -----------------------------------------------------------------------------
    def init(self, key: jax.Array) -> TrainState:
        """A fresh run of one seed."""
        key, key_sac, key_env = jax.random.split(key, 3)
        env_state = self._reset_envs(key_env)
        nan = jnp.full((), jnp.nan, jnp.float32)
        return TrainState(
            sac=self.sac.init(key_sac),
            buffer=replay.init(
                self.cfg.train.capacity, self.num_train, self.env.observation_size, self.env.action_size
            ),
            env=env_state,
            episodes=EpisodeStats(jnp.zeros(self.num_all), nan, nan),
            key=key,
        )

    def _reset_envs(self, key: jax.Array) -> State:
        return jax.vmap(self.env.reset)(jax.random.split(key, self.num_all))

    # -- one vector step ------------------------------------------------------------------
    def _act(self, ts: TrainState, t: jax.Array, key: jax.Array) -> jax.Array:
        key_policy, key_random = jax.random.split(key)
        obs = ts.env.obs
        explore = self.sac.act(ts.sac.actor_params, obs[: self.num_train], key_policy)
        random = jax.random.uniform(key_random, explore.shape, minval=-1.0, maxval=1.0)
        seeding = t * self.num_train < self.cfg.train.seed_steps
        train_action = jnp.where(seeding, random, explore)
        eval_action = self.sac.act_deterministic(ts.sac.actor_params, obs[self.num_train :])
        return jnp.concatenate([train_action, eval_action])

    def _record(self, ts: TrainState, nxt: State, action: jax.Array) -> tuple[replay.Buffer, EpisodeStats]:
        n = self.num_train
        truncated = nxt.info["truncation"]
        step = replay.Step(
            obs=ts.env.obs[:n],
            action=action[:n],
            next_obs=nxt.obs[:n],
            reward=nxt.reward[:n],
            terminal=(nxt.done - truncated)[:n],
            truncated=truncated[:n],
            episode_step=ts.env.info["steps"][:n],
        )
        running = ts.episodes.running + nxt.reward
        done = nxt.done > 0

        def finished_mean(part, last):
            mask = done[part]
            mean = jnp.sum(jnp.where(mask, running[part], 0.0)) / jnp.maximum(jnp.sum(mask), 1)
            return jnp.where(jnp.any(mask), mean, last)

        episodes = EpisodeStats(
            running=jnp.where(done, 0.0, running),
            train_return=finished_mean(slice(0, n), ts.episodes.train_return),
            eval_return=finished_mean(slice(n, None), ts.episodes.eval_return),
        )
        return replay.add(ts.buffer, step), episodes

    def _updates(self, sac_state: SACState, buffer: replay.Buffer, key: jax.Array):
        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            batch = replay.sample(buffer, key_sample, self.cfg.sac.batch_size, self.use_learned_reward)
            return self.sac.update(state, batch, key_update)

        sac_state, metrics = jax.lax.scan(one, sac_state, jax.random.split(key, self.updates_per_step))
        return sac_state, jax.tree.map(jnp.mean, metrics)

    def vector_step(self, ts: TrainState, t: jax.Array) -> tuple[TrainState, dict]:
        """One step of every environment, then ``utd * num_envs`` SAC updates.

        Args:
          ts: one seed's state.
          t: the vector-step index in the run, the same for every seed (unbatched).
        """
        key, key_reset, key_act, key_update = jax.random.split(ts.key, 4)
        new_episode = (t % self.cfg.env.episode_length == 0) & (t > 0)
        env_state = jax.lax.cond(new_episode, lambda: self._reset_envs(key_reset), lambda: ts.env)
        ts = ts.replace(env=env_state, key=key)
        action = self._act(ts, t, key_act)
        nxt = jax.vmap(self.env.step)(ts.env, action)
        buffer, episodes = self._record(ts, nxt, action)
        learning = (t + 1) * self.num_train >= self.cfg.train.seed_steps
        zeros = {k: jnp.zeros(()) for k in ("critic_loss", "actor_loss", "alpha_loss", "alpha", "q", "entropy")}
        sac_state, metrics = jax.lax.cond(
            learning,
            lambda: self._updates(ts.sac, buffer, key_update),
            lambda: (ts.sac, zeros),
        )
        ts = ts.replace(sac=sac_state, buffer=buffer, env=nxt, episodes=episodes)
        metrics = dict(metrics, learning=learning.astype(jnp.float32))
        return ts, metrics

    # -- the round ------------------------------------------------------------------------
    def round(self, ts: TrainState, round_index: jax.Array) -> tuple[TrainState, dict]:
        """``steps_per_round`` environment steps with their updates, as one ``lax.scan``.

        Args:
          ts: one seed's state.
          round_index: the round number, unbatched (the same for every seed).

        Returns:
          The new state and the round's metrics: SAC metrics averaged over the round's
          learning steps, and the last finished training and evaluation returns.
        """
        self.trace_count += 1  # Python side effect: counts traces, not calls.
        t0 = round_index * self.steps_per_round
        ts, metrics = jax.lax.scan(self.vector_step, ts, t0 + jnp.arange(self.steps_per_round))
        learning = metrics.pop("learning")
        weight = learning / jnp.maximum(learning.sum(), 1.0)
        summary = {k: jnp.sum(v * weight) for k, v in metrics.items()}
        summary["train_return"] = ts.episodes.train_return
        summary["eval_return"] = ts.episodes.eval_return
        return ts, summary

    # -- frozen-policy evaluation ----------------------------------------------------------
    def evaluate(self, actor_params, key: jax.Array) -> jax.Array:
        """Mean true return of ``eval_episodes`` deterministic episodes of a frozen policy."""
        state = jax.vmap(self.env.reset)(jax.random.split(key, self.cfg.train.eval_episodes))

        def body(carry, _):
            state, total = carry
            state = jax.vmap(self.env.step)(state, self.sac.act_deterministic(actor_params, state.obs))
            return (state, total + state.reward), None

        (_, total), _ = jax.lax.scan(body, (state, jnp.zeros(state.reward.shape)), length=self.env.episode_length)
        return total.mean()


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
    """One raw PRNG key per seed: ``fold_in(PRNGKey(seed), i)``."""
    base = jax.random.PRNGKey(seed)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(num_seeds))


def compiled(trainer: Trainer) -> tuple[Callable, Callable, Callable]:
    """Jitted, seed-vmapped ``init(keys)``, ``round(states, r)`` and ``evaluate(params, keys)``.

    The round donates its input state so the replay buffer is updated in place.
    """
    init = jax.jit(jax.vmap(trainer.init))
    round_fn = jax.jit(jax.vmap(trainer.round, in_axes=(0, None)), donate_argnums=0)
    evaluate = jax.jit(jax.vmap(trainer.evaluate))
    return init, round_fn, evaluate


if __name__ == "__main__":
    from rebel_jax.cli import main

    main()
