"""The feedback session on a state task: select -> teach -> learn, with the reward model of
:mod:`rebel_jax.preference.reward_model`, and the session's metrics.

:meth:`StateFeedback.select` picks query pairs (the method's ``query_segments``), :meth:`StateFeedback.teach`
labels them with the scripted teacher (the only place that reads the true reward), and
:meth:`StateFeedback.learn` stores the labels, trains the reward ensemble with the method's loss terms,
relabels the whole replay and, at the first feedback session, re-initialises the critic. The three are separate
pure functions, so a human can answer the queries between rounds (:meth:`StateFeedback.session_queries`, then
:meth:`StateFeedback.session_learn`). The pixel tasks' session is :mod:`rebel_jax.preference.pixel_feedback`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from rebel_jax.agents import replay
from rebel_jax.preference import pretrain, queries, reward_model, teachers
from rebel_jax.preference.budget import within_budget
from rebel_jax.preference.queries import Segments


@struct.dataclass
class SessionQueries:
    """A feedback session's query pairs and the keys of its teacher and of its ``learn``."""

    seg_a: Segments
    seg_b: Segments
    key_teach: jax.Array
    key_learn: jax.Array


COMMON_SESSION_METRICS = (
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
)
"""Per-round metrics of a feedback session on either kind of task."""

SESSION_METRICS = COMMON_SESSION_METRICS + (
    "reward_correlation",
    "reward_correlation_return",
    "reward_correlation_queries",
    "reward_learned_mean",
    "reward_saturated",
)
"""Per-round metrics of the feedback session on a state task (NaN in rounds without one, except ``labels_used``).

``reward_correlation`` is the per-step Pearson correlation of the learned (ensemble-mean) reward with the true one
on 64 fresh segments of the query pool (pixel tasks log ``reward_correlation_replay`` instead, over every replay
row: :data:`rebel_jax.preference.pixel_feedback.PIXEL_SESSION_METRICS`). The two other correlations tell apart why it
can be
low or negative: ``reward_correlation_return`` is over those segments' sums, which is all the Bradley-Terry loss
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
"""Per-round metrics of the preference methods on state tasks, on the training transitions of the round (every
round, also after the label budget is spent, when the session metrics stop): the learned reward's
mean, its saturated fraction (as ``reward_saturated``), and its per-step correlation with the true
reward. They follow the learned reward along the states the improving policy reaches (RESULTS.md,
SURF on cheetah_run: saturated on 87% of them, and still improving).
"""


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


TRAINING_METRICS = ("epochs", "train_accuracy", "loss")
"""The metrics every method's ``train_reward`` returns (logged as ``reward_epochs``, ``reward_accuracy_all`` and
``reward_loss``); any other key is the method's own (:func:`method_metrics`)."""


def method_metrics(name: str, metrics: dict, kept: jax.Array) -> dict[str, jax.Array]:
    """A method's own metrics of a session, as logged: ``NAME/KEY`` for every key of ``metrics`` beyond
    :data:`TRAINING_METRICS`, float32, NaN where no answer was kept (``kept`` 0)."""
    own = {k: v for k, v in metrics.items() if k not in TRAINING_METRICS}
    return {f"{name}/{k}": jnp.where(kept > 0, jnp.asarray(v, jnp.float32), jnp.nan) for k, v in own.items()}


def summary(names: tuple[str, ...], ts: Any, metrics: dict) -> dict:
    """``names``' values from ``metrics`` (NaN where missing), the method's own (keys ``NAME/KEY``) and
    ``labels_used`` from the label store."""
    nan = jnp.full((), jnp.nan, jnp.float32)
    out = {k: jnp.asarray(metrics.get(k, nan), jnp.float32) for k in names}
    out.update({k: v for k, v in metrics.items() if "/" in k})
    out["labels_used"] = ts.reward.data.count.astype(jnp.float32)
    return out


def saturated_fraction(reward: jax.Array, output: str) -> jax.Array:
    """Fraction of ``reward``'s entries within 5% of the output's range from a bound (see :data:`SESSION_METRICS`)."""
    low, high = (0.0, 1.0) if output == "sigmoid" else (-1.0, 1.0)
    margin = 0.05 * (high - low)
    return jnp.mean((reward < low + margin) | (reward > high - margin))


