"""DrQ-v2 on a pixel task in the scanned round: ``--algo drqv2`` (true reward) and ``--algo pebble``
(SURF's pixel PEBBLE: the reward learned from preferences by :mod:`rebel_jax.pixel_reward`).

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

``--algo pebble`` on a pixel task follows SURF's ``pixel_train_PEBBLE.py`` (alinlab/SURF 214bc1d,
branch ``pixel``):

- no unsupervised phase (README's ``num_unsup_frames=0``): the first feedback session comes right
  after the seed steps (pixel_train_PEBBLE.py:383), then one every ``feedback.interval`` agent steps
  (SURF's ``num_interact`` frames, :428), as a ``lax.cond`` on the unbatched round index at the start
  of a round (as :class:`rebel_jax.train.Trainer`);
- the buffer's ``reward`` is the learned one: each step stores the ensemble mean of the new
  transition (pixel_train_PEBBLE.py:493-514), and each session relabels every row
  (``relabel_with_predictor``, :399, :445). The task's reward is kept beside it (``true_reward``,
  as SURF's episodes keep ``true_reward``, :513) for the teacher; DrQ-v2's n-step returns read the
  learned one. Relabelling once per session, not at sampling, fits the frame replay: a sample would
  otherwise run the 3 encoders on every one of its ``batch_size x 2`` stacks at every update;
- at the first feedback session the critic is re-initialised and ``pretrain.reset_updates`` DrQ-v2 updates
  follow (``agent.reset_critic()``, ``update_after_reset(gradient_update=reset_update)``, :413-420);
- the label store keeps copies of its segments (a :class:`rebel_jax.reward_model.PairStore` of frames: the
  ``H + stack - 1`` frames of an ``H``-step segment, each once as uint8, and its actions), taken from the
  replay when the teacher answers; SURF keeps replay indices (``buffer_seg*_index``,
  pixel_reward_model.py:200-203) in a replay of 1M transitions (config_pebble.yaml:18), which never evicts in
  its 500k-step runs. With copies the replay needs no more than DrQ-v2's: ``train.buffer_capacity`` 0 is
  :data:`DEFAULT_CAPACITY` here too (a ring of the last 100k transitions, 2.13 GB per seed at 84x84, where
  the whole run was 10.6 GB), and queries, SURF's pool and REBEL's replay segments come from the complete
  episodes it still holds (``pixel_reward.sample_segments``). The store is sized by the label budget:
  ``labels x 2`` segments of 52 frames (50 steps), 440 MB per seed for 200 labels, 2.2 GB for 1,000
  (``pixel_reward.store_bytes``); SURF's pool the same per pair. What changes against SURF is the agent's
  replay (the last 100k transitions, not the run), as for ``--algo drqv2``; the labelled frames are SURF's.
  Each session relabels every row the ring holds. ``--buffer-capacity 500000`` keeps the whole run.

A method changes the session's queries, the agent's batches and their reward through its pixel hooks
(``Method.pixel_query_segments``, ``pixel_sample_batch``, ``pixel_batch_reward``; QPA's and RUNE's), whose
defaults are the calls above.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from rebel_jax import frame_replay, pixel_reward, reward_model, teachers
from rebel_jax.config import Config
from rebel_jax.drqv2 import DrQV2, DrQV2State
from rebel_jax.envs import State, make_env
from rebel_jax.envs.pixels import agent_steps
from rebel_jax.errors import check
from rebel_jax.queries import Segments
from rebel_jax.train import (
    EpisodeStats,
    _all_finite,
    init_trajectory,
    record_trajectory,
    reward_training_metrics,
    session_due,
    session_index,
    within_budget,
)

PIXEL_SESSION_METRICS = (
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
)
"""Per-round metrics of a pixel feedback session (NaN in rounds without one, except ``labels_used``).
``reward_correlation`` is the Pearson correlation of the relabelled (learned) and the true reward over
every written row of the replay, per step. ``session_skipped``, ``session_equal`` and ``session_oracle_agreement``
are the scripted teacher's, as in :data:`rebel_jax.train.SESSION_METRICS`."""

