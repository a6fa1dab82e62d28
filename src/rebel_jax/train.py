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

The preference methods (``pebble``, ``surf``, ``rebel``) add two things to a round.
Vector steps before ``feedback_start`` update SAC on PEBBLE's unsupervised state-entropy
reward (:mod:`rebel_jax.pretrain`), and a round that starts on the feedback schedule first
runs a *feedback session*: :meth:`Trainer.select` picks query pairs, :meth:`Trainer.teach`
labels them with the scripted teacher (the only place that reads the true reward), and
:meth:`Trainer.learn` stores the labels, trains the reward ensemble with the algorithm's
loss terms, relabels the whole buffer and, at the first feedback session, re-initialises the critic.
The three are separate pure functions, so a human can answer the queries between rounds.
The session is a ``lax.cond`` on the (unbatched) round index, so rounds without one skip it.
A trainer built with ``host_teacher=True`` (the human and replay teachers, :mod:`rebel_jax.human`)
leaves the session out of the round: the host runs :meth:`Trainer.session_queries`, gets the
answers, and runs :meth:`Trainer.session_learn` before the round; its buffer also stores each
transition's physics positions, from which the clips are rendered.

Evaluation runs inside the same batch: ``eval_episodes`` extra environments follow the
deterministic policy (the mean action) next to the ``num_envs`` training environments,
so evaluation costs no extra env-step latency. As B-Pref's ``evaluate``, each evaluation
episode runs one frozen policy: the actor's parameters are copied into
``TrainState.eval_actor`` when the episode starts. :func:`evaluate` runs separate episodes
of a given policy (used for the final evaluation).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct
from jax.sharding import NamedSharding

from rebel_jax import pretrain, queries, replay, reward_model, surf, sweep, teachers
from rebel_jax.config import Config, FeedbackConfig
from rebel_jax.envs import DMCEnv, PointProbe, State, VmapWrapper, make_env
from rebel_jax.queries import Segments
from rebel_jax.sac import SAC, SACState


@struct.dataclass
class SessionQueries:
    """A feedback session's query pairs and the keys of its teacher and of its ``learn``."""

    seg_a: Segments
    seg_b: Segments
    key_teach: jax.Array
    key_learn: jax.Array


SESSION_METRICS = (
    "session",
    "labels_used",
    "session_labels",
    "session_skipped",
    "session_equal",
    "session_oracle_agreement",
    "reward_accuracy_new",
    "reward_accuracy_all",
    "reward_epochs",
    "reward_loss",
    "reward_correlation",
    "reward_correlation_return",
    "reward_correlation_queries",
    "reward_learned_mean",
    "reward_saturated",
)
"""Per-round metrics of the feedback session (NaN in rounds without one, except ``labels_used``).

The three correlations of the learned (ensemble-mean) reward with the true one tell apart why
``reward_correlation`` (per step, on 64 fresh segments of the query pool) can be low or negative:
``reward_correlation_return`` is over those segments' sums, which is all the Bradley-Terry loss
constrains (a model can order segments right and still spread reward over their steps wrongly);
``reward_correlation_queries`` is per step on this session's queried segments, the data the
labels came from (high there but low on fresh segments points to a shift between the two).

``reward_learned_mean`` and ``reward_saturated`` describe the learned reward on the same fresh
segments: its mean, and the fraction of steps within 5% of the output's range from one of its bounds
(``|r| > 0.9`` for tanh; below 0.05 or above 0.95 for sigmoid). Near its bounds a reward has little
room left to rank one good behaviour above a better one.

``session_oracle_agreement`` is the share of the answers the reward model learns from (kept and within the
budget) that equal the oracle teacher's on the same segments: 1 for the oracle; for B-Pref's imperfect teachers
and for a person, the label noise they actually put into the run (the human page's ``human_agreement`` compares
a person with the hidden scripted teacher instead, which may itself be imperfect).
"""


ROUND_REWARD_METRICS = ("round_learned_mean", "round_learned_saturated", "round_reward_correlation")
"""Per-round metrics of the preference methods, on the training transitions of the round (every
round, also after the label budget is spent, when the session metrics stop): the learned reward's
mean, its saturated fraction (as ``reward_saturated``), and its per-step correlation with the true
reward. They follow the learned reward along the states the improving policy reaches (RESULTS.md,
SURF on cheetah_run: saturated on 87% of them, and still improving).
"""


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

    def after_step(self, reward: jax.Array, done: jax.Array, n: int) -> EpisodeStats:
        """The statistics after one vector step of rewards and done flags, the first ``n`` envs training ones."""
        running = self.running + reward
        finished = done > 0

        def finished_mean(part, last):
            mask = finished[part]
            mean = jnp.sum(jnp.where(mask, running[part], 0.0)) / jnp.maximum(jnp.sum(mask), 1)
            return jnp.where(jnp.any(mask), mean, last)

        return EpisodeStats(
            running=jnp.where(finished, 0.0, running),
            train_return=finished_mean(slice(0, n), self.train_return),
            eval_return=finished_mean(slice(n, None), self.eval_return),
        )