def pearson(x: jax.Array, y: jax.Array) -> jax.Array:
    """Pearson correlation of two vectors (0 if either is constant)."""
    x, y = x - x.mean(), y - y.mean()
    return jnp.sum(x * y) / jnp.maximum(jnp.sqrt(jnp.sum(x * x) * jnp.sum(y * y)), 1e-12)


class RewardFeedback:
    """What the state and the pixel tasks' feedback sessions share: the trainer's config and reward settings, and
    the ensemble's learned reward (:mod:`rebel_jax.preference.reward_model`, over either network).

    Args:
      trainer: the run's trainer (:class:`rebel_jax.train.Trainer`), whose config, sizes and agent it reads.
    """

    def __init__(self, trainer: Any):
        self.trainer = trainer

    @property
    def cfg(self):
        """The trainer's config."""
        return self.trainer.cfg

    @property
    def reward_cfg(self):
        """The reward model's config (``trainer.reward_cfg``: ``reward`` on state tasks, ``pixel_reward`` on pixels)."""
        return self.trainer.reward_cfg

    def mean_reward(self, params, obs: jax.Array, action: jax.Array) -> jax.Array:
        """The ensemble-mean learned reward of (obs, action) with any leading axes."""
        return reward_model.mean_reward(self.reward_cfg, params, obs, action)

    def members(self, params, obs: jax.Array, action: jax.Array) -> jax.Array:
        """Each member's learned reward: (M, ...)."""
        return reward_model.predict(self.reward_cfg, params, obs, action)


