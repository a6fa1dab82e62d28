"""SURF (Park et al., ICLR 2022): pseudo-labels on an unlabelled pool and temporal cropping, on states and pixels.

Segments are stored at length ``L = H + 2 * surf.crop`` and a crop is a 0/1 step mask over them
(:func:`rebel_jax.preference.reward_model.crop_masks`), so every shape stays static. The labelled pairs train with the
Bradley-Terry term on random crops (``reward_model.bt_loss(cfg, crop)``); the unlabelled pairs of SURF's pool get
the ensemble's own confident labels (:func:`pseudo_label_term`). A session grows the pool by ``surf.pool_size``
pairs, then runs a fixed number of steps with no early stop: on states ``ceil(reward_update * labels / batch)``
minibatch steps (:func:`rebel_jax.preference.reward_train.steps_per_label`,
alinlab/SURF@2088ee8:train_PEBBLE_semi_dataaug.py:162),
on pixels ``surf.reward_update`` passes (alinlab/SURF@214bc1d:pixel_train_PEBBLE_semi.py:275-281).

References:
  Park, Seo, Shin, Lee, Abbeel, Lee. SURF: Semi-supervised Reward Learning with Data
  Augmentation for Feedback-efficient Preference-based Reinforcement Learning, ICLR 2022
  (code: alinlab/SURF 2088ee8).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp

from rebel_jax.core.errors import check as _check
from rebel_jax.methods.base import Method
from rebel_jax.preference import pixel_reward, reward_model, reward_train
from rebel_jax.preference.reward_model import (
    LossTerm,
    PairStore,
    PrefBatch,
    RewardState,
    Steps,
    bt_cross_entropy,
    central_length,
    crop_masks,
    step_rewards,
    write_pairs,
)


@dataclasses.dataclass(frozen=True)
class SURFConfig:
    """SURF's semi-supervised reward learning with temporal cropping (walker_walk settings)."""

    threshold: float = 0.99
    """Pseudo-label confidence tau: an unlabelled pair counts when ``max(P, 1 - P) >= tau``."""
    weight: float = 1.0
    """Weight of the unlabelled (pseudo-label) loss."""
    ratio: int = 4
    """Unlabelled pairs per labelled pair in each minibatch (mu)."""
    pool_size: int = 1000
    """Unlabelled pairs added to the pool at each feedback session (SURF's ``inv_label_ratio``
    times the queries per session; walker: 100 x 10 = 1000). The pool keeps every session's
    pairs, as SURF's ``u_buffer``."""
    reward_update: int = 1000
    """SURF's ``reward_update``: a session runs ``ceil(reward_update * labels / reward.batch_size)``
    gradient steps with no early stop (its walker command: 1000)."""
    crop: int = 5
    """Temporal crop c: segments are stored at length ``H + 2c``; each segment of a pair is
    cropped to a length uniform in ``[H - c, H + c]`` (shared by the pair) with its own uniform
    start; pseudo-labels come from the central H steps. 0 turns cropping off."""

    def validate(self, segment_length: int | None = None) -> None:
        """Checks the ranges; with ``segment_length`` (H) also that ``crop < H``."""
        _check(0 <= self.threshold <= 1, "surf.threshold", self.threshold, "[0, 1]")
        _check(self.weight >= 0, "surf.weight", self.weight, ">= 0")
        for name in ("ratio", "pool_size", "reward_update"):
            _check(getattr(self, name) >= 1, f"surf.{name}", getattr(self, name), ">= 1")
        _check(self.crop >= 0, "surf.crop", self.crop, ">= 0")
        if segment_length is not None:
            _check(self.crop < segment_length, "surf.crop", self.crop, f"< segment_length {segment_length}")