METRICS = ("critic_loss", "actor_loss", "q", "target_q", "std")

DEFAULT_CAPACITY = 100_000
"""Replay transitions per seed when ``train.buffer_capacity`` is 0 (at most ``train.total_steps``), for DrQ-v2
and the preference runs alike: 2.13 GB of 84x84 frames per seed (:mod:`rebel_jax.frame_replay`). DrQ-v2 keeps
1M (config.yaml:18), 21 GB per seed; SURF's pixel PEBBLE the same (config_pebble.yaml:18)."""


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
      reward: the pixel reward ensemble and its labels (``--algo pebble``; None for drqv2).
      teacher: the scripted teacher's knobs (``teachers.knobs``), traced (None for drqv2).
      lam: () REBEL's signed lambda, traced so that a sweep can vmap over it (None unless rebel).
      eval_trajectory: REBEL's on-policy V (``rebel.source='onpolicy'``; else None): the first
        ``rebel.episodes`` evaluation environments' newest frames and actions over the first
        ``rebel.horizon`` agent steps T of their episodes (:func:`rebel_jax.train.record_trajectory`),
        ``current`` being written and ``last`` the last complete one, each ``{"frame": (T, episodes, H, W,
        3) uint8, "action": (T, episodes, A)}``; the stacks are rebuilt from the frames
        (:func:`rebel_jax.frame_replay.episode_stacks`).
    """

    sac: DrQV2State
    buffer: frame_replay.FrameBuffer
    env: State
    episodes: EpisodeStats
    key: jax.Array
    eval_policy: Any
    reward: reward_model.RewardState | None = None
    teacher: dict | None = None
    lam: jax.Array | None = None
    eval_trajectory: dict | None = None


def policy_of(agent_state: DrQV2State) -> dict:
    """The deterministic policy's parameters: encoder and actor."""
    return {"encoder": agent_state.encoder_params, "actor": agent_state.actor_params}


def check_config(cfg: Config) -> None:
    """The pixel preference runs' checks in agent steps, before anything is built or written.

    The label store keeps copies, so the replay is a ring of recent episodes: the stored segments (and the
    method's own, e.g. REBEL's V) must fit an episode, a complete episode must precede the first feedback
    session, and the ring must hold a complete episode whatever the running one's step (2 L - 1 rows).

    Raises:
      ConfigError: naming the settings.
    """
    if not cfg.preference:
        return
    length = agent_steps(cfg.env.episode_length)
    stored = cfg.query.segment_length + 2 * cfg.method.crop(cfg)
    capacity = cfg.train.buffer_capacity or min(cfg.train.total_steps, DEFAULT_CAPACITY)
    envs = cfg.env.num_envs
    crop = f" + 2 x crop {cfg.method.crop(cfg)}" if cfg.method.crop(cfg) else ""
    allowed = f"query.segment_length{crop} <= {length} agent steps (one episode)"
    check(stored <= length, "query.segment_length", cfg.query.segment_length, allowed)
    for field, steps in cfg.method.episode_lengths(cfg).items():
        check(steps <= length, field, steps, f"<= {length} agent steps per episode")
    check(
        cfg.feedback_start // envs >= length,
        "train.seed_steps",
        cfg.train.seed_steps,
        f">= num_envs x {length} agent steps: a complete episode before the first feedback session",
    )
    check(
        capacity // envs >= 2 * length - 1,
        "train.buffer_capacity",
        capacity,
        f">= num_envs x {2 * length - 1} rows: a complete episode in the replay at any step",
    )


