"""QPA (Hu et al., ICLR 2024): queries, SAC batches and reward learning aligned with the current policy.

QPA (huxiao09/QPA@7e9e49e, built on B-Pref) changes three things of PEBBLE:

- **policy-aligned queries** (:meth:`QPA.query_segments`): every session's pairs
  are uniform (``explore=false``) from the last ``qpa.recent_episodes`` complete episodes, the reward model's FIFO
  of ``max_reward_buffer_size`` episodes (reward_model.py:198-205, ``get_queries`` :365-401, train_QPA.py:124-128);
- **hybrid experience replay** (:meth:`QPA.sample_batch`): while the label budget lasts, ``int(her_ratio
  * batch_size)`` transitions of each agent batch come from the last ``recent_episodes`` episodes' worth of
  transitions, the rest from the whole replay (train_QPA.py:258-262, agent/sac.py:274-285);
- **temporal-crop augmentation** (:meth:`QPA.reward_terms`): every labelled pair is seen in ``data_aug_ratio``
  random crops per reward step (reward_model.py:680-695, :723-744), in sessions of at most ``ceil(reward_update *
  labels / reward.batch_size)`` steps that stop once the running accuracy reaches ``stop_accuracy``
  (train_QPA.py:143-144, reward_model.py:761); on pixels one crop per step.
Its other settings (one reward member, B-Pref's ``asked`` budget) are the ``qpa`` preset's.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Literal

import jax
import jax.numpy as jnp

from rebel_jax.agents import frame_replay, replay
from rebel_jax.core.errors import check
from rebel_jax.methods.base import Method
from rebel_jax.preference import reward_model, reward_train


@dataclasses.dataclass(frozen=True)
class QPAConfig:
    """QPA's settings (its walker_walk and cheetah_run commands, huxiao09/QPA@7e9e49e:run_QPA.sh:3-11)."""

    recent_episodes: int = 10
    """``max_reward_buffer_size``: queries come from the last this-many complete episodes, and the hybrid part of
    a SAC batch from the last this-many episodes' worth of buffer rows."""
    her_ratio: float = 0.5
    """Share of each SAC batch drawn from those recent rows while the label budget lasts (0: uniform batches)."""
    data_aug_ratio: int = 20
    """Random crops of each labelled pair in every reward step (0: the whole segments, once)."""
    crop: int = 5
    """A crop keeps ``H - 3 crop`` to ``H - crop`` consecutive steps of an H-step segment, one length per pair and
    one start per segment (QPA's ``get_cropping_mask``: 35 to 45 of 50 steps)."""
    reward_update: int = 2000
    """A session runs at most ``ceil(reward_update * labels / reward.batch_size)`` reward steps..."""
    stop_accuracy: float = 0.98
    """...and stops once the mean accuracy of its steps so far reaches this (above 1: never early)."""
    reward_session: Literal["steps", "epochs"] = "steps"
    """How a session trains the reward. ``steps``: QPA's on DeepMind Control (its ``train_reward_iter``, the three
    settings above; train_QPA.py:142-145). ``epochs``: QPA's on Meta-World (train_QPA.py:136-141): PEBBLE's session,
    up to ``reward.max_epochs`` epochs over the whole segments (its ``train_reward``, reward_model.py:618, crops none),
    stopped once an epoch's accuracy is above ``reward.stop_accuracy``; ``data_aug_ratio``, ``crop``,
    ``reward_update`` and ``stop_accuracy`` are then unused."""

    def validate(self, segment_length: int) -> None:
        """Checks the ranges; ``segment_length`` is H (``query.segment_length``)."""
        check(self.recent_episodes >= 1, "qpa.recent_episodes", self.recent_episodes, ">= 1")
        check(0 <= self.her_ratio <= 1, "qpa.her_ratio", self.her_ratio, "[0, 1]")
        check(self.data_aug_ratio >= 0, "qpa.data_aug_ratio", self.data_aug_ratio, ">= 0")
        check(0 <= 3 * self.crop < segment_length, "qpa.crop", self.crop, f">= 0, 3 crop < {segment_length} steps")
        check(self.reward_update >= 1, "qpa.reward_update", self.reward_update, ">= 1")
        check(self.stop_accuracy > 0, "qpa.stop_accuracy", self.stop_accuracy, "> 0")
        check(self.reward_session in ("steps", "epochs"), "qpa.reward_session", self.reward_session, "steps, epochs")