def add_unlabelled(state: RewardState, seg_a: Any, seg_b: Any, keep: jax.Array | bool = True) -> RewardState:
    """Appends unlabelled pairs of state segments to SURF's pool (``put_unlabeled_queries``), all of them or none.

    Args:
      state: the reward state, with a pool.
      seg_a: segments with ``obs`` and ``action`` (N, L, ...).
      seg_b: the other segment of each pair.
      keep: whether to add them (a seed whose session is a no-op adds none).

    Returns:
      The state with the pairs written at ``ptr`` onwards (wrapping), ``count`` updated.
    """
    num = seg_a.obs.shape[0]
    mask = jnp.full((num,), jnp.asarray(keep, jnp.float32))
    new_a, new_b = Steps(seg_a.obs, seg_a.action), Steps(seg_b.obs, seg_b.action)
    return state.replace(pool=write_pairs(state.pool, new_a, new_b, jnp.zeros(num), mask))


def pseudo_labels(logits: jax.Array, threshold: float | jax.Array) -> tuple[jax.Array, jax.Array]:
    """SURF's pseudo-labels and confidence mask from BT logits ``G(b) - G(a)``.

    Args:
      logits: BT logits of unlabelled pairs, any shape.
      threshold: confidence tau.

    Returns:
      ``(labels, confident)`` float: ``labels = 1[P > 0.5]`` with ``P = sigmoid(logits)`` the
      probability that b is preferred (ties go to a, as SURF's argmax), ``confident =
      1[max(P, 1 - P) >= threshold]``.
    """
    prob = jax.nn.sigmoid(logits)
    labels = (prob > 0.5).astype(logits.dtype)
    confident = (jnp.maximum(prob, 1.0 - prob) >= threshold).astype(logits.dtype)
    return labels, confident


def pseudo_label_term(cfg: Any, surf: SURFConfig, pool: PairStore) -> LossTerm:
    """SURF's semi-supervised term on unlabelled pairs with confident pseudo-labels, on states or pixels.

    Each call draws, per member, ``ratio * B`` pairs (B the batch's labelled pairs per member) among the first
    ``pool.count`` of the pool uniformly with replacement (SURF walks through a shuffled order of its pool
    instead, which differs only in that a pair may repeat within a pass), for the whole ensemble, keeping
    ``batch.members``' rows. Each member labels them itself from its sums over the central H steps, without
    gradient (``pseudo_labels``), and is trained on fresh crops of them
    (:func:`rebel_jax.preference.reward_model.crop_masks`):
    ``loss_m = mean over the drawn pairs of CE(cropped logits, label) * confident`` (the mean
    counts the unconfident pairs too, as SURF's ``mean(CE * mask)``); the term is
    ``weight * sum_m loss_m`` (alinlab/SURF@214bc1d:pixel_reward_model_semi.py:291-301 on pixels).

    Args:
      cfg: the reward settings.
      surf: the SURF settings.
      pool: the unlabelled pairs, stored at ``L = H + 2 * crop`` steps, filled by the caller before the session.

    Returns:
      ``(params, batch, key) -> (loss, metrics)`` with metrics ``pseudo_loss`` (the term) and
      ``pseudo_fraction`` (the fraction of drawn pairs above the threshold, over members).

    References:
      Park et al., SURF, ICLR 2022, section 4.1 (semi-supervised reward learning).
    """
    stored_length = pool.a.action.shape[1]
    length = central_length(stored_length, surf.crop)
    central = slice(surf.crop, surf.crop + length)

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        shape = (cfg.ensemble_size, surf.ratio * batch.labels.shape[1])
        key_index, key_crop = jax.random.split(key)
        index = jax.random.randint(key_index, shape, 0, jnp.maximum(pool.count, 1))
        mask_a, mask_b = crop_masks(key_crop, shape, stored_length, surf.crop)
        index, mask_a, mask_b = index[batch.members], mask_a[batch.members], mask_b[batch.members]

        def one(member_params, member_index, member_mask_a, member_mask_b):
            def take(x):
                return x[member_index]

            reward_a = step_rewards(cfg, member_params, jax.tree.map(take, pool.a))
            reward_b = step_rewards(cfg, member_params, jax.tree.map(take, pool.b))
            logits = jnp.sum(reward_b * member_mask_b, axis=-1) - jnp.sum(reward_a * member_mask_a, axis=-1)
            central_logits = jnp.sum(reward_b[:, central], axis=-1) - jnp.sum(reward_a[:, central], axis=-1)
            return logits, jax.lax.stop_gradient(central_logits)

        logits, central_logits = jax.vmap(one)(params, index, mask_a, mask_b)
        labels, confident = pseudo_labels(central_logits, surf.threshold)
        per_member = jnp.mean(bt_cross_entropy(logits, labels) * confident, axis=1)
        loss = surf.weight * jnp.sum(per_member)
        return loss, {"pseudo_loss": loss, "pseudo_fraction": jnp.mean(confident)}

    return loss_fn