class PixelTrainer:
    """Builds the pure functions of one seed's DrQ-v2 run from a :class:`Config` (``algo='drqv2'``)."""

    def __init__(self, cfg: Config):
        self.cfg = cfg.validate()
        if cfg.algo == "sac" or not cfg.pixels:
            raise ValueError(f"PixelTrainer runs drqv2 or pebble on a pixel task, not {cfg.algo!r} on {cfg.env.task!r}")
        self.env = make_env(cfg.env.task, solver=cfg.env.solver, episode_length=cfg.env.episode_length)
        self.agent = DrQV2(cfg.drqv2, self.env.observation_shape, self.env.action_size)
        self.num_train = cfg.env.num_envs
        self.num_all = cfg.env.num_envs + cfg.train.eval_episodes
        self.episode_length = self.env.episode_length  # agent steps
        self.steps_per_round = cfg.train.steps_per_round // cfg.env.num_envs  # vector steps
        every = cfg.drqv2.update_every
        self.updates_per_step = max(1, self.num_train // every)
        self.update_period = max(1, every // self.num_train)  # vector steps between updates
        self.preference = cfg.preference
        self.method = cfg.method
        self.reward_cfg = cfg.pixel_reward
        self.capacity = cfg.train.buffer_capacity or min(cfg.train.total_steps, DEFAULT_CAPACITY)
        check_config(cfg)
        if self.preference:  # The label store keeps copies: the replay is a ring of recent episodes.
            self.horizon = cfg.query.segment_length
            self.crop = self.method.crop(cfg)
            self.stored = self.horizon + 2 * self.crop  # SURF stores H + 2 c steps (size_segment, :195)
            sessions = -(-cfg.feedback.labels // cfg.feedback.queries)
            self.pool_capacity = self.method.pool_size(cfg) * sessions
        # The evaluation episodes kept for the method's loss (REBEL's on-policy V): (episodes, steps), or None.
        self.trajectory_size = self.method.trajectory_size(cfg, self.episode_length, True) if self.preference else None
        self.trace_count = 0
        self._looped_session = loop_in_place(self._feedback_session)

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
            true_reward=self.preference,
        )
        ts = PixelTrainState(
            sac=agent,
            buffer=buffer,
            env=self._reset_envs(key_env),
            episodes=EpisodeStats(jnp.zeros(self.num_all), *[jnp.full((), jnp.nan, jnp.float32)] * 2),
            key=key,
            eval_policy=policy_of(agent),
        )
        if not self.preference:
            return ts
        key, key_reward = jax.random.split(key)
        shape, labels = self.env.observation_shape, self.cfg.feedback.labels
        actions = self.env.action_size
        reward = pixel_reward.init(self.cfg.pixel_reward, key_reward, shape, actions, labels, self.stored)
        if self.pool_capacity:
            reward = reward.replace(pool=pixel_reward.empty_store(self.pool_capacity, self.stored, shape, actions))
        lam = self.method.knob(self.cfg)
        ts = ts.replace(key=key, reward=reward, teacher=teachers.knobs(self.cfg.teacher), lam=lam)
        if self.trajectory_size:
            fields = {"frame": (shape[:2] + (3,), jnp.uint8), "action": ((self.env.action_size,), jnp.float32)}
            ts = ts.replace(eval_trajectory=init_trajectory(fields, *self.trajectory_size))
        return ts

    def _reset_envs(self, key: jax.Array) -> State:
        return jax.vmap(self.env.reset)(jax.random.split(key, self.num_all))

    def mean_action(self, policy: dict, obs: jax.Array) -> jax.Array:
        """The deterministic action of ``policy`` (:meth:`policy_params`) at frame stacks ``obs`` (..., H, W, C)."""
        return self.agent.actor.apply(policy["actor"], self.agent.encoder.apply(policy["encoder"], obs))

    def _act(self, ts: PixelTrainState, t: jax.Array, key: jax.Array) -> jax.Array:
        key_policy, key_random = jax.random.split(key)
        obs, n = ts.env.obs, self.num_train
        explore = self.agent.act(ts.sac, obs[:n], key_policy, t * n)
        random = jax.random.uniform(key_random, explore.shape, minval=-1.0, maxval=1.0)
        train_action = jnp.where(t * n < self.cfg.train.seed_steps, random, explore)
        return jnp.concatenate([train_action, self.mean_action(ts.eval_policy, obs[n:])])

    def _record(self, ts: PixelTrainState, nxt: State, action: jax.Array, t: jax.Array):
        n = self.num_train
        truncated = nxt.info["truncation"]
        reward, true_reward = nxt.reward[:n], None
        if self.preference:  # SURF stores r_hat(stack, action), keeps the true reward (pixel_train_PEBBLE.py:493-514).
            reward, true_reward = self._learned_reward(ts.reward.params, ts.env.obs[:n], action[:n]), reward
        step = frame_replay.FrameStep(
            obs=ts.env.obs[:n],
            action=action[:n],
            next_obs=nxt.obs[:n],
            reward=reward,
            terminal=(nxt.done - truncated)[:n],
            truncated=truncated[:n],
            episode_step=(t % self.episode_length).astype(jnp.int32),
            true_reward=true_reward,
        )
        episodes = ts.episodes.after_step(nxt.reward, nxt.done, n)
        return frame_replay.add(ts.buffer, step), episodes

    def _updates(self, ts: PixelTrainState, buffer: frame_replay.FrameBuffer, key: jax.Array, agent_step: jax.Array):
        """DrQ-v2's updates of one vector step from ``ts.sac``: the method's batches (``Method.pixel_sample_batch``)
        and reward (``Method.pixel_batch_reward``) on a preference run, uniform batches of the true reward else."""
        cfg = self.cfg.drqv2

        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            if not self.preference:
                batch = frame_replay.sample(buffer, key_sample, cfg.batch_size, cfg.nstep, cfg.gamma)
            else:
                batch = self.method.pixel_sample_batch(self, ts, buffer, key_sample)
                batch = self.method.pixel_batch_reward(self, ts, batch, agent_step)
            return self.agent.update(state, batch, key_update, agent_step)

        agent, metrics = jax.lax.scan(one, ts.sac, jax.random.split(key, self.updates_per_step))
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
            lambda: self._updates(ts, buffer, key_update, t * self.num_train),
            lambda: (ts.sac, zeros),
        )
        ts = ts.replace(sac=agent, buffer=buffer, env=nxt, episodes=episodes)
        if self.trajectory_size:  # The evaluation environments' step: the newest frame acted on, the action.
            first, end = self.num_train, self.num_train + self.trajectory_size[0]
            step = {"frame": env_state.obs[first:end, ..., -3:], "action": action[first:end]}
            trajectory = record_trajectory(ts.eval_trajectory, step, t, self.episode_length)
            ts = ts.replace(eval_trajectory=trajectory)
        return ts, dict(metrics, learning=learning.astype(jnp.float32))

    # -- feedback session (--algo pebble) --------------------------------------------------
    def _learned_reward(self, params, obs: jax.Array, action: jax.Array) -> jax.Array:
        return reward_model.mean_reward(self.cfg.pixel_reward, params, obs, action)

    def session_due(self, round_index: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Whether round ``round_index`` starts with a feedback session, and whether it is the first."""
        return session_due(self.cfg, round_index)

    def select(self, ts: PixelTrainState, key: jax.Array, first: jax.Array):
        """The session's query pairs as segment places (uniform at the first feedback session): the default of
        ``Method.pixel_query_segments``."""
        cfg = self.cfg
        return pixel_reward.select(
            cfg.pixel_reward,
            key,
            ts.reward.params,
            ts.buffer,
            cfg.feedback.queries,
            self.stored,
            self.episode_length,
            cfg.query.recent_episodes,
            cfg.query.sampling,
            cfg.query.candidate_factor,
            first,
        )

    def teach(self, ts: PixelTrainState, key: jax.Array, seg_a, seg_b, index: jax.Array):
        """The scripted teacher on the stored true rewards of the segments, masked to the remaining budget at
        session ``index`` (:func:`rebel_jax.train.within_budget`).

        The margin (skip / equal thresholds) is ``H x`` the mean true reward of the written rows.

        Returns:
          ``(labels, mask, info)``: :func:`rebel_jax.teachers.label`'s, the mask limited to the budget, and
          ``info`` with the share of the kept answers that are the oracle's (``oracle_agreement``).
        """
        buffer = ts.buffer
        written = (jnp.arange(buffer.rows) < buffer.size)[:, None]
        count = jnp.maximum(jnp.sum(written) * buffer.num_envs, 1)
        margin = self.horizon * jnp.sum(jnp.where(written, buffer.true_reward, 0.0)) / count
        # The central H steps of SURF's H + 2c (get_label, pixel_reward_model.py:578-580).
        seg_a, seg_b = self._central(seg_a), self._central(seg_b)
        true_a = Segments(obs=None, action=None, true_reward=pixel_reward.true_returns(buffer, seg_a, self.horizon))
        true_b = Segments(obs=None, action=None, true_reward=pixel_reward.true_returns(buffer, seg_b, self.horizon))
        labels, mask, info = teachers.label(teachers.TeacherConfig(**ts.teacher), key, true_a, true_b, margin)
        mask = within_budget(self.cfg.feedback, mask, ts.reward.data.count, index)
        info = dict(info, oracle_agreement=teachers.oracle_agreement(key, true_a, true_b, labels, mask))
        return labels, mask, info

    def _central(self, seg: pixel_reward.SegmentPlaces) -> pixel_reward.SegmentPlaces:
        return seg.replace(row=seg.row + self.crop)

    def learn(self, ts: PixelTrainState, key: jax.Array, seg_a, seg_b, labels, mask, first, agent_step):
        """Stores the answers, trains the ensemble, relabels the replay; new critic at the first feedback session."""
        key_train, key_critic, key_value = jax.random.split(key, 3)
        rcfg, h = self.cfg.pixel_reward, self.horizon
        both = jax.tree.map(lambda a, b: jnp.concatenate([a, b]), self._central(seg_a), self._central(seg_b))
        returns = pixel_reward.ensemble_returns(rcfg, ts.reward.params, ts.buffer, both, h)
        n = labels.shape[0]
        new_logits = returns[:, n:] - returns[:, :n]
        hard = (labels != 0.5) * mask
        correct = ((new_logits > 0) == (labels > 0.5)) * hard
        accuracy_new = jnp.sum(correct) / jnp.maximum(jnp.sum(hard) * rcfg.ensemble_size, 1.0)
        kept = jnp.sum(mask)
        stored = pixel_reward.add_labels(ts.reward, ts.buffer, seg_a, seg_b, labels, mask)
        keys = {"train": key_train, "terms": key_value, "pool": key_value}
        trained, train_metrics = self.method.train_reward(self, ts, stored, keys, kept, agent_step)
        # A session without a kept label trains no epoch (``epochs`` above; SURF and B-Pref hold no session
        # once the budget is spent), so its members and Adam state come back as they were: no select needed.
        reward = trained
        buffer = frame_replay.relabel(
            ts.buffer, lambda obs, action: self._learned_reward(reward.params, obs, action), rcfg.relabel_rows
        )
        new = ts.replace(buffer=buffer, reward=reward)
        agent = jax.lax.cond(first, lambda: self._reset_critic(new, key_critic, agent_step), lambda: ts.sac)
        written = (jnp.arange(buffer.rows) < buffer.size)[:, None] * jnp.ones((1, buffer.num_envs))
        metrics = reward_training_metrics(accuracy_new, train_metrics, kept)
        metrics["reward_correlation"] = weighted_pearson(buffer.reward, buffer.true_reward, written)
        return ts.replace(sac=agent, buffer=buffer, reward=reward), metrics

    def _reset_critic(self, ts: PixelTrainState, key: jax.Array, agent_step):
        """A fresh critic for ``ts.sac``, then ``pretrain.reset_updates`` DrQ-v2 updates on ``ts.buffer``
        (pixel_train_PEBBLE.py:413-420): uniform batches (QPA's ``update_after_reset`` samples uniformly,
        huxiao09/QPA@7e9e49e:agent/sac.py:334-337) with the method's reward (RUNE's ``update_after_reset`` adds
        its bonus, rll-research/rune@8b3c77a:agent/sac_explore.py:399-411)."""
        cfg, buffer = self.cfg.drqv2, ts.buffer
        key_reset, key_updates = jax.random.split(key)
        agent = self.agent.reset_critic(ts.sac, key_reset)

        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            batch = frame_replay.sample(buffer, key_sample, cfg.batch_size, cfg.nstep, cfg.gamma)
            batch = self.method.pixel_batch_reward(self, ts, batch, agent_step)
            return self.agent.update(state, batch, key_update, agent_step)[0], None

        return jax.lax.scan(one, agent, jax.random.split(key_updates, self.cfg.pretrain.reset_updates))[0]

    def feedback_session(self, ts: PixelTrainState, first: jax.Array, agent_step: jax.Array, index: jax.Array):
        """select -> teach -> learn at session ``index``, with :data:`PIXEL_SESSION_METRICS`.

        With ``pixel_reward.session_loop`` a ``vmap`` of this method runs one column's session at a time
        (:func:`loop_in_place`); called unbatched it is the same session either way."""
        if self.cfg.pixel_reward.session_loop:  # Positional arguments: custom_vmap takes no keywords.
            return self._looped_session(ts, first, agent_step, index)
        return self._feedback_session(ts, first, agent_step, index)

    def _feedback_session(self, ts: PixelTrainState, first: jax.Array, agent_step: jax.Array, index: jax.Array):
        """:meth:`feedback_session` as one batched computation under ``vmap``."""
        key, key_select, key_teach, key_learn = jax.random.split(ts.key, 4)
        ts = ts.replace(key=key)
        seg_a, seg_b = self.method.pixel_query_segments(self, ts, key_select, first)
        labels, mask, info = self.teach(ts, key_teach, seg_a, seg_b, index)
        ts, metrics = self.learn(ts, key_learn, seg_a, seg_b, labels, mask, first, agent_step)
        return ts, self._session_summary(ts, dict(metrics, session=1.0, **teachers.session_metrics(info)))

    def _session_summary(self, ts: PixelTrainState, metrics: dict) -> dict:
        nan = jnp.full((), jnp.nan, jnp.float32)
        out = {k: jnp.asarray(metrics.get(k, nan), jnp.float32) for k in PIXEL_SESSION_METRICS}
        out["labels_used"] = ts.reward.data.count.astype(jnp.float32)
        return out

    # -- the round ------------------------------------------------------------------------
    def round(self, ts: PixelTrainState, round_index: jax.Array) -> tuple[PixelTrainState, dict]:
        """``steps_per_round`` agent steps per seed with their updates, as one ``lax.scan``; with
        ``--algo pebble`` a round on the feedback schedule starts with a session.

        Returns:
          The new state and the round's metrics: DrQ-v2's losses averaged over the round's updates,
          the last finished training and evaluation returns, ``diverged`` and (pebble) the session's metrics.
        """
        self.trace_count += 1  # Python side effect: counts traces, not calls.
        session = {}
        if self.preference:
            due, first = self.session_due(round_index)
            agent_step = round_index * self.cfg.train.steps_per_round
            ts, session = jax.lax.cond(
                due,
                lambda ts: self.feedback_session(ts, first, agent_step, session_index(self.cfg, round_index)),
                lambda ts: (ts, self._session_summary(ts, {})),
                ts,
            )
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
        finite = _all_finite(({k: summary[k] for k in METRICS}, ts.sac, ts.episodes.running, ts.reward))
        summary["diverged"] = 1.0 - (finite & returns_ok[0] & returns_ok[1]).astype(jnp.float32)
        return ts, {**summary, **session}

    def evaluate(self, policy: dict, key: jax.Array, random_actions: bool | jax.Array = False) -> jax.Array:
        """Mean true return of ``eval_episodes`` episodes of the mean action of ``policy`` (:func:`policy_of`),
        or of uniform random actions on the same initial states (as :meth:`Trainer.evaluate`)."""
        key_reset, key_actions = jax.random.split(key)
        state = jax.vmap(self.env.reset)(jax.random.split(key_reset, self.cfg.train.eval_episodes))

        def body(carry, key):
            state, total = carry
            uniform = jax.random.uniform(key, (state.obs.shape[0], self.env.action_size), minval=-1.0, maxval=1.0)
            action = jnp.where(random_actions, uniform, self.mean_action(policy, state.obs))
            state = jax.vmap(self.env.step)(state, action)
            return (state, total + state.reward), None

        keys = jax.random.split(key_actions, self.episode_length)
        (_, total), _ = jax.lax.scan(body, (state, jnp.zeros(state.reward.shape)), keys)
        return total.mean()


def loop_in_place(fn: Callable) -> Callable:
    """``fn(state, *args) -> (state, aux)`` whose ``vmap`` runs one column at a time, as
    ``jax.custom_batching.sequential_vmap(fn)``, with the batched ``state`` carried through the loop (a
    ``fori_loop``) and each column's new state written back into it (``.at[i].set``).

    ``sequential_vmap`` runs ``lax.map``, whose stacked outputs are a fresh buffer beside its inputs: a second
    copy of the whole batched state (replay, label store, SURF's pool) in the round's working memory, on top of
    the column being computed. ``memory_analysis()`` of the round (``benchmarks/pixel_memory.py``, surf_cheetah,
    3 seeds, bf16, CPU): temp 73.3 GiB beside a state of 51.3 GiB (the pool 36.7 GiB), where the GPU run died
    allocating 72.6 GiB; carried, 27.9 GiB (batched sessions: 15.2 GiB). What remains is about one column's copy
    of its state (17.1 GiB there): each column's session reads and writes a slice of the carry.
    Same numbers as ``sequential_vmap``: one column at a time, each reading its own column only.
    """
    fn = jax.custom_batching.custom_vmap(fn)

    @fn.def_vmap
    def rule(axis_size: int, in_batched: list, state, *args):
        def batch(x, batched):
            return x if batched else jnp.broadcast_to(x, (axis_size, *jnp.shape(x)))

        def columns(i, state):
            """Column ``i`` of the batched state and of the batched arguments (unbatched ones as they are)."""
            pairs = zip(args, in_batched[1:], strict=True)
            args_i = [jax.tree.map(lambda x, b: x[i] if b else x, arg, batched) for arg, batched in pairs]
            return jax.tree.map(lambda x: x[i], state), *args_i

        state = jax.tree.map(batch, state, in_batched[0])
        aux = jax.eval_shape(lambda: fn(*columns(0, state))[1])
        aux = jax.tree.map(lambda s: jnp.zeros((axis_size, *s.shape), s.dtype), aux)

        def body(i, carry):
            # Column i of the carried state, not of ``state``: reading the input would keep it alive beside the carry.
            new = fn(*columns(i, carry[0]))
            return jax.tree.map(lambda out, x: out.at[i].set(x), carry, new)

        out = jax.lax.fori_loop(0, axis_size, body, (state, aux))
        return out, jax.tree.map(lambda _: True, out)

    return fn


def weighted_pearson(x: jax.Array, y: jax.Array, weight: jax.Array) -> jax.Array:
    """Pearson correlation of ``x`` and ``y`` over the entries of weight 1 (NaN if either is constant there)."""
    total = jnp.maximum(jnp.sum(weight), 1.0)
    mx, my = jnp.sum(weight * x) / total, jnp.sum(weight * y) / total
    cov = jnp.sum(weight * (x - mx) * (y - my))
    return cov / jnp.sqrt(jnp.sum(weight * (x - mx) ** 2) * jnp.sum(weight * (y - my) ** 2))