@struct.dataclass
class TrainState:
    """Everything one seed carries from round to round (all of it is checkpointed).

    Attributes:
      sac: networks, optimisers, temperature.
      buffer: the replay buffer of training transitions.
      env: batched env state, ``num_envs`` training then ``eval_episodes`` evaluation envs.
      episodes: running and last returns.
      key: the PRNG key of the run.
      reward: the reward ensemble and its labels (preference methods; None for sac).
      entropy_stats: running statistics of the pre-training kNN distances (None for sac).
      lam: () REBEL's signed lambda, a traced value so that a sweep can vmap over it
        (``rebel.lam`` at init; None for the other methods).
      teacher: the scripted teacher's knobs (``teachers.knobs``), traced for the same reason
        (``cfg.teacher`` at init; None for sac).
      eval_actor: the actor parameters the evaluation environments follow, frozen at the
        start of each episode.
      eval_trajectory: REBEL's on-policy V (``rebel.source='onpolicy'``; else None): the first
        ``rebel.episodes`` evaluation environments' observations and actions over the first
        ``rebel.horizon`` steps T of their episodes (:func:`record_trajectory`), ``current`` being
        written and ``last`` the last complete one, each ``{"obs": (T, episodes, obs_size),
        "action": (T, episodes, act_size)}``.
    """

    sac: SACState
    buffer: replay.Buffer
    env: State
    episodes: EpisodeStats
    key: jax.Array
    reward: reward_model.RewardState | None = None
    entropy_stats: pretrain.RunningStats | None = None
    lam: jax.Array | None = None
    teacher: dict[str, jax.Array] | None = None
    eval_actor: Any = None
    eval_trajectory: dict | None = None