class QPA(Method):
    name = "qpa"
    config = QPAConfig

    def validate(self, cfg):
        cfg.qpa.validate(cfg.query.segment_length)

    def query_segments(self, trainer, ts, key, first):
        """Uniform pairs from the last ``qpa.recent_episodes`` complete episodes, every session (on state tasks
        from ``query.pool``)."""
        del first  # Unused: the first feedback session is uniform as the others.
        return trainer.sample_pairs(ts.buffer, key, trainer.cfg.feedback.queries, trainer.cfg.qpa.recent_episodes)

    def sample_batch(self, trainer, ts, buffer, key):
        """Uniform rows, the last ``int(her_ratio * batch_size)`` of them from the last ``recent_episodes``
        episodes' rows while the budget lasts (``0 < labels stored < feedback.labels``); the learned reward. On
        pixel tasks DrQ-v2's n-step batch over the valid rows (episodes in agent steps)."""
        cfg, count = trainer.cfg, ts.reward.data.count
        pixels = isinstance(buffer, frame_replay.FrameBuffer)
        size = cfg.drqv2.batch_size if pixels else cfg.sac.batch_size
        # QPA's recent part: the last int(her_ratio B) positions while 0 < count < labels (train_QPA.py:258-262),
        # from the last recent_episodes x L transitions (replay_buffer.py:107-108), ceil(episodes L / E) rows.
        hybrid = (count > 0) & (count < cfg.feedback.labels)
        recent = hybrid & (jnp.arange(size) >= size - int(cfg.qpa.her_ratio * size))
        rows = min(buffer.rows, math.ceil(cfg.qpa.recent_episodes * trainer.episode_length / buffer.num_envs))
        window = jnp.clip(rows, 1, jnp.maximum(buffer.size, 1)).astype(jnp.int32)
        if pixels:
            return frame_replay.sample_recent(buffer, key, size, cfg.drqv2.nstep, cfg.drqv2.gamma, recent, window)
        return replay.sample_recent(buffer, key, size, recent, window)

    def reward_terms(self, trainer, ts, key, agent_step):
        """The BT loss over ``data_aug_ratio`` random crops of every labelled pair (QPA's ``train_reward_iter``,
        reward_model.py:723-744: its labels repeated that many times), each crop ``H - 3 crop`` to ``H - crop``
        steps of the stored H; the whole segments with ``data_aug_ratio`` 0 or ``reward_session='epochs'``. On
        pixels one crop per pair and step, the accuracy counted on it: the members' convolutions bound the crops and
        steps."""
        del ts, key, agent_step  # Unused.
        rcfg, qpa = trainer.reward_cfg, trainer.cfg.qpa
        if not qpa.data_aug_ratio or qpa.reward_session == "epochs":
            return [reward_model.bt_loss(rcfg)]
        if trainer.cfg.pixels:
            return [reward_model.bt_loss(rcfg, qpa.crop, crop_accuracy=True)]
        return [reward_model.bt_loss(rcfg, qpa.crop, copies=qpa.data_aug_ratio)]

    def train_reward(self, trainer, ts, stored, keys, kept, agent_step, first):
        """One reward step at a time (:func:`reward_train.train_iterations`) while the steps' mean accuracy on
        whole segments (QPA's: on the crops) is below ``stop_accuracy``, at most ``reward_update`` per label. With
        ``reward_session='epochs'``, and on pixels, PEBBLE's session (``max_epochs`` epochs, stopped early)."""
        if trainer.cfg.pixels or trainer.cfg.qpa.reward_session == "epochs":
            return super().train_reward(trainer, ts, stored, keys, kept, agent_step, first)
        rcfg, qpa = trainer.reward_cfg, trainer.cfg.qpa
        terms = self.reward_terms(trainer, ts.replace(reward=stored), keys["terms"], agent_step)
        most = reward_train.steps_per_label(qpa.reward_update, stored.data.count, rcfg.batch_size, kept)

        def running(carry):
            _, step, accuracy, _ = carry
            return (step < most) & ((step == 0) | (accuracy < qpa.stop_accuracy * step))

        def one_step(carry):
            state, step, accuracy, loss = carry
            key = jax.random.fold_in(keys["train"], step)
            one = jnp.ones((), jnp.int32)
            state, metrics = reward_train.train_iterations(rcfg, state, key, terms, one, trainer.reward_optimizer)
            return state, step + 1, accuracy + metrics["train_accuracy"], loss + metrics["loss"]

        start = (stored, jnp.zeros((), jnp.int32), jnp.zeros(()), jnp.zeros(()))
        state, steps, accuracy, loss = jax.lax.while_loop(running, one_step, start)
        ran = jnp.maximum(steps, 1)
        return state, ts.method, {"epochs": steps, "train_accuracy": accuracy / ran, "loss": loss / ran}