class StateFeedback(RewardFeedback):
    """The feedback session, the learned reward and the pre-training phase of a state task's :class:`Trainer`.

    Args:
      trainer: the run's trainer (:class:`rebel_jax.train.Trainer`), whose config, sizes and agent it reads.
    """

    session_metrics = SESSION_METRICS

    # -- the reward model -------------------------------------------------------------------
    def init_reward(self, key: jax.Array, obs_shape: tuple[int, ...], action_size: int, pool_capacity: int):
        """The reward ensemble, its label store and (SURF) its unlabelled pool."""
        (obs_size,) = obs_shape
        stored = self.trainer.stored_length
        optimizer = self.trainer.reward_optimizer
        reward = reward_model.init(self.reward_cfg, key, obs_size, action_size, stored, optimizer)
        if pool_capacity:
            reward = reward.replace(pool=reward_model.init_pool(pool_capacity, stored, obs_size, action_size))
        return reward

    def trajectory_fields(self, obs_shape: tuple[int, ...], action_size: int) -> dict:
        """What REBEL's on-policy store keeps per evaluation step: the state and the action."""
        return {"obs": (obs_shape, jnp.float32), "action": ((action_size,), jnp.float32)}

    def trajectory_step(self, obs: jax.Array, action: jax.Array) -> dict:
        """One step of the on-policy store (:meth:`trajectory_fields`)."""
        return {"obs": obs, "action": action}

    # -- queries ----------------------------------------------------------------------------
    def _central(self, seg: Segments) -> Segments:
        """The middle ``segment_length`` steps of stored segments (all of them unless SURF crops)."""
        crop, horizon = self.trainer.crop, self.trainer.horizon
        return jax.tree.map(lambda x: x[:, crop : crop + horizon], seg)

    def sample_segments(self, buffer: replay.Buffer, key: jax.Array, n: int, length: int) -> Segments:
        """``n`` segments of ``length`` steps from the query pool (``query.recent_episodes``, ``query.pool``)."""
        query = self.cfg.query
        episode_length = self.cfg.env.episode_length
        return queries.sample_segments(buffer, key, n, length, episode_length, query.recent_episodes, query.pool)

    def sample_pairs(self, buffer: replay.Buffer, key: jax.Array, n: int, recent_episodes: int):
        """``n`` uniform pairs of stored-length segments from the last ``recent_episodes`` complete episodes."""
        sizes = (self.trainer.stored_length, self.cfg.env.episode_length, recent_episodes, self.cfg.query.pool)
        return queries.sample_pairs(buffer, key, n, *sizes)

    def select_queries(self, ts, key: jax.Array, first: bool | jax.Array) -> tuple[Segments, Segments]:
        """The session's query pairs by ``query.sampling`` (uniform at the first feedback session), stored length.

        Disagreement and entropy are scored on the whole stored segments, as SURF scores its
        ``H + 2 * crop`` segments (``get_rank_probability`` on ``sa_t_1``, ``sa_t_2``).
        """
        query = dataclasses.replace(self.cfg.query, segment_length=self.trainer.stored_length)

        def pref_probs(seg_a, seg_b):
            return reward_model.pref_probs(self.reward_cfg, ts.reward.params, seg_a, seg_b)

        num = self.cfg.feedback.queries
        return queries.select_queries(query, key, ts.buffer, num, self.cfg.env.episode_length, pref_probs, first)

    # -- the session --------------------------------------------------------------------------
    def teach(self, ts, key: jax.Array, seg_a: Segments, seg_b: Segments, index: jax.Array):
        """The scripted teacher's answers on the central steps, masked to the seed's remaining budget at
        session ``index`` (:func:`rebel_jax.preference.budget.within_budget`).

        Returns:
          labels (N,), mask (N,) and the teacher's counts (``teachers.label``'s ``info``).
        """
        recent = self.cfg.query.recent_episodes
        margin = queries.reward_margin(ts.buffer, self.trainer.horizon, self.cfg.env.episode_length, recent)
        teacher = teachers.TeacherConfig(**ts.teacher)
        labels, mask, info = teachers.label(teacher, key, self._central(seg_a), self._central(seg_b), margin)
        return labels, within_budget(self.cfg.feedback, mask, ts.reward.data.count, index), info

    def learn(self, ts, key, seg_a: Segments, seg_b: Segments, labels, mask, first) -> tuple[Any, dict]:
        """Stores the answers, trains the ensemble, relabels the buffer; a fresh critic at the first feedback session.

        A seed whose answers are all masked (budget spent, or all skipped) keeps its reward model.
        """
        trainer = self.trainer
        key_terms, key_train, key_fresh, key_critic, key_pool = jax.random.split(key, 5)
        rcfg = self.reward_cfg
        accuracy_new = reward_model.accuracy(
            rcfg, ts.reward.params, self._central(seg_a), self._central(seg_b), labels, mask
        )
        kept = jnp.sum(mask)
        stored = reward_model.add_labels(ts.reward, seg_a, seg_b, labels, mask)
        keys = {"terms": key_terms, "train": key_train, "pool": key_pool}
        method = trainer.method
        trained, method_state, train_metrics = method.train_reward(trainer, ts, stored, keys, kept, None, first)
        reward = jax.tree.map(lambda new, old: jnp.where(kept > 0, new, old), trained, ts.reward)

        def reward_fn(obs, action):
            return reward_model.mean_reward(rcfg, reward.params, obs, action)

        buffer = replay.relabel(ts.buffer, reward_fn, chunk_rows=max(1, 16_384 // trainer.num_train))
        agent_state = ts.agent
        if self.cfg.pretrain.steps:
            agent_state = jax.lax.cond(
                first, lambda: self._reset_critic(ts.agent, buffer, key_critic), lambda: ts.agent
            )
        fresh = self.sample_segments(buffer, key_fresh, 64, trainer.horizon)
        learned = reward_model.mean_reward(rcfg, reward.params, fresh.obs, fresh.action)
        metrics = reward_training_metrics(accuracy_new, train_metrics, kept)
        metrics.update(method_metrics(method.name, train_metrics, kept))
        metrics["reward_correlation"] = pearson(learned.reshape(-1), fresh.true_reward.reshape(-1))
        metrics["reward_correlation_return"] = pearson(learned.sum(-1), fresh.true_reward.sum(-1))
        metrics["reward_learned_mean"] = jnp.mean(learned)
        metrics["reward_saturated"] = saturated_fraction(learned, rcfg.output)
        queried = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), self._central(seg_a), self._central(seg_b))
        learned_queried = reward_model.mean_reward(rcfg, reward.params, queried.obs, queried.action)
        metrics["reward_correlation_queries"] = pearson(learned_queried.reshape(-1), queried.true_reward.reshape(-1))
        return ts.replace(agent=agent_state, buffer=buffer, reward=reward, method=method_state), metrics

    def _reset_critic(self, agent_state, buffer: replay.Buffer, key: jax.Array):
        """A fresh critic after pre-training (unless the method keeps it, ``Method.resets_critic``), then
        ``pretrain.reset_updates`` SAC updates on the relabelled buffer.

        B-Pref's ``agent.reset_critic()`` then ``agent.update_after_reset(gradient_update=reset_update)``
        (``train_PEBBLE.py``; ``agent/sac.py``): critic, actor and temperature steps on the learned
        reward. The target critic moves on this project's update counter (``SAC.update``), where B-Pref
        moves it on the even indices of these updates.
        """
        agent = self.trainer.agent
        key_reset, key_updates = jax.random.split(key)
        if self.trainer.method.resets_critic(self.cfg):
            agent_state = agent.reset_critic(agent_state, key_reset)

        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            batch = replay.sample(buffer, key_sample, agent.batch_size, True)
            return agent.update(state, batch, key_update, None)[0], None

        keys = jax.random.split(key_updates, self.cfg.pretrain.reset_updates)
        return jax.lax.scan(one, agent_state, keys)[0]

    def feedback_session(self, ts, first: jax.Array, index: jax.Array, agent_step: jax.Array) -> tuple[Any, dict]:
        """select -> teach -> learn at session ``index``, with the session's metrics (:data:`SESSION_METRICS`)."""
        del agent_step  # Unused: the state methods' terms read no agent step.
        ts, asked = self.session_queries(ts, first)
        labels, mask, info = self.teach(ts, asked.key_teach, asked.seg_a, asked.seg_b, index)
        return self.session_learn(ts, asked, labels, mask, first, info)

    def session_queries(self, ts, first: jax.Array) -> tuple[Any, SessionQueries]:
        """The first half of a session: its keys and query pairs (the method's ``query_segments``)."""
        key, key_select, key_teach, key_learn = jax.random.split(ts.key, 4)
        ts = ts.replace(key=key)
        seg_a, seg_b = self.trainer.method.query_segments(self.trainer, ts, key_select, first)
        return ts, SessionQueries(seg_a, seg_b, key_teach, key_learn)

    def session_learn(self, ts, asked: SessionQueries, labels, mask, first, info: dict) -> tuple[Any, dict]:
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
        return ts, summary(SESSION_METRICS, ts, dict(metrics, session=1.0, **teacher))

    def round_metrics(self, buffer: replay.Buffer) -> dict[str, jax.Array]:
        """:data:`ROUND_REWARD_METRICS` on the transitions this round wrote (the policy's own, this round)."""
        rows = queries.window_index(buffer, min(self.trainer.steps_per_round, buffer.rows))
        learned, true = buffer.learned_reward[rows].reshape(-1), buffer.true_reward[rows].reshape(-1)
        return {
            "round_learned_mean": jnp.mean(learned),
            "round_learned_saturated": saturated_fraction(learned, self.reward_cfg.output),
            "round_reward_correlation": pearson(learned, true),
        }

    # -- PEBBLE's unsupervised phase ------------------------------------------------------------
    def init_entropy_stats(self):
        """The running statistics of the pre-training kNN distances."""
        return pretrain.init_stats(self.cfg.pretrain.running_std)

    def intrinsic_batches(self, batches, stats, buffer: replay.Buffer):
        """A vector step's minibatches (stacked, in order) with PEBBLE's state-entropy reward: the kNN over the rows
        written before the buffer wraps, one search for all of them (``pretrain.intrinsic_rewards``)."""
        early = buffer.replace(obs=buffer.obs[: max(self.trainer.pretrain_steps, 1)])
        rewards, stats = pretrain.intrinsic_rewards(self.cfg.pretrain, stats, batches.obs, early)
        return batches.replace(reward=rewards), stats