class Trainer:
    """Builds the pure functions of one seed's run from a :class:`Config`."""

    def __init__(self, cfg: Config, host_teacher: bool = False):
        """
        Args:
          cfg: the run's configuration.
          host_teacher: the feedback sessions run on the host between rounds (the human and replay
            teachers): the round leaves them out and the buffer stores physics positions for clips.
        """
        self.cfg = cfg.validate()
        if cfg.pixels:
            raise ValueError("pixel tasks run in rebel_jax.pixel_train.PixelTrainer, not Trainer")
        if host_teacher and not cfg.preference:
            raise ValueError(f"host_teacher needs a preference algo, not {cfg.algo!r}")
        self.host_teacher = host_teacher
        self.env: DMCEnv | PointProbe = make_env(
            cfg.env.task, solver=cfg.env.solver, episode_length=cfg.env.episode_length
        )
        self.sac = SAC(cfg.sac, self.env.observation_size, self.env.action_size)
        self.num_train = cfg.env.num_envs
        self.num_all = cfg.env.num_envs + cfg.train.eval_episodes
        # brax's VmapWrapper: reset(key) resets the envs on jax.random.split(key, batch_size).
        self.envs = VmapWrapper(self.env, batch_size=self.num_all)  # training, then in-batch evaluation
        self.eval_envs = VmapWrapper(self.env, batch_size=cfg.train.eval_episodes)  # Trainer.evaluate
        self.steps_per_round = cfg.train.steps_per_round // cfg.env.num_envs  # vector steps
        self.updates_per_step = max(1, round(cfg.sac.utd * cfg.env.num_envs))
        self.preference = cfg.preference  # the preference methods train SAC on the learned reward
        self.method = cfg.method
        # The label store holds exactly the budget; SURF stores segments longer by 2 * crop.
        self.reward_cfg = dataclasses.replace(cfg.reward, label_capacity=cfg.feedback.labels)
        self.horizon = cfg.query.segment_length
        self.crop = self.method.crop(cfg) if self.preference else 0
        self.stored_length = self.horizon + 2 * self.crop
        self.pretrain_steps = cfg.feedback_start // cfg.env.num_envs if self.preference else 0  # vector steps
        sessions = -(-cfg.feedback.labels // cfg.feedback.queries)
        self.pool_capacity = self.method.pool_size(cfg) * sessions if self.preference else 0  # every session's
        # The evaluation episodes kept for the method's loss (REBEL's on-policy V): (episodes, steps), or None.
        self.trajectory_size = (
            self.method.trajectory_size(cfg, cfg.env.episode_length, False) if self.preference else None
        )

    def policy_params(self, ts: TrainState):
        """What :meth:`evaluate` takes: the actor's parameters."""
        return ts.sac.actor_params

    def mean_action(self, actor_params, obs: jax.Array) -> jax.Array:
        """The deterministic action of ``actor_params`` (:meth:`policy_params`) at ``obs``."""
        return self.sac.act_deterministic(actor_params, obs)

    # -- init -----------------------------------------------------------------------------
    def init(self, key: jax.Array) -> TrainState:
        """A fresh run of one seed."""
        key, key_sac, key_env = jax.random.split(key, 3)
        env_state = self._reset_envs(key_env)
        nan = jnp.full((), jnp.nan, jnp.float32)
        obs_size, action_size = self.env.observation_size, self.env.action_size
        sac_state = self.sac.init(key_sac)
        ts = TrainState(
            sac=sac_state,
            buffer=replay.init(self.cfg.train.capacity, self.num_train, obs_size, action_size, self._qpos_size()),
            env=env_state,
            episodes=EpisodeStats(jnp.zeros(self.num_all), nan, nan),
            key=key,
            eval_actor=sac_state.actor_params,
        )
        if not self.preference:
            return ts
        key, key_reward = jax.random.split(key)
        reward = reward_model.init(self.reward_cfg, key_reward, obs_size, action_size, self.stored_length)
        if self.pool_capacity:
            reward = reward.replace(pool=surf.init_pool(self.pool_capacity, self.stored_length, obs_size, action_size))
        lam = self.method.knob(self.cfg)
        teacher = teachers.knobs(self.cfg.teacher)
        stats = pretrain.init_stats(self.cfg.pretrain.running_std)
        ts = ts.replace(key=key, reward=reward, entropy_stats=stats, lam=lam, teacher=teacher)
        if self.trajectory_size:
            fields = {"obs": ((obs_size,), jnp.float32), "action": ((action_size,), jnp.float32)}
            ts = ts.replace(eval_trajectory=init_trajectory(fields, *self.trajectory_size))
        return ts

    def _qpos_size(self) -> int:
        """Physics positions stored per transition: the task's qpos for the host teacher, else none."""
        if not self.host_teacher:
            return 0
        state = jax.eval_shape(self.env.reset, jax.random.PRNGKey(0))
        return physics_positions(state.pipeline_state).shape[-1]

    def _reset_envs(self, key: jax.Array) -> State:
        return self.envs.reset(key)

    # -- one vector step ------------------------------------------------------------------
    def _act(self, ts: TrainState, t: jax.Array, key: jax.Array) -> jax.Array:
        key_policy, key_random = jax.random.split(key)
        obs = ts.env.obs
        explore = self.sac.act(ts.sac.actor_params, obs[: self.num_train], key_policy)
        random = jax.random.uniform(key_random, explore.shape, minval=-1.0, maxval=1.0)
        seeding = t * self.num_train < self.cfg.train.seed_steps
        train_action = jnp.where(seeding, random, explore)
        eval_action = self.mean_action(ts.eval_actor, obs[self.num_train :])
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
            learned_reward=self._learned_reward(ts, ts.env.obs[:n], action[:n]) if self.preference else None,
            qpos=physics_positions(ts.env.pipeline_state)[:n] if self.host_teacher else None,
        )
        episodes = ts.episodes.after_step(nxt.reward, nxt.done, n)
        return replay.add(ts.buffer, step), episodes

    def _learned_reward(self, ts: TrainState, obs: jax.Array, action: jax.Array) -> jax.Array:
        return reward_model.mean_reward(self.reward_cfg, ts.reward.params, obs, action)

    def _updates(self, ts: TrainState, buffer: replay.Buffer, key: jax.Array, t: jax.Array, intrinsic: bool):
        """``utd * num_envs`` SAC updates on the learned (or true, for sac) or the intrinsic reward."""
        # Pre-training happens before the buffer wraps: its kNN search needs only the rows written by then.
        early = buffer.replace(obs=buffer.obs[: max(self.pretrain_steps, 1)])

        def one(carry, key):
            state, stats = carry
            key_sample, key_update = jax.random.split(key)
            if not self.preference:
                batch = replay.sample(buffer, key_sample, self.cfg.sac.batch_size, False)
            else:
                batch = self.method.sample_batch(self, ts, buffer, key_sample)
            if intrinsic:
                reward, stats = pretrain.intrinsic_reward(self.cfg.pretrain, stats, batch.obs, early)
                batch = batch.replace(reward=reward)
            elif self.preference:
                batch = self.method.batch_reward(self, ts, batch, t)
            state, metrics = self.sac.update(state, batch, key_update)
            return (state, stats), metrics

        keys = jax.random.split(key, self.updates_per_step)
        (sac_state, stats), metrics = jax.lax.scan(one, (ts.sac, ts.entropy_stats), keys)
        return (sac_state, stats), jax.tree.map(jnp.mean, metrics)

    def vector_step(self, ts: TrainState, t: jax.Array) -> tuple[TrainState, dict]:
        """One step of every environment, then ``utd * num_envs`` SAC updates.

        Args:
          ts: one seed's state.
          t: the vector-step index in the run, the same for every seed (unbatched).
        """
        key, key_reset, key_act, key_update = jax.random.split(ts.key, 4)
        new_episode = (t % self.cfg.env.episode_length == 0) & (t > 0)
        env_state, eval_actor = jax.lax.cond(
            new_episode,
            lambda: (self._reset_envs(key_reset), ts.sac.actor_params),  # Evaluation freezes this episode's policy.
            lambda: (ts.env, ts.eval_actor),
        )
        ts = ts.replace(env=env_state, key=key, eval_actor=eval_actor)
        action = self._act(ts, t, key_act)
        nxt = self.envs.step(ts.env, action)
        buffer, episodes = self._record(ts, nxt, action)
        learning = (t + 1) * self.num_train >= self.cfg.train.seed_steps
        zeros = {k: jnp.zeros(()) for k in ("critic_loss", "actor_loss", "alpha_loss", "alpha", "q", "entropy")}
        branches = [
            lambda: ((ts.sac, ts.entropy_stats), zeros),
            lambda: self._updates(ts, buffer, key_update, t, intrinsic=False),
        ]
        phase = learning.astype(jnp.int32)  # 0: seeding, 1: SAC on the stored reward
        if self.pretrain_steps:
            branches.append(lambda: self._updates(ts, buffer, key_update, t, intrinsic=True))
            phase = jnp.where(learning & (t < self.pretrain_steps), 2, phase)  # 2: unsupervised pre-training
        (sac_state, stats), metrics = jax.lax.switch(phase, branches)
        ts = ts.replace(sac=sac_state, entropy_stats=stats, buffer=buffer, env=nxt, episodes=episodes)
        if self.trajectory_size:  # The evaluation environments' step: the state acted in, the action.
            first, end = self.num_train, self.num_train + self.trajectory_size[0]
            step = {"obs": env_state.obs[first:end], "action": action[first:end]}
            trajectory = record_trajectory(ts.eval_trajectory, step, t, self.cfg.env.episode_length)
            ts = ts.replace(eval_trajectory=trajectory)
        metrics = dict(metrics, learning=learning.astype(jnp.float32))
        return ts, metrics

    # -- feedback session (preference methods) ---------------------------------------------
    def _central(self, seg: Segments) -> Segments:
        """The middle ``segment_length`` steps of stored segments (all of them unless SURF crops)."""
        return jax.tree.map(lambda x: x[:, self.crop : self.crop + self.horizon], seg)

    def sample_segments(self, buffer: replay.Buffer, key: jax.Array, n: int, length: int) -> Segments:
        """``n`` segments of ``length`` steps from the query pool (``query.recent_episodes``, ``query.pool``)."""
        query = self.cfg.query
        episode_length = self.cfg.env.episode_length
        return queries.sample_segments(buffer, key, n, length, episode_length, query.recent_episodes, query.pool)

    def select(self, ts: TrainState, key: jax.Array, first: bool | jax.Array) -> tuple[Segments, Segments]:
        """The session's query pairs, of the stored length: the method's (``Method.query_segments``)."""
        return self.method.query_segments(self, ts, key, first)

    def select_queries(self, ts: TrainState, key: jax.Array, first: bool | jax.Array) -> tuple[Segments, Segments]:
        """The session's query pairs by ``query.sampling`` (uniform at the first feedback session), stored length.

        Disagreement and entropy are scored on the whole stored segments, as SURF scores its
        ``H + 2 * crop`` segments (``get_rank_probability`` on ``sa_t_1``, ``sa_t_2``).
        """
        query = dataclasses.replace(self.cfg.query, segment_length=self.stored_length)

        def pref_probs(seg_a, seg_b):
            return reward_model.pref_probs(self.reward_cfg, ts.reward.params, seg_a, seg_b)

        num = self.cfg.feedback.queries
        return queries.select_queries(query, key, ts.buffer, num, self.cfg.env.episode_length, pref_probs, first)

    def teach(self, ts: TrainState, key: jax.Array, seg_a: Segments, seg_b: Segments, index: jax.Array):
        """The scripted teacher's answers on the central steps, masked to the seed's remaining budget at
        session ``index`` (:func:`within_budget`).

        Returns:
          labels (N,), mask (N,) and the teacher's counts (``teachers.label``'s ``info``).
        """
        query = self.cfg.query
        margin = queries.reward_margin(ts.buffer, self.horizon, self.cfg.env.episode_length, query.recent_episodes)
        teacher = teachers.TeacherConfig(**ts.teacher)
        labels, mask, info = teachers.label(teacher, key, self._central(seg_a), self._central(seg_b), margin)
        return labels, within_budget(self.cfg.feedback, mask, ts.reward.data.count, index), info

    def learn(
        self,
        ts: TrainState,
        key: jax.Array,
        seg_a: Segments,
        seg_b: Segments,
        labels: jax.Array,
        mask: jax.Array,
        first: bool | jax.Array,
    ) -> tuple[TrainState, dict]:
        """Stores the answers, trains the ensemble, relabels the buffer; a fresh critic at the first feedback session.

        A seed whose answers are all masked (budget spent, or all skipped) keeps its reward model.
        """
        key_terms, key_train, key_fresh, key_critic, key_pool = jax.random.split(key, 5)
        rcfg = self.reward_cfg
        accuracy_new = reward_model.accuracy(
            rcfg, ts.reward.params, self._central(seg_a), self._central(seg_b), labels, mask
        )
        kept = jnp.sum(mask)
        stored = reward_model.add_labels(ts.reward, seg_a, seg_b, labels, mask)
        keys = {"terms": key_terms, "train": key_train, "pool": key_pool}
        trained, train_metrics = self.method.train_reward(self, ts, stored, keys, kept, None)
        reward = jax.tree.map(lambda new, old: jnp.where(kept > 0, new, old), trained, ts.reward)

        def reward_fn(obs, action):
            return reward_model.mean_reward(rcfg, reward.params, obs, action)

        buffer = replay.relabel(ts.buffer, reward_fn, chunk_rows=max(1, 16_384 // self.num_train))
        sac_state = ts.sac
        if self.cfg.pretrain.steps:
            sac_state = jax.lax.cond(first, lambda: self._reset_critic(ts.sac, buffer, key_critic), lambda: ts.sac)
        fresh = self.sample_segments(buffer, key_fresh, 64, self.horizon)
        learned = reward_model.mean_reward(rcfg, reward.params, fresh.obs, fresh.action)
        metrics = reward_training_metrics(accuracy_new, train_metrics, kept)
        metrics["reward_correlation"] = _pearson(learned.reshape(-1), fresh.true_reward.reshape(-1))
        metrics["reward_correlation_return"] = _pearson(learned.sum(-1), fresh.true_reward.sum(-1))
        metrics["reward_learned_mean"] = jnp.mean(learned)
        metrics["reward_saturated"] = saturated_fraction(learned, rcfg.output)
        queried = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), self._central(seg_a), self._central(seg_b))
        learned_queried = reward_model.mean_reward(rcfg, reward.params, queried.obs, queried.action)
        metrics["reward_correlation_queries"] = _pearson(learned_queried.reshape(-1), queried.true_reward.reshape(-1))
        return ts.replace(sac=sac_state, buffer=buffer, reward=reward), metrics

    def _reset_critic(self, sac_state: SACState, buffer: replay.Buffer, key: jax.Array) -> SACState:
        """A fresh critic after pre-training, then ``pretrain.reset_updates`` SAC updates on the relabelled buffer.

        B-Pref's ``agent.reset_critic()`` then ``agent.update_after_reset(gradient_update=reset_update)``
        (``train_PEBBLE.py``; ``agent/sac.py``): critic, actor and temperature steps on the learned
        reward. The target critic moves on this project's update counter (``SAC.update``), where B-Pref
        moves it on the even indices of these updates.
        """
        key_reset, key_updates = jax.random.split(key)
        sac_state = self.sac.reset_critic(sac_state, key_reset)

        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            batch = replay.sample(buffer, key_sample, self.cfg.sac.batch_size, True)
            return self.sac.update(state, batch, key_update)[0], None

        keys = jax.random.split(key_updates, self.cfg.pretrain.reset_updates)
        return jax.lax.scan(one, sac_state, keys)[0]

    def feedback_session(self, ts: TrainState, first: jax.Array, index: jax.Array) -> tuple[TrainState, dict]:
        """select -> teach -> learn at session ``index``, with the session's metrics (:data:`SESSION_METRICS`)."""
        ts, asked = self.session_queries(ts, first)
        labels, mask, info = self.teach(ts, asked.key_teach, asked.seg_a, asked.seg_b, index)
        return self.session_learn(ts, asked, labels, mask, first, info)

    def session_queries(self, ts: TrainState, first: jax.Array) -> tuple[TrainState, SessionQueries]:
        """The first half of a session: its keys and query pairs (``select``)."""
        key, key_select, key_teach, key_learn = jax.random.split(ts.key, 4)
        ts = ts.replace(key=key)
        seg_a, seg_b = self.select(ts, key_select, first)
        return ts, SessionQueries(seg_a, seg_b, key_teach, key_learn)

    def session_learn(
        self,
        ts: TrainState,
        asked: SessionQueries,
        labels: jax.Array,
        mask: jax.Array,
        first: jax.Array,
        info: dict[str, jax.Array],
    ) -> tuple[TrainState, dict]:
        """The second half: ``learn`` from the answers and the session's metrics.

        The caller masks the answers to the seed's remaining budget (``teach`` does it for the scripted teachers).

        Args:
          info: the teacher's ``num_skipped`` and ``num_equal`` counts.
        """
        ts, metrics = self.learn(ts, asked.key_learn, asked.seg_a, asked.seg_b, labels, mask, first)
        agreement = teachers.oracle_agreement(
            asked.key_teach, self._central(asked.seg_a), self._central(asked.seg_b), labels, mask
        )
        teacher = teachers.session_metrics(dict(info, oracle_agreement=agreement))
        return ts, self._session_summary(ts, dict(metrics, session=1.0, **teacher))

    def _session_summary(self, ts: TrainState, metrics: dict) -> dict:
        nan = jnp.full((), jnp.nan, jnp.float32)
        out = {k: jnp.asarray(metrics.get(k, nan), jnp.float32) for k in SESSION_METRICS}
        out["labels_used"] = ts.reward.data.count.astype(jnp.float32)
        return out

    def session_index(self, round_index: jax.Array) -> jax.Array:
        """The index (0-based) of the session on the schedule at round ``round_index`` (if it has one)."""
        return session_index(self.cfg, round_index)

    def session_due(self, round_index: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Whether round ``round_index`` starts with a feedback session, and whether it is the first."""
        return session_due(self.cfg, round_index)

    # -- the round ------------------------------------------------------------------------
    def round(self, ts: TrainState, round_index: jax.Array) -> tuple[TrainState, dict]:
        """``steps_per_round`` environment steps with their updates, as one ``lax.scan``.

        Args:
          ts: one seed's state.
          round_index: the round number, unbatched (the same for every seed).

        Returns:
          The new state and the round's metrics: SAC metrics averaged over the round's
          learning steps, the last finished training and evaluation returns, and
          ``diverged`` (1.0 if a loss, parameter, observation or return is NaN or infinite).
        """
        episodes_before = ts.episodes
        session = {}
        if self.host_teacher:  # The host ran this round's session, if any, before the round.
            session = self._session_summary(ts, {})
        elif self.preference:
            due, first = self.session_due(round_index)
            ts, session = jax.lax.cond(
                due,
                self.feedback_session,
                lambda ts, first, index: (ts, self._session_summary(ts, {})),
                ts,
                first,
                self.session_index(round_index),
            )
        t0 = round_index * self.steps_per_round
        ts, metrics = jax.lax.scan(self.vector_step, ts, t0 + jnp.arange(self.steps_per_round))
        learning = metrics.pop("learning")
        weight = learning / jnp.maximum(learning.sum(), 1.0)
        summary = {k: jnp.sum(v * weight) for k, v in metrics.items()}
        summary["train_return"] = ts.episodes.train_return
        summary["eval_return"] = ts.episodes.eval_return
        if self.preference:
            summary.update(self._round_reward_metrics(ts.buffer))
        summary["diverged"] = _diverged(ts, summary, episodes_before)
        return ts, {**summary, **session}

    def _round_reward_metrics(self, buffer: replay.Buffer) -> dict[str, jax.Array]:
        """:data:`ROUND_REWARD_METRICS` on the transitions this round wrote (the policy's own, this round)."""
        rows = queries.window_index(buffer, min(self.steps_per_round, buffer.rows))
        learned, true = buffer.learned_reward[rows].reshape(-1), buffer.reward[rows].reshape(-1)
        return {
            "round_learned_mean": jnp.mean(learned),
            "round_learned_saturated": saturated_fraction(learned, self.reward_cfg.output),
            "round_reward_correlation": _pearson(learned, true),
        }

    # -- frozen-policy evaluation ----------------------------------------------------------
    def evaluate(self, actor_params, key: jax.Array, random_actions: bool | jax.Array = False) -> jax.Array:
        """Mean true return of ``eval_episodes`` episodes of a frozen deterministic policy or of random actions.

        Args:
          actor_params: the policy's parameters (its mean action is taken).
          key: fixes the episodes' initial states, the same for both kinds of actions, and the random actions.
          random_actions: act uniformly at random in [-1, 1] instead (the random-policy baseline). A traced
            value: both kinds share one compiled program.
        """
        key_reset, key_actions = jax.random.split(key)
        state = self.eval_envs.reset(key_reset)

        def body(carry, key):
            state, total = carry
            uniform = jax.random.uniform(key, (state.obs.shape[0], self.env.action_size), minval=-1.0, maxval=1.0)
            action = jnp.where(random_actions, uniform, self.mean_action(actor_params, state.obs))
            state = self.eval_envs.step(state, action)
            return (state, total + state.reward), None

        keys = jax.random.split(key_actions, self.env.episode_length)
        (_, total), _ = jax.lax.scan(body, (state, jnp.zeros(state.reward.shape)), keys)
        return total.mean()


def init_trajectory(fields: dict[str, tuple[tuple[int, ...], Any]], episodes: int, horizon: int) -> dict:
    """An empty store of REBEL's on-policy trajectories (``TrainState.eval_trajectory``).

    Args:
      fields: name -> (shape of one environment's step, dtype), e.g. the state observation and the
        action (:class:`Trainer`), or the newest frame and the action (the pixel trainer).
      episodes: N, evaluation environments recorded.
      horizon: T, steps recorded from each episode's reset.

    Returns:
      ``{"current": ..., "last": ...}``, each ``{name: (T, N, *shape)}`` zeros.
    """
    episode = {name: jnp.zeros((horizon, episodes, *shape), dtype) for name, (shape, dtype) in fields.items()}
    return {"current": episode, "last": episode}


def record_trajectory(trajectory: dict, step: dict[str, jax.Array], t: jax.Array, episode_length: int) -> dict:
    """Writes the evaluation environments' step ``t`` into ``current``; copies it to ``last`` once complete.

    The episode's step ``k = t mod episode_length`` goes to row k of each field while ``k < T`` (the
    store's horizon; later steps are dropped), and at ``k = T - 1`` the T steps are copied to ``last``:
    ``last`` holds the first T steps of the most recent evaluation episodes that have taken them. The copy
    is a ``lax.cond`` on the unbatched ``t``, a real branch under ``vmap``.

    Args:
      trajectory: the store (:func:`init_trajectory`).
      step: name -> (N, ...) this step's values, the state acted in and the action taken.
      t: the vector-step index (unbatched; all episodes start together).
      episode_length: agent steps per episode.
    """
    k = t % episode_length
    horizon = jax.tree.leaves(trajectory["last"])[0].shape[0]
    current = {name: trajectory["current"][name].at[k].set(value, mode="drop") for name, value in step.items()}
    last = jax.lax.cond(k == horizon - 1, lambda: current, lambda: trajectory["last"])
    return {"current": current, "last": last}


def _all_finite(tree) -> jax.Array:
    """Whether every floating-point value in ``tree`` is finite."""
    leaves = [x for x in jax.tree.leaves(tree) if jnp.issubdtype(x.dtype, jnp.floating)]
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves]))


