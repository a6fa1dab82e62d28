"""The pixel tasks' part of :class:`rebel_jax.train.Trainer`: DrQ-v2's schedule, the frame replay, and the
feedback session with the reward model of :mod:`rebel_jax.preference.pixel_reward` (SURF's pixel PEBBLE and the methods
built on it).

DrQ-v2's schedule (facebookresearch/drqv2 c0c650b, train.py:124-190; SURF's pixel branch
pixel_train_drqv2.py the same), counted in agent steps per seed (one transition, two frames):

- ``train.seed_steps`` agent steps of uniform random actions and no updates (DrQ-v2: 4,000 seed
  frames = 2,000 agent steps, config.yaml:11 and ``num_expl_steps: 2000``, config.yaml:43; drqv2.py:173-174);
- then one update every ``drqv2.update_every`` agent steps (drqv2.py:233): ``num_envs /
  update_every`` updates per vector step, or one every ``update_every / num_envs`` vector steps;
- the exploration std read at the seed's agent-step count (DrQ-v2's ``global_step``).

Transitions go to :mod:`rebel_jax.agents.frame_replay` (each frame once); updates sample DrQ-v2's n-step
transitions from it.

A preference method on a pixel task follows SURF's ``pixel_train_PEBBLE.py`` (alinlab/SURF 214bc1d,
branch ``pixel``):

- no unsupervised phase (README's ``num_unsup_frames=0``): the first feedback session comes right
  after the seed steps (pixel_train_PEBBLE.py:383), then one every ``feedback.interval`` agent steps
  (SURF's ``num_interact`` frames, :428), as a ``lax.cond`` on the unbatched round index at the start
  of a round;
- each step stores the ensemble mean of the new transition in the buffer's ``learned_reward``
  (pixel_train_PEBBLE.py:493-514), and each session relabels every row (``relabel_with_predictor``,
  :399, :445). The task's reward is kept beside it (``true_reward``, as SURF's episodes keep ``true_reward``,
  :513) for the teacher; DrQ-v2's n-step returns read the learned one. Relabelling once per session,
  not at sampling, fits the frame replay: a sample would otherwise run the 3 encoders on every one of its
  ``batch_size x 2`` stacks at every update;
- at the first feedback session the critic is re-initialised and ``pretrain.reset_updates`` DrQ-v2 updates
  follow (``agent.reset_critic()``, ``update_after_reset(gradient_update=reset_update)``, :413-420);
- the label store keeps copies of its segments (a :class:`rebel_jax.preference.reward_model.PairStore` of frames: the
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

A method changes the session's queries, the agent's batches and their reward through its hooks
(``Method.query_segments``, ``sample_batch``, ``batch_reward``; QPA's and RUNE's), whose defaults are the calls
above.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from rebel_jax.agents import frame_replay
from rebel_jax.core.errors import check
from rebel_jax.envs.pixels import agent_steps
from rebel_jax.preference import pixel_reward, teachers
from rebel_jax.preference.budget import within_budget
from rebel_jax.preference.feedback import (
    COMMON_SESSION_METRICS,
    RewardFeedback,
    method_metrics,
    reward_training_metrics,
    summary,
)
from rebel_jax.preference.queries import Segments

PIXEL_SESSION_METRICS = (*COMMON_SESSION_METRICS, "reward_correlation_replay")
"""Per-round metrics of a pixel feedback session (NaN in rounds without one, except ``labels_used``).
``reward_correlation_replay`` is the Pearson correlation of the relabelled (learned) and the true reward over
every written row of the replay, per step (logs written before it had this name call it ``reward_correlation``;
state tasks' ``reward_correlation`` is over 64 fresh segments). ``session_skipped``, ``session_equal`` and
``session_oracle_agreement`` are the scripted teacher's, as in :data:`rebel_jax.preference.feedback.SESSION_METRICS`."""

DEFAULT_CAPACITY = 100_000
"""Replay transitions per seed when ``train.buffer_capacity`` is 0 (at most ``train.total_steps``), for DrQ-v2
and the preference runs alike: 2.13 GB of 84x84 frames per seed (:mod:`rebel_jax.agents.frame_replay`). DrQ-v2 keeps
1M (config.yaml:18), 21 GB per seed; SURF's pixel PEBBLE the same (config_pebble.yaml:18)."""


def capacity(cfg) -> int:
    """Replay transitions per seed of a pixel run: ``train.buffer_capacity``, or :data:`DEFAULT_CAPACITY` at most
    ``train.total_steps``."""
    return cfg.train.buffer_capacity or min(cfg.train.total_steps, DEFAULT_CAPACITY)


def check_config(cfg) -> None:
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
    rows = capacity(cfg)
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
        rows // envs >= 2 * length - 1,
        "train.buffer_capacity",
        rows,
        f">= num_envs x {2 * length - 1} rows: a complete episode in the replay at any step",
    )


