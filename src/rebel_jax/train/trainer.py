"""The composition: one trainer for state and pixel tasks, the scanned training round, evaluation.

One seed's run is a pure function of a PRNG key: ``init(key)`` then ``round(state, r)`` for r = 0, 1, ...
:class:`Trainer` composes five parts, chosen by the config:

- the **task** (:func:`rebel_jax.envs.make_env`): state vectors, or frame stacks on a pixel task;
- the **agent** (:class:`rebel_jax.agents.base.Agent`): SAC on state tasks, DrQ-v2 on pixel tasks, with its update
  schedule;
- the **replay** (the contract of :mod:`rebel_jax.agents.replay`): the state ring, or the frame ring
  (:mod:`rebel_jax.agents.frame_replay`);
- the **reward model** and its feedback session (preference methods):
:class:`rebel_jax.preference.feedback.StateFeedback`
  or :class:`rebel_jax.preference.pixel_feedback.PixelFeedback`;
- the **method** (:mod:`rebel_jax.methods`): what tells PEBBLE, SURF, REBEL, QPA and RUNE apart, through its hooks.

Each round is a single ``lax.scan`` over vector env steps, each step followed by the agent's updates due then;
``jax.vmap`` runs many seeds at once and :mod:`rebel_jax.train.placement` shards the seed axis over devices. A Python
loop
over rounds drives progress, logging and checkpoints (``python -m rebel_jax.train``).

Episodes of all environments (training and evaluation, all seeds) start together: every ``episode_length``
vector steps all environments reset at once. The vector-step index is the same for every seed, so it is passed
*unbatched* and the reset is a real ``lax.cond`` even under ``vmap`` (a per-environment auto-reset would become a
select that pays for a reset every step).

The preference methods add two things to a round. On state tasks, vector steps before ``feedback_start`` update
SAC on PEBBLE's unsupervised state-entropy reward (:mod:`rebel_jax.preference.pretrain`); and a round that starts on the
feedback schedule (:mod:`rebel_jax.preference.budget`) first runs a *feedback session* (select, teach, learn), a
``lax.cond`` on the (unbatched) round index, so rounds without one skip it. A trainer built with
``host_teacher=True`` (the human and replay teachers, :mod:`rebel_jax.run.human`; state tasks) leaves the session out
of the round: the host runs :meth:`Trainer.session_queries`, gets the answers, and runs
:meth:`Trainer.session_learn` before the round; its buffer also stores each transition's physics positions, from
which the clips are rendered.

Evaluation runs inside the same batch: ``eval_episodes`` extra environments follow the deterministic policy (the
mean action) next to the ``num_envs`` training environments, so evaluation costs no extra env-step latency. As
B-Pref's ``evaluate``, each evaluation episode runs one frozen policy: the agent's policy parameters are copied
into ``TrainState.eval_policy`` when the episode starts. :meth:`Trainer.evaluate` runs separate episodes of a
given policy (used for the final evaluation).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import jax.numpy as jnp

from rebel_jax.agents import frame_replay, replay
from rebel_jax.agents.base import Agent
from rebel_jax.agents.drqv2 import DrQV2
from rebel_jax.agents.sac import SAC
from rebel_jax.config import Config, ConfigError
from rebel_jax.envs import State, VmapWrapper, make_env
from rebel_jax.preference import budget, pixel_feedback, teachers
from rebel_jax.preference.feedback import StateFeedback, summary
from rebel_jax.preference.pixel_feedback import PixelFeedback
from rebel_jax.train.episodes import EpisodeStats, all_finite, init_trajectory, physics_positions, record_trajectory
from rebel_jax.train.placement import on_second_stream
from rebel_jax.train.state import METHOD_KEY, TrainState, method_mean, nan_like


class Trainer:
    """Builds the pure functions of one seed's run from a :class:`Config`, on a state or a pixel task."""

    def __init__(self, cfg: Config, host_teacher: bool = False, columns: int = 1):
        """
        Args:
          cfg: the run's configuration.
          host_teacher: the feedback sessions run on the host between rounds (the human and replay
            teachers): the round leaves them out and the buffer stores physics positions for clips.
          columns: the most columns (seeds, settings) that one device runs; with ``env.impl='warp'`` the physics
            step's contact buffer is sized for that many columns' environments.
        """
        self.cfg = cfg.validate()
        self.pixels, self.preference, self.method = cfg.pixels, cfg.preference, cfg.method
        if host_teacher and (not cfg.preference or cfg.pixels):
            raise ValueError(f"host_teacher needs a preference algo on a state task, not {cfg.algo!r}")
        if self.pixels:
            pixel_feedback.check_config(cfg)
        self.host_teacher = host_teacher
        if cfg.train.overlap and jax.default_backend() == "gpu" and jax.__version_info__ >= (0, 11):
            raise ConfigError(
                "--overlap is refused on GPUs with JAX >= 0.11: XLA aborted its second-stream program with JAX 0.11.2"
            )
        self.num_train = cfg.env.num_envs
        self.num_all = cfg.env.num_envs + cfg.train.eval_episodes
        self.env = make_env(
            cfg.env.task,
            cfg.env.solver,
            cfg.env.episode_length,
            unroll_substeps=cfg.env.unroll_substeps,
            all_contacts=cfg.env.all_contacts,
            impl=cfg.env.impl,
            # Environments in one vmapped step: the round's, or the final evaluation's of the policy and of random
            # actions together (compiled's evaluate).
            worlds=columns * max(self.num_all, 2 * cfg.train.eval_episodes),
        )
        self.episode_length = self.env.episode_length  # agent steps
        # A task whose steps report ``success`` (Meta-World's): its episodes' success rates are logged too.
        self.reports_success = bool(getattr(self.env, "reports_success", False))
        env, actions = self.env, self.env.action_size
        self.obs_shape = env.observation_shape if self.pixels else (env.observation_size,)
        self.agent: Agent = (
            DrQV2(cfg.drqv2, env.observation_shape, actions)
            if self.pixels
            else SAC(cfg.sac, env.observation_size, actions)
        )
        self.ring = frame_replay if self.pixels else replay
        # brax's VmapWrapper: reset(key) resets the envs on jax.random.split(key, batch_size).
        self.envs = VmapWrapper(self.env, batch_size=self.num_all)  # training, then in-batch evaluation
        self.eval_envs = VmapWrapper(self.env, batch_size=cfg.train.eval_episodes)  # Trainer.evaluate
        self.steps_per_round = cfg.train.steps_per_round // cfg.env.num_envs  # vector steps
        self.schedule = self.agent.schedule(self.num_train)
        self.updates_per_step, self.update_period = self.schedule.per_step, self.schedule.period
        self.capacity = pixel_feedback.capacity(cfg) if self.pixels else cfg.train.capacity
        # The reward ensemble's settings. On state tasks the label store holds exactly the budget; SURF stores
        # segments longer by 2 * crop.
        self.reward_cfg = (
            cfg.pixel_reward if self.pixels else dataclasses.replace(cfg.reward, label_capacity=cfg.feedback.labels)
        )
        self.horizon = cfg.query.segment_length
        self.crop = self.method.crop(cfg) if self.preference else 0
        self.stored_length = self.horizon + 2 * self.crop
        # PEBBLE's unsupervised phase, on state tasks (SURF's pixel PEBBLE has none: num_unsup_frames=0).
        self.pretrain_steps = cfg.feedback_start // cfg.env.num_envs if self.preference and not self.pixels else 0
        self.pretrain_hook = bool(self.pretrain_steps) and self.method.has_pretrain_step()
        self.agent_hook = self.preference and self.method.has_agent_step()
        sessions = -(-cfg.feedback.labels // cfg.feedback.queries)
        self.pool_capacity = self.method.pool_size(cfg) * sessions if self.preference else 0  # every session's
        # The evaluation episodes kept for the method's loss (REBEL's on-policy V): (episodes, steps), or None.
        self.trajectory_size = (
            self.method.trajectory_size(cfg, self.episode_length, self.pixels) if self.preference else None
        )
        # The reward members' optimiser (None: Adam at the reward settings' lr), before the feedback makes them.
        self.reward_optimizer = self.method.reward_optimizer(self) if self.preference else None
        self.feedback = (PixelFeedback if self.pixels else StateFeedback)(self) if self.preference else None
        self.trace_count = 0

    # -- the policy ---------------------------------------------------------------------------
    def policy_params(self, ts: TrainState):
        """What :meth:`evaluate` takes: the agent's policy parameters (``Agent.policy``)."""
        return self.agent.policy(ts.agent)

    def mean_action(self, policy, obs: jax.Array) -> jax.Array:
        """The deterministic action of ``policy`` (:meth:`policy_params`) at ``obs``."""
        return self.agent.mean_action(policy, obs)

    # -- init -----------------------------------------------------------------------------
    def init(self, key: jax.Array) -> TrainState:
        """A fresh run of one seed."""
        key, key_agent, key_env = jax.random.split(key, 3)
        agent = self.agent.init(key_agent)
        ts = TrainState(
            agent=agent,
            buffer=self._init_buffer(),
            env=self.envs.reset(key_env),
            episodes=EpisodeStats.init(self.num_all, success=self.reports_success),
            key=key,
            eval_policy=self.agent.policy(agent),
        )
        if not self.preference:
            return ts
        key, key_reward = jax.random.split(key)
        actions = self.env.action_size
        ts = ts.replace(
            key=key,
            reward=self.feedback.init_reward(key_reward, self.obs_shape, actions, self.pool_capacity),
            entropy_stats=None if self.pixels else self.feedback.init_entropy_stats(),
            lam=self.method.knob(self.cfg),
            teacher=teachers.knobs(self.cfg.teacher),
            # Its own key, folded from the run's without drawing from it: the other parts' draws stay as they were.
            method=self.method.init_state(self, jax.random.fold_in(key, METHOD_KEY)),
        )
        if self.trajectory_size:
            fields = self.feedback.trajectory_fields(self.obs_shape, actions)
            ts = ts.replace(eval_trajectory=init_trajectory(fields, *self.trajectory_size))
        return ts

    def _init_buffer(self):
        n, actions = self.num_train, self.env.action_size
        if self.pixels:
            height, width, _ = self.obs_shape
            size = (self.capacity, n, (height, width, 3), actions, self.episode_length, self.env.frames)
            return frame_replay.init(*size, learned_reward=self.preference)
        return replay.init(self.capacity, n, self.obs_shape[0], actions, self._qpos_size(), self._scene_size())

    def _qpos_size(self) -> int:
        """Physics positions stored per transition: the task's qpos for the host teacher, else none."""
        if not self.host_teacher:
            return 0
        state = jax.eval_shape(self.env.reset, jax.random.PRNGKey(0))
        return physics_positions(state.pipeline_state).shape[-1]

    def _scene_size(self) -> int:
        """Numbers of a frame's scene stored per transition (``env.scene``, a Meta-World task's) for the host teacher,
        else none."""
        if not self.host_teacher or not hasattr(self.env, "scene"):
            return 0
        return jax.eval_shape(lambda key: self.env.scene(self.env.reset(key)), jax.random.PRNGKey(0)).shape[-1]

    # -- one vector step ------------------------------------------------------------------
    def _act(self, ts: TrainState, t: jax.Array, key: jax.Array) -> jax.Array:
        key_policy, key_random = jax.random.split(key)
        obs, n = ts.env.obs, self.num_train
        explore = self.agent.act(ts.agent, obs[:n], key_policy, t * n)
        random = jax.random.uniform(key_random, explore.shape, minval=-1.0, maxval=1.0)
        train_action = jnp.where(t * n < self.cfg.train.seed_steps, random, explore)
        return jnp.concatenate([train_action, self.mean_action(ts.eval_policy, obs[n:])])

    def _record(self, ts: TrainState, nxt: State, action: jax.Array, t: jax.Array):
        """The vector step's transitions written to the replay, and the episodes' returns after it."""
        n = self.num_train
        truncated = nxt.info["truncation"]
        fields = dict(
            obs=ts.env.obs[:n],
            action=action[:n],
            next_obs=nxt.obs[:n],
            true_reward=nxt.reward[:n],
            terminal=(nxt.done - truncated)[:n],
            truncated=truncated[:n],
            # SURF stores r_hat(obs, action) with each transition (pixel_train_PEBBLE.py:493-514).
            learned_reward=self.feedback.mean_reward(ts.reward.params, ts.env.obs[:n], action[:n])
            if self.preference
            else None,
        )
        if self.pixels:  # One agent step for every environment: their episodes start together.
            step = frame_replay.FrameStep(**fields, episode_step=(t % self.episode_length).astype(jnp.int32))
        else:
            qpos = physics_positions(ts.env.pipeline_state)[:n] if self.host_teacher else None
            scene = self.env.scene(ts.env)[:n] if ts.buffer.scene is not None else None  # as _init_buffer chose
            step = replay.Step(**fields, episode_step=ts.env.info["steps"][:n], qpos=qpos, scene=scene)
        episodes = ts.episodes.after_step(nxt.reward, nxt.done, n, nxt.info.get("success"))
        return self.ring.add(ts.buffer, step), episodes

    def sample(self, buffer, key: jax.Array, learned_reward: bool):
        """The agent's minibatch, uniform over the replay (the default of ``Method.sample_batch``)."""
        return self.ring.sample(buffer, key, self.agent.batch_size, learned_reward, **self.agent.sample_args)

    def _updates(self, ts: TrainState, buffer, key: jax.Array, t: jax.Array, pretraining: jax.Array | bool = False):
        """The agent's updates of one vector step: its minibatches drawn first (``Method.sample_batch`` on a
        preference run), then rewarded (``Method.batch_reward``, or PEBBLE's intrinsic reward while ``pretraining``: one
        kNN search, then scaled minibatch by minibatch), then one update on each: one update program for every phase."""
        agent_step = t * self.num_train
        keys = jax.vmap(jax.random.split)(jax.random.split(key, self.updates_per_step))  # (updates, 2): sample, update

        def draw(key):
            if self.preference:
                return self.method.sample_batch(self, ts, buffer, key)
            return self.sample(buffer, key, False)

        def stored(batches, stats):  # the stored (learned or true) reward, and the method's bonus on it
            if self.preference:
                batches = jax.vmap(lambda batch: self.method.batch_reward(self, ts, batch, agent_step))(batches)
            return batches, stats

        def intrinsic(batches, stats):
            return self.feedback.intrinsic_batches(batches, stats, buffer)

        batches = jax.vmap(draw)(keys[:, 0])
        extra, own = (), {}
        if self.pretrain_hook:  # the method's step too: (reward, method state) and its metrics, NaN after the phase
            name, key_method = self.method.name, jax.random.fold_in(key, METHOD_KEY)

            def hooked(batches, stats, reward, state):
                batches, stats = intrinsic(batches, stats)
                inner = ts.replace(reward=reward, method=state, entropy_stats=stats)
                batches, reward, state, metrics = self.method.pretrain_step(self, inner, batches, key_method)
                return (
                    batches,
                    stats,
                    reward,
                    state,
                    {f"{name}/{k}": jnp.asarray(v, jnp.float32) for k, v in metrics.items()},
                )

            def plain(batches, stats, reward, state):
                shapes = jax.eval_shape(hooked, batches, stats, reward, state)[-1]
                return (*stored(batches, stats), reward, state, nan_like(shapes))

            batches, stats, *extra, own = jax.lax.cond(
                pretraining, hooked, plain, batches, ts.entropy_stats, ts.reward, ts.method
            )
        elif self.pretrain_steps:
            batches, stats = jax.lax.cond(pretraining, intrinsic, stored, batches, ts.entropy_stats)
        else:
            batches, stats = stored(batches, ts.entropy_stats)

        def update(state, inputs):
            batch, key = inputs
            return self.agent.update(state, batch, key, agent_step)

        agent, metrics = jax.lax.scan(update, ts.agent, (batches, keys[:, 1]), unroll=self.cfg.train.unroll_updates)
        return (agent, stats, *extra), {**jax.tree.map(jnp.mean, metrics), **own}

    def _env_step(self, env_state: State, action: jax.Array) -> State:
        """Every environment's step; with ``train.overlap`` on a GPU, annotated to run on a second stream, where
        nothing of the step's updates waits for it."""
        if self.cfg.train.overlap and jax.default_backend() == "gpu":
            return on_second_stream(self.envs.step)(env_state, action)
        return self.envs.step(env_state, action)

    def vector_step(self, ts: TrainState, t: jax.Array) -> tuple[TrainState, dict]:
        """One step of every environment, then the agent's updates due at this step.

        Args:
          ts: one seed's state.
          t: the vector-step index in the run, the same for every seed (unbatched).
        """
        key, key_reset, key_act, key_update = jax.random.split(ts.key, 4)
        new_episode = (t % self.episode_length == 0) & (t > 0)
        env_state, eval_policy = jax.lax.cond(
            new_episode,  # Evaluation freezes this episode's policy.
            lambda: (self.envs.reset(key_reset), self.agent.policy(ts.agent)),
            lambda: (ts.env, ts.eval_policy),
        )
        ts = ts.replace(env=env_state, key=key, eval_policy=eval_policy)
        action = self._act(ts, t, key_act)
        nxt = self._env_step(ts.env, action)
        buffer, episodes = self._record(ts, nxt, action, t)
        learning = self.schedule.learning(t, self.num_train, self.cfg.train.seed_steps)
        sampled = ts.buffer if self.cfg.train.overlap else buffer  # train.overlap: the replay one step behind

        def updates():
            return self._updates(ts, sampled, key_update, t, pretraining=t < self.pretrain_steps)

        zeros = {k: jnp.zeros(()) for k in self.agent.metric_names}
        idle = (ts.agent, ts.entropy_stats)
        if self.pretrain_hook:  # the method's metrics NaN where no update runs
            zeros |= nan_like({k: v for k, v in jax.eval_shape(updates)[1].items() if k not in zeros})
            idle = (*idle, ts.reward, ts.method)
        # No updates while seeding; pre-training's reward for the steps before pretrain_steps.
        parts, metrics = jax.lax.cond(learning, updates, lambda: (idle, zeros))
        agent, stats = parts[:2]
        if self.pretrain_hook:
            ts = ts.replace(reward=parts[2], method=parts[3])
        ts = ts.replace(agent=agent, entropy_stats=stats, buffer=buffer, env=nxt, episodes=episodes)
        if self.agent_hook:  # the method's own step after the updates (its metrics NaN where it does nothing)
            ts, own = self.method.agent_step(self, ts, t, jax.random.fold_in(key_update, METHOD_KEY))
            metrics = {**metrics, **{f"{self.method.name}/{k}": jnp.asarray(v, jnp.float32) for k, v in own.items()}}
        if self.trajectory_size:  # The evaluation environments' step: what was acted on, the action.
            first, end = self.num_train, self.num_train + self.trajectory_size[0]
            step = self.feedback.trajectory_step(env_state.obs[first:end], action[first:end])
            ts = ts.replace(eval_trajectory=record_trajectory(ts.eval_trajectory, step, t, self.episode_length))
        return ts, dict(metrics, learning=learning.astype(jnp.float32))

    # -- the feedback session (preference methods; see rebel_jax.preference.feedback) ----------------------
    def sample_segments(self, buffer, key: jax.Array, n: int, length: int):
        """``n`` segments of ``length`` steps from the query pool: ``queries.Segments`` on state tasks, replay
        places (``pixel_reward.SegmentPlaces``) on pixel tasks."""
        return self.feedback.sample_segments(buffer, key, n, length)

    def sample_pairs(self, buffer, key: jax.Array, n: int, recent_episodes: int):
        """``n`` uniform pairs of stored-length segments from the last ``recent_episodes`` complete episodes."""
        return self.feedback.sample_pairs(buffer, key, n, recent_episodes)

    def select_queries(self, ts: TrainState, key: jax.Array, first: bool | jax.Array):
        """The session's query pairs by ``query.sampling`` (uniform at the first feedback session), of the stored
        length: the default of ``Method.query_segments``."""
        return self.feedback.select_queries(ts, key, first)

    def select(self, ts: TrainState, key: jax.Array, first: bool | jax.Array):
        """The session's query pairs: the method's (``Method.query_segments``)."""
        return self.method.query_segments(self, ts, key, first)

    def reward_members(self, params, obs: jax.Array, action: jax.Array) -> jax.Array:
        """Each reward member's reward of (obs, action): (M, ...)."""
        return self.feedback.members(params, obs, action)

    def teach(self, ts: TrainState, key: jax.Array, seg_a, seg_b, index: jax.Array):
        """The scripted teacher's answers, masked to the seed's remaining label budget at session ``index``."""
        return self.feedback.teach(ts, key, seg_a, seg_b, index)

    def learn(self, ts: TrainState, key: jax.Array, seg_a, seg_b, labels, mask, first, *agent_step):
        """Stores the answers, trains the ensemble, relabels the replay; a new critic at the first feedback session."""
        return self.feedback.learn(ts, key, seg_a, seg_b, labels, mask, first, *agent_step)

    def feedback_session(self, ts: TrainState, first, index, agent_step=None) -> tuple[TrainState, dict]:
        """select -> teach -> learn at session ``index`` (``agent_step``: the seed's agent steps so far)."""
        return self.feedback.feedback_session(ts, first, index, agent_step)

    def session_queries(self, ts: TrainState, first: jax.Array):
        """The first half of a host-run session (state tasks): its keys and query pairs."""
        return self.feedback.session_queries(ts, first)

    def session_learn(self, ts: TrainState, asked, labels, mask, first, info) -> tuple[TrainState, dict]:
        """The second half of a host-run session: ``learn`` from the answers and the session's metrics."""
        return self.feedback.session_learn(ts, asked, labels, mask, first, info)

    def session_index(self, round_index: jax.Array) -> jax.Array:
        """The index (0-based) of the session on the schedule at round ``round_index`` (if it has one)."""
        return budget.session_index(self.cfg, round_index)

    def session_due(self, round_index: jax.Array) -> tuple[jax.Array, jax.Array]:
        """Whether round ``round_index`` starts with a feedback session, and whether it is the first."""
        return budget.session_due(self.cfg, round_index)

    # -- the round ------------------------------------------------------------------------
    def round(self, ts: TrainState, round_index: jax.Array) -> tuple[TrainState, dict]:
        """``steps_per_round`` environment steps with their updates, as one ``lax.scan``; on a preference run a
        round on the feedback schedule starts with a session.

        Args:
          ts: one seed's state.
          round_index: the round number, unbatched (the same for every seed).

        Returns:
          The new state and the round's metrics: the agent's metrics averaged over the round's learning steps,
          the last finished training and evaluation returns, ``diverged`` (1.0 if a loss, parameter, observation
          or return is NaN or infinite) and the session's metrics.
        """
        self.trace_count += 1  # Python side effect: counts traces, not calls.
        session = {}
        if self.host_teacher:  # The host ran this round's session, if any, before the round.
            session = summary(self.feedback.session_metrics, ts, {})
        elif self.preference:
            due, first = self.session_due(round_index)
            index, agent_step = self.session_index(round_index), round_index * self.cfg.train.steps_per_round

            traced = {}  # the session's metrics as its trace leaves them, for the branch without one

            def session_fn(ts):
                ts, metrics = self.feedback_session(ts, first, index, agent_step)
                traced.update(jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), metrics))
                return ts, metrics

            def no_session(ts):  # the session's metrics NaN (the method's own too), labels_used as it is
                shapes = traced or jax.eval_shape(session_fn, ts)[1]  # cond traces its true branch first
                return ts, {**nan_like(shapes), **summary(self.feedback.session_metrics, ts, {})}

            # The session is traced once (cond's true branch, traced first) and is the conditional's second branch:
            # with it first (lax.switch) XLA kept a stacked copy of a looped pixel session's columns beside the donated
            # state (tests/test_pixel_preference.py, test_looped_session_writes_the_columns_in_place...).
            ts, session = jax.lax.cond(due, session_fn, no_session, ts)
        before = ts.episodes
        t0 = round_index * self.steps_per_round
        ts, metrics = jax.lax.scan(self.vector_step, ts, t0 + jnp.arange(self.steps_per_round))
        learning = metrics.pop("learning")
        weight = learning / jnp.maximum(learning.sum(), 1.0)
        # The method's own metrics (NAME/KEY) over the steps where they are defined; the agent's over the learning ones.
        out = {k: method_mean(v, learning) if "/" in k else jnp.sum(v * weight) for k, v in metrics.items()}
        out["train_return"] = ts.episodes.train_return
        out["eval_return"] = ts.episodes.eval_return
        if self.reports_success:
            out["train_success"] = ts.episodes.train_success
            out["eval_success"] = ts.episodes.eval_success
        if self.preference:
            out.update(self.feedback.round_metrics(ts.buffer))
        out["diverged"] = self._diverged(ts, out, before)
        return ts, {**out, **session}

    def _diverged(self, ts: TrainState, out: dict, before: EpisodeStats) -> jax.Array:
        """1.0 if the round left a NaN or infinity in the seed's losses, agent, reward model, observations or
        returns, else 0.0. A return may stay NaN (no episode finished yet) but not become NaN."""
        losses = {k: out[k] for k in self.agent.metric_names}
        reward_params = ts.reward.params if ts.reward is not None else ()
        finite = all_finite((losses, ts.agent, reward_params, ts.env.obs, ts.episodes.running))
        return 1.0 - (finite & ts.episodes.returns_ok(before)).astype(jnp.float32)

    # -- frozen-policy evaluation ----------------------------------------------------------
    def evaluate(
        self, policy, key: jax.Array, random_actions: bool | jax.Array = False, success: bool = False
    ) -> jax.Array | tuple[jax.Array, jax.Array]:
        """Mean true return of ``eval_episodes`` episodes of a frozen deterministic policy or of random actions.

        Args:
          policy: the policy's parameters (:meth:`policy_params`; its mean action is taken).
          key: fixes the episodes' initial states, the same for both kinds of actions, and the random actions.
          random_actions: act uniformly at random in [-1, 1] instead (the random-policy baseline). A traced
            value: both kinds share one compiled program.
          success: also the episodes' success rate, on a task that reports success (:attr:`reports_success`).

        Returns:
          The mean return; with ``success``, (mean return, success rate): the fraction of the episodes that
          succeeded, the round's ``eval_success`` rule (:meth:`EpisodeStats.after_step`: an episode succeeds if
          any of its steps does).
        """
        if success and not self.reports_success:
            raise ValueError(f"evaluate(success=True): the task {self.cfg.env.task!r} does not report success")
        key_reset, key_actions = jax.random.split(key)
        state = self.eval_envs.reset(key_reset)

        def body(carry, key):
            state, total, stats = carry
            uniform = jax.random.uniform(key, (state.obs.shape[0], self.env.action_size), minval=-1.0, maxval=1.0)
            action = jnp.where(random_actions, uniform, self.mean_action(policy, state.obs))
            state = self.eval_envs.step(state, action)
            if stats is not None:  # the episodes' success flags, every episode an evaluation one
                stats = stats.after_step(state.reward, state.done, 0, state.info["success"])
            return (state, total + state.reward, stats), None

        keys = jax.random.split(key_actions, self.episode_length)
        stats = EpisodeStats.init(state.reward.shape[0], success=True) if success else None
        (_, total, stats), _ = jax.lax.scan(body, (state, jnp.zeros(state.reward.shape), stats), keys)
        return (total.mean(), stats.eval_success) if success else total.mean()

    # -- columns of a sweep --------------------------------------------------------------------
    def with_knobs(
        self, state: TrainState, lams: Sequence[float] | None = None, teacher_cfgs: Sequence | None = None
    ) -> TrainState:
        """``state`` (columns on its leading axis, from the vmapped :meth:`init`) with each column's method knob
        (REBEL's lambda) and scripted teacher's knobs, e.g. a sweep's grid; None keeps the config's.

        Args:
          lams: one knob value per column.
          teacher_cfgs: one ``teachers.TeacherConfig`` per column.
        """
        if lams is not None and state.lam is not None:
            state = state.replace(lam=jnp.asarray(list(lams), jnp.float32))
        if teacher_cfgs is not None:
            knobs = [teachers.knobs(t) for t in teacher_cfgs]
            state = state.replace(teacher=jax.tree.map(lambda *xs: jnp.stack(xs), *knobs))
        return state