def _diverged(ts: TrainState, summary: dict, episodes_before: EpisodeStats) -> jax.Array:
    """1.0 if the round left a NaN or infinity in the seed's SAC losses, parameters, reward model,
    observations or returns, else 0.0. A return may stay NaN (no episode finished yet) but not become NaN.
    """
    losses = {k: summary[k] for k in ("critic_loss", "actor_loss", "alpha_loss", "alpha", "q", "entropy")}
    returns_ok = [
        jnp.isfinite(new) | (jnp.isnan(new) & jnp.isnan(old))
        for new, old in (
            (ts.episodes.train_return, episodes_before.train_return),
            (ts.episodes.eval_return, episodes_before.eval_return),
        )
    ]
    reward_params = ts.reward.params if ts.reward is not None else ()
    finite = _all_finite((losses, ts.sac, reward_params, ts.env.obs, ts.episodes.running))
    return 1.0 - (finite & returns_ok[0] & returns_ok[1]).astype(jnp.float32)


def physics_positions(pipeline_state) -> jax.Array:
    """The positions a clip is drawn from: MJX's ``qpos``, or the probe's ``pos``."""
    qpos = getattr(pipeline_state, "qpos", None)
    return pipeline_state.pos if qpos is None else qpos


def reward_training_metrics(accuracy_new: jax.Array, train_metrics: dict, kept: jax.Array) -> dict[str, jax.Array]:
    """A session's reward-training metrics and its label count ``session_labels``.

    NaN where no answer was kept (``kept`` 0): that session's training was discarded.
    """
    training = {
        "reward_accuracy_new": accuracy_new,
        "reward_accuracy_all": train_metrics["train_accuracy"],
        "reward_epochs": train_metrics["epochs"],
        "reward_loss": train_metrics["loss"],
    }
    metrics = {k: jnp.where(kept > 0, jnp.asarray(v, jnp.float32), jnp.nan) for k, v in training.items()}
    metrics["session_labels"] = kept
    return metrics