class PixelFeedback(RewardFeedback):
    """The feedback session and the learned reward of a pixel task's :class:`rebel_jax.train.Trainer`.

    Args:
      trainer: the run's trainer, whose config, sizes and agent it reads.
    """

    session_metrics = PIXEL_SESSION_METRICS

    def __init__(self, trainer: Any):
        super().__init__(trainer)
        self._looped_session = loop_in_place(self._feedback_session)

    # -- the reward model -------------------------------------------------------------------
    def init_reward(self, key: jax.Array, obs_shape: tuple[int, ...], action_size: int, pool_capacity: int):
        """The pixel reward ensemble, its label store (copies of the labelled frames) and (SURF) its pool."""
        stored, labels = self.trainer.stored_length, self.cfg.feedback.labels
        optimizer = self.trainer.reward_optimizer
        reward = pixel_reward.init(self.reward_cfg, key, obs_shape, action_size, labels, stored, optimizer)
        if pool_capacity:
            reward = reward.replace(pool=pixel_reward.empty_store(pool_capacity, stored, obs_shape, action_size))
        return reward

    def trajectory_fields(self, obs_shape: tuple[int, ...], action_size: int) -> dict:
        """What REBEL's on-policy store keeps per evaluation step: the newest frame (stacks are rebuilt from the
        frames, :func:`rebel_jax.agents.frame_replay.episode_stacks`) and the action."""
        return {"frame": (obs_shape[:2] + (3,), jnp.uint8), "action": ((action_size,), jnp.float32)}

    def trajectory_step(self, obs: jax.Array, action: jax.Array) -> dict:
        """One step of the on-policy store (:meth:`trajectory_fields`)."""
        return {"frame": obs[..., -3:], "action": action}

    # -- queries ----------------------------------------------------------------------------
    def sample_segments(self, buffer: frame_replay.FrameBuffer, key: jax.Array, n: int, length: int):
        """``n`` segments of ``length`` steps (replay places) from the last ``query.recent_episodes`` complete
        episodes."""
        recent = self.cfg.query.recent_episodes
        return pixel_reward.sample_segments(key, buffer, n, length, self.trainer.episode_length, recent)

    def sample_pairs(self, buffer: frame_replay.FrameBuffer, key: jax.Array, n: int, recent_episodes: int):
        """``n`` uniform pairs of stored-length segments (replay places) from the last ``recent_episodes``
        complete episodes."""
        sizes = (self.trainer.stored_length, self.trainer.episode_length, recent_episodes)
        both = pixel_reward.sample_segments(key, buffer, 2 * n, *sizes)
        return jax.tree.map(lambda x: x[:n], both), jax.tree.map(lambda x: x[n:], both)

    def select_queries(self, ts, key: jax.Array, first: jax.Array):
        """The session's query pairs as segment places, by ``query.sampling`` over the last ``query.recent_episodes``
        complete episodes (uniform at the first feedback session)."""
        cfg = self.cfg
        return pixel_reward.select(
            self.reward_cfg,
            key,
            ts.reward.params,
            ts.buffer,
            cfg.feedback.queries,
            self.trainer.stored_length,
            self.trainer.episode_length,
            cfg.query.recent_episodes,
            cfg.query.sampling,
            cfg.query.candidate_factor,
            first,
        )

    # -- the session --------------------------------------------------------------------------
    def teach(self, ts, key: jax.Array, seg_a, seg_b, index: jax.Array):
        """The scripted teacher on the stored true rewards of the segments, masked to the remaining budget at
        session ``index`` (:func:`rebel_jax.preference.budget.within_budget`).

        The margin (skip / equal thresholds) is ``H x`` the mean true reward of the written rows.

        Returns:
          ``(labels, mask, info)``: :func:`rebel_jax.preference.teachers.label`'s, the mask limited to the budget, and
          ``info`` with the share of the kept answers that are the oracle's (``oracle_agreement``).
        """
        buffer, horizon = ts.buffer, self.trainer.horizon
        written = (jnp.arange(buffer.rows) < buffer.size)[:, None]
        count = jnp.maximum(jnp.sum(written) * buffer.num_envs, 1)
        margin = horizon * jnp.sum(jnp.where(written, buffer.true_reward, 0.0)) / count
        # The central H steps of SURF's H + 2c (get_label, pixel_reward_model.py:578-580).
        seg_a, seg_b = self._central(seg_a), self._central(seg_b)
        true_a = Segments(obs=None, action=None, true_reward=pixel_reward.true_returns(buffer, seg_a, horizon))
        true_b = Segments(obs=None, action=None, true_reward=pixel_reward.true_returns(buffer, seg_b, horizon))
        labels, mask, info = teachers.label(teachers.TeacherConfig(**ts.teacher), key, true_a, true_b, margin)
        mask = within_budget(self.cfg.feedback, mask, ts.reward.data.count, index)
        info = dict(info, oracle_agreement=teachers.oracle_agreement(key, true_a, true_b, labels, mask))
        return labels, mask, info

    def _central(self, seg: pixel_reward.SegmentPlaces) -> pixel_reward.SegmentPlaces:
        return seg.replace(row=seg.row + self.trainer.crop)

    def learn(self, ts, key: jax.Array, seg_a, seg_b, labels, mask, first, agent_step):
        """Stores the answers, trains the ensemble, relabels the replay; new critic at the first feedback session."""
        trainer = self.trainer
        key_train, key_critic, key_value = jax.random.split(key, 3)
        rcfg, h = self.reward_cfg, trainer.horizon
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
        method = trainer.method
        trained, method_state, train_metrics = method.train_reward(trainer, ts, stored, keys, kept, agent_step, first)
        # A session without a kept label trains no epoch (``epochs`` above; SURF and B-Pref hold no session
        # once the budget is spent), so its members and Adam state come back as they were: no select needed.
        reward = trained
        buffer = frame_replay.relabel(
            ts.buffer, lambda obs, action: self.mean_reward(reward.params, obs, action), rcfg.relabel_rows
        )
        new = ts.replace(buffer=buffer, reward=reward, method=method_state)
        agent = jax.lax.cond(first, lambda: self._reset_critic(new, key_critic, agent_step), lambda: ts.agent)
        written = (jnp.arange(buffer.rows) < buffer.size)[:, None] * jnp.ones((1, buffer.num_envs))
        metrics = reward_training_metrics(accuracy_new, train_metrics, kept)
        metrics.update(method_metrics(method.name, train_metrics, kept))
        metrics["reward_correlation_replay"] = weighted_pearson(buffer.learned_reward, buffer.true_reward, written)
        return ts.replace(agent=agent, buffer=buffer, reward=reward, method=method_state), metrics

    def _reset_critic(self, ts, key: jax.Array, agent_step):
        """A fresh critic for ``ts.agent``, then ``pretrain.reset_updates`` DrQ-v2 updates on ``ts.buffer``
        (pixel_train_PEBBLE.py:413-420): uniform batches (QPA's ``update_after_reset`` samples uniformly,
        huxiao09/QPA@7e9e49e:agent/sac.py:334-337) with the method's reward (RUNE's ``update_after_reset`` adds
        its bonus, rll-research/rune@8b3c77a:agent/sac_explore.py:399-411)."""
        trainer, buffer = self.trainer, ts.buffer
        agent = trainer.agent
        key_reset, key_updates = jax.random.split(key)
        agent_state = ts.agent
        if trainer.method.resets_critic(self.cfg):
            agent_state = agent.reset_critic(agent_state, key_reset)

        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            batch = frame_replay.sample(buffer, key_sample, agent.batch_size, True, **agent.sample_args)
            batch = trainer.method.batch_reward(trainer, ts, batch, agent_step)
            return agent.update(state, batch, key_update, agent_step)[0], None

        return jax.lax.scan(one, agent_state, jax.random.split(key_updates, self.cfg.pretrain.reset_updates))[0]

    def feedback_session(self, ts, first: jax.Array, index: jax.Array, agent_step: jax.Array):
        """select -> teach -> learn at session ``index``, with :data:`PIXEL_SESSION_METRICS`.

        With ``pixel_reward.session_loop`` a ``vmap`` of this method runs one column's session at a time
        (:func:`loop_in_place`); called unbatched it is the same session either way."""
        if self.reward_cfg.session_loop:  # Positional arguments: custom_vmap takes no keywords.
            return self._looped_session(ts, first, agent_step, index)
        return self._feedback_session(ts, first, agent_step, index)

    def _feedback_session(self, ts, first: jax.Array, agent_step: jax.Array, index: jax.Array):
        """:meth:`feedback_session` as one batched computation under ``vmap``."""
        key, key_select, key_teach, key_learn = jax.random.split(ts.key, 4)
        ts = ts.replace(key=key)
        seg_a, seg_b = self.trainer.method.query_segments(self.trainer, ts, key_select, first)
        labels, mask, info = self.teach(ts, key_teach, seg_a, seg_b, index)
        ts, metrics = self.learn(ts, key_learn, seg_a, seg_b, labels, mask, first, agent_step)
        return ts, summary(PIXEL_SESSION_METRICS, ts, dict(metrics, session=1.0, **teachers.session_metrics(info)))

    def round_metrics(self, buffer: frame_replay.FrameBuffer) -> dict[str, jax.Array]:
        """None on pixel tasks (their session metrics cover the whole replay)."""
        del buffer  # Unused.
        return {}


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
