"""QPA (Hu et al., ICLR 2024): queries, SAC batches and reward learning aligned with the current policy.

QPA (huxiao09/QPA@7e9e49e, built on B-Pref) changes three things of PEBBLE:

- **policy-aligned queries** (:meth:`QPA.query_segments`): every session's pairs
  are uniform (``explore=false``) from the last ``qpa.recent_episodes`` complete episodes, the reward model's FIFO
  of ``max_reward_buffer_size`` episodes (reward_model.py:198-205, ``get_queries`` :365-401, train_QPA.py:124-128);
- **hybrid experience replay** (:mod:`rebel_jax.methods.qpa_replay`): while the label budget lasts, ``int(her_ratio
  * batch_size)`` transitions of each agent batch come from the last ``recent_episodes`` episodes' worth of
  transitions, the rest from the whole replay (train_QPA.py:258-262, agent/sac.py:274-285);
- **temporal-crop augmentation** (:func:`augmented_bt_loss`): every labelled pair is seen in ``data_aug_ratio``
  random crops per reward step (reward_model.py:680-695, :723-744), in sessions of at most ``ceil(reward_update *
  labels / reward.batch_size)`` steps that stop once the running accuracy reaches ``stop_accuracy``
  (train_QPA.py:143-144, reward_model.py:761); on pixels one crop per step (:meth:`QPA.train_pixel_reward`).
Its other settings (one reward member, B-Pref's ``asked`` budget) are the ``qpa`` preset's.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from rebel_jax import pixel_reward, reward_model, surf
from rebel_jax.errors import check
from rebel_jax.methods import qpa_replay
from rebel_jax.methods.base import Method


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

    def validate(self, segment_length: int) -> None:
        """Checks the ranges; ``segment_length`` is H (``query.segment_length``)."""
        check(self.recent_episodes >= 1, "qpa.recent_episodes", self.recent_episodes, ">= 1")
        check(0 <= self.her_ratio <= 1, "qpa.her_ratio", self.her_ratio, "[0, 1]")
        check(self.data_aug_ratio >= 0, "qpa.data_aug_ratio", self.data_aug_ratio, ">= 0")
        check(0 <= 3 * self.crop < segment_length, "qpa.crop", self.crop, f">= 0, 3 crop < {segment_length} steps")
        check(self.reward_update >= 1, "qpa.reward_update", self.reward_update, ">= 1")
        check(self.stop_accuracy > 0, "qpa.stop_accuracy", self.stop_accuracy, "> 0")


def augmented_bt_loss(cfg: reward_model.RewardConfig, qpa: QPAConfig) -> reward_model.LossTerm:
    """The Bradley-Terry term over ``data_aug_ratio`` random crops of every pair (QPA's ``train_reward_iter``).

    Each member sums its rewards over its own crops (:func:`rebel_jax.surf.crop_masks` with ``qpa.crop`` on the
    stored H steps), and its loss is the mean cross-entropy over the ``data_aug_ratio x B`` cropped pairs, as QPA's
    over its labels repeated ``data_aug_ratio`` times (reward_model.py:723-744). With ``data_aug_ratio`` 0 it is
    ``bt_loss``. Metrics: ``bt_loss`` and ``bt_accuracy`` (on the crops).
    """
    if qpa.data_aug_ratio == 0:
        return reward_model.bt_loss(cfg)
    apply, copies = reward_model.network(cfg).apply, qpa.data_aug_ratio

    def loss_fn(params, batch: reward_model.PrefBatch, key: jax.Array):
        members, pairs = batch.labels.shape
        mask_a, mask_b = surf.crop_masks(key, (members, copies, pairs), batch.obs_a.shape[2], qpa.crop)

        def one(member, obs_a, act_a, obs_b, act_b, member_mask_a, member_mask_b):  # (B, H) rewards, (R, B) logits
            reward_a, reward_b = apply(member, obs_a, act_a), apply(member, obs_b, act_b)
            return jnp.sum(reward_b * member_mask_b, -1) - jnp.sum(reward_a * member_mask_a, -1)

        logits = jax.vmap(one)(params, batch.obs_a, batch.act_a, batch.obs_b, batch.act_b, mask_a, mask_b)
        repeated = batch.replace(labels=jnp.tile(batch.labels, (1, copies)), weight=jnp.tile(batch.weight, (1, copies)))
        return reward_model.bt_term(logits.reshape(members, -1), repeated)  # copy-major, as the tiled labels

    return loss_fn


class QPA(Method):
    name = "qpa"
    config_field = "qpa"

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
        return qpa_replay.hybrid_batch(trainer.cfg, ts.reward.data.count, buffer, key, trainer.episode_length)

    def state_terms(self, trainer, ts, key):
        del ts, key  # Unused.
        return [augmented_bt_loss(trainer.reward_cfg, trainer.cfg.qpa)]

    def train_state_reward(self, trainer, ts, stored, keys, kept):
        """One reward step at a time (:func:`reward_model.train_iterations`) while the steps' mean accuracy on
        whole segments (QPA's: on the crops) is below ``stop_accuracy``, at most ``reward_update`` per label."""
        rcfg, qpa = trainer.reward_cfg, trainer.cfg.qpa
        terms = self.state_terms(trainer, ts.replace(reward=stored), keys["terms"])
        most = surf.surf_iterations(qpa.reward_update, stored.data.count, rcfg.batch_size, kept)

        def running(carry):
            _, step, accuracy, _ = carry
            return (step < most) & ((step == 0) | (accuracy < qpa.stop_accuracy * step))

        def one_step(carry):
            state, step, accuracy, loss = carry
            key = jax.random.fold_in(keys["train"], step)
            state, metrics = reward_model.train_iterations(rcfg, state, key, terms, jnp.ones((), jnp.int32))
            return state, step + 1, accuracy + metrics["train_accuracy"], loss + metrics["loss"]

        start = (stored, jnp.zeros((), jnp.int32), jnp.zeros(()), jnp.zeros(()))
        state, steps, accuracy, loss = jax.lax.while_loop(running, one_step, start)
        ran = jnp.maximum(steps, 1)
        return state, {"epochs": steps, "train_accuracy": accuracy / ran, "loss": loss / ran}

    def train_pixel_reward(self, trainer, ts, stored, keys, kept, agent_step):
        """PEBBLE's pixel session (``pixel_reward.max_epochs``, stopped early), each labelled pair seen through one
        QPA crop per step (none with ``data_aug_ratio`` 0): the members' convolutions bound the crops and steps."""
        del agent_step  # Unused.
        rcfg, qpa = trainer.cfg.pixel_reward, trainer.cfg.qpa
        crop = qpa.crop if qpa.data_aug_ratio else 0
        return pixel_reward.train(rcfg, stored, keys["train"], (), crop, jnp.where(kept > 0, rcfg.max_epochs, 0))