def session_index(cfg: Config, round_index):
    """The index (0-based) of the feedback session on the schedule at round ``round_index`` (if it has one)."""
    step = round_index * cfg.train.steps_per_round
    return (step - cfg.feedback_start) // cfg.feedback.interval


def session_due(cfg: Config, round_index):
    """Whether round ``round_index`` starts with a feedback session, and whether it is the first: at
    ``cfg.feedback_start``, then every ``feedback.interval`` steps; under ``feedback.budget`` ``asked`` none
    after the ``feedback.sessions`` the budget allows (B-Pref holds none once it is spent)."""
    step = round_index * cfg.train.steps_per_round
    start = cfg.feedback_start
    due = (step >= start) & ((step - start) % cfg.feedback.interval == 0)
    if cfg.feedback.sessions is not None:
        due = due & (session_index(cfg, round_index) < cfg.feedback.sessions)
    return due, step == start


def remaining_budget(feedback: FeedbackConfig, stored, index):
    """Pairs the seed may still count at session ``index`` (0-based) with ``stored`` labels held
    (``feedback.budget``): ``labels - index * queries`` asked, or ``labels - stored`` answered."""
    return feedback.labels - (index * feedback.queries if feedback.budget == "asked" else stored)


def offered_pairs(feedback: FeedbackConfig, remaining: int, queries: int) -> int:
    """How many of a session's ``queries`` pairs a person is shown, ``remaining`` being
    :func:`remaining_budget`: under ``asked`` only the first ``remaining`` (B-Pref's
    ``train_PEBBLE.py`` shrinks the last session's batch to ``max_feedback - total_feedback``, its
    "corner case: new total feed > max feed"), which are also the only ones :func:`within_budget`
    counts; under ``answered`` all of them, a skipped pair leaving its place to the next."""
    return max(0, min(remaining, queries)) if feedback.budget == "asked" else queries