class SURF(Method):
    name = "surf"
    config = SURFConfig

    def validate(self, cfg):
        cfg.surf.validate(cfg.query.segment_length)

    def crop(self, cfg) -> int:
        return cfg.surf.crop

    def pool_size(self, cfg) -> int:
        return cfg.surf.pool_size

    def reward_terms(self, trainer, ts, key, agent_step):
        """The BT loss on random crops of the labelled pairs and the pseudo-label term on the pool."""
        del key, agent_step  # Unused.
        rcfg, scfg = trainer.reward_cfg, trainer.cfg.surf
        pseudo = pseudo_label_term(rcfg, scfg, ts.reward.pool)
        if not trainer.cfg.pixels:
            return [reward_model.bt_loss(rcfg, scfg.crop), pseudo]

        def pixel_pseudo(params, batch, key):  # the pool's draws from fold_in(key, 0), as pixel runs always drew them
            return pseudo(params, batch, jax.random.fold_in(key, 0))

        # SURF's pixel code counts the training accuracy on the crops (pixel_reward_model.py:909-919).
        return [reward_model.bt_loss(rcfg, scfg.crop, crop_accuracy=True), pixel_pseudo]

    def grow_pool(self, trainer, ts, stored, key, kept):
        """``stored`` with ``surf.pool_size`` unlabelled pairs of recent episodes added to its pool (none if no
        answer was kept)."""
        size = trainer.cfg.surf.pool_size
        pool_a, pool_b = trainer.sample_pairs(ts.buffer, key, size, trainer.cfg.query.recent_episodes)
        if not trainer.cfg.pixels:
            return add_unlabelled(stored, pool_a, pool_b, kept > 0)
        ones = jnp.full((size,), (kept > 0).astype(jnp.float32))
        return stored.replace(pool=pixel_reward.append_segments(stored.pool, ts.buffer, pool_a, pool_b, ones * 0, ones))

    def train_reward(self, trainer, ts, stored, keys, kept, agent_step, first):
        """A fixed number of steps, none without new labels: ``ceil(surf.reward_update * labels /
        reward.batch_size)`` minibatch steps on a state task, ``surf.reward_update`` epochs on a pixel task."""
        rcfg, scfg = trainer.reward_cfg, trainer.cfg.surf
        stored = self.grow_pool(trainer, ts, stored, keys["pool"], kept)
        terms = self.reward_terms(trainer, ts.replace(reward=stored), keys["terms"], agent_step)
        optimizer = trainer.reward_optimizer
        if trainer.cfg.pixels:
            epochs = jnp.where(kept > 0, scfg.reward_update, 0)
            reward, metrics = reward_train.train(rcfg, stored, keys["train"], terms, epochs, float("inf"), optimizer)
        else:
            steps = reward_train.steps_per_label(scfg.reward_update, stored.data.count, rcfg.batch_size, kept)
            reward, metrics = reward_train.train_iterations(rcfg, stored, keys["train"], terms, steps, optimizer)
        return reward, ts.method, metrics