def within_budget(feedback: FeedbackConfig, mask: jax.Array, stored: jax.Array, index: jax.Array) -> jax.Array:
    """``mask`` (N,) limited to the seed's remaining budget (``feedback.budget``) at session ``index`` (0-based),
    with ``stored`` labels held so far.

    ``asked`` (B-Pref): the first ``labels - index * queries`` pairs of the session, answered or skipped
    (``learn_reward``'s ``total_feedback += mb_size``; ``set_batch(max_feedback - total_feedback)`` in the
    last session). ``answered``: the answered pairs while ``labels - stored`` last.
    """
    remaining = remaining_budget(feedback, stored, index)
    if feedback.budget == "asked":
        return mask * (jnp.arange(mask.shape[-1]) < remaining)
    return mask * (jnp.cumsum(mask, axis=-1) <= remaining)


def saturated_fraction(reward: jax.Array, output: str) -> jax.Array:
    """Fraction of ``reward``'s entries within 5% of the output's range from a bound (see :data:`SESSION_METRICS`)."""
    low, high = (0.0, 1.0) if output == "sigmoid" else (-1.0, 1.0)
    margin = 0.05 * (high - low)
    return jnp.mean((reward < low + margin) | (reward > high - margin))


def _pearson(x: jax.Array, y: jax.Array) -> jax.Array:
    """Pearson correlation of two vectors (0 if either is constant)."""
    x, y = x - x.mean(), y - y.mean()
    return jnp.sum(x * y) / jnp.maximum(jnp.sqrt(jnp.sum(x * x) * jnp.sum(y * y)), 1e-12)


def seed_keys(seed: int, num_seeds: int) -> jax.Array:
    """One raw PRNG key per seed: ``fold_in(base, i)``, every integer ``seed`` its own ``base``.

    ``base`` is ``PRNGKey(seed)`` for ``0 <= seed < 2**32`` (``PRNGKey`` keeps 32 bits). Any other seed starts from
    ``PRNGKey`` of the low 32 bits of ``|seed|`` and folds in ``2 * chunks + (seed < 0)``, then each further 32-bit
    chunk of ``|seed|``, low to high: the folded words spell the whole integer, sign included.
    """
    magnitude = abs(int(seed))
    base = jax.random.PRNGKey(magnitude & 0xFFFFFFFF)
    chunks = [(magnitude >> shift) & 0xFFFFFFFF for shift in range(32, magnitude.bit_length(), 32)]
    words = [2 * len(chunks) + (seed < 0), *chunks] if seed < 0 or chunks else []
    for word in words:
        base = jax.random.fold_in(base, word)
    return jax.vmap(lambda i: jax.random.fold_in(base, i))(jnp.arange(num_seeds))


def compiled(trainer: Trainer, sharding: NamedSharding | None = None) -> tuple[Callable, Callable, Callable]:
    """Jitted, seed-vmapped ``init(keys)``, ``round(states, r)`` and ``evaluate(params, keys, random_actions)``.

    The round donates its input state so the replay buffer is updated in place. ``random_actions``
    (unbatched, default False) evaluates uniform random actions on the same initial states instead.

    Args:
      trainer: the run's trainer.
      sharding: the seed axis's sharding over several devices (``sweep.seed_sharding``), or None
        for one device. Each device then runs the one-device program on its own seeds
        (:func:`rebel_jax.sweep.per_device`), with no communication between devices. Per seed the
        result is the same as on one device: under ``vmap`` a seed whose loop has stopped (the
        reward model's early stopping) is masked, whichever seeds share its batch.
    """
    init = jax.vmap(trainer.init)
    round_fn = jax.vmap(trainer.round, in_axes=(0, None))
    evaluate_seeds = jax.vmap(trainer.evaluate, in_axes=(0, 0, None))
    if sharding is None:
        init, round_fn, evaluate_seeds = jax.jit(init), jax.jit(round_fn, donate_argnums=0), jax.jit(evaluate_seeds)
    else:
        init = sweep.per_device(init, sharding, batched=(True,))
        round_fn = sweep.per_device(round_fn, sharding, batched=(True, False), donate_argnums=(0,))
        evaluate_seeds = sweep.per_device(evaluate_seeds, sharding, batched=(True, True, False))

    def evaluate(actor_params, keys: jax.Array, random_actions: bool = False) -> jax.Array:
        return evaluate_seeds(actor_params, keys, jnp.asarray(random_actions))

    return init, round_fn, evaluate


if __name__ == "__main__":  # ``python -m rebel_jax.train`` runs the package's entry point; train never imports cli.
    import runpy

    runpy.run_module("rebel_jax", run_name="__main__")
