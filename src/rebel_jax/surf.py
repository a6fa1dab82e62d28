"""SURF's terms: temporal cropping, pseudo-labels on unlabelled pairs, and the pool that holds them.

With SURF, segments are stored at length ``L = H + 2 * crop`` and a crop is a 0/1 step mask
over them, so every shape stays static. The labelled pairs are trained with the Bradley-Terry
term on random crops (``cropped_bt_loss``); the unlabelled pairs of SURF's pool get the
ensemble's own confident labels (``pseudo_label_term``). A session runs a fixed number of
minibatch steps (``surf_iterations``, run by ``reward_model.train_iterations``).

References:
  Park, Seo, Shin, Lee, Abbeel, Lee. SURF: Semi-supervised Reward Learning with Data
  Augmentation for Feedback-efficient Preference-based Reinforcement Learning, ICLR 2022
  (code: alinlab/SURF 2088ee8).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp

from rebel_jax.errors import check as _check
from rebel_jax.reward_model import LossTerm, PrefBatch, RewardConfig, RewardState, bt_cross_entropy, bt_term, network


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


@flax.struct.dataclass
class UnlabelledPool:
    """SURF's growing store of unlabelled pairs (``u_buffer_seg1/2`` of ``reward_model_semi_dataaug.py``)."""

    obs_a: jax.Array
    """(U, L, obs_size) observations of the first segments."""
    act_a: jax.Array
    """(U, L, act_size) their actions."""
    obs_b: jax.Array
    """(U, L, obs_size) observations of the second segments."""
    act_b: jax.Array
    """(U, L, act_size) their actions."""
    ptr: jax.Array
    """Next slot to write (wraps at U)."""
    count: jax.Array
    """Filled slots, <= U."""


def init_pool(capacity: int, segment_length: int, obs_size: int, act_size: int) -> UnlabelledPool:
    """An empty pool of ``capacity`` unlabelled pairs of segments of ``segment_length`` (L) steps.

    Returns:
      The ``UnlabelledPool``, to put in ``RewardState.pool``.
    """
    shape = (capacity, segment_length)
    return UnlabelledPool(
        obs_a=jnp.zeros(shape + (obs_size,)),
        act_a=jnp.zeros(shape + (act_size,)),
        obs_b=jnp.zeros(shape + (obs_size,)),
        act_b=jnp.zeros(shape + (act_size,)),
        ptr=jnp.zeros((), jnp.int32),
        count=jnp.zeros((), jnp.int32),
    )


def add_unlabelled(state: RewardState, seg_a: Any, seg_b: Any, keep: jax.Array | bool = True) -> RewardState:
    """Appends unlabelled pairs to SURF's pool (``put_unlabeled_queries``), all of them or none.

    Args:
      state: the reward state, with a pool.
      seg_a: segments with ``obs`` and ``action`` (N, L, ...).
      seg_b: the other segment of each pair.
      keep: whether to add them (a seed whose session is a no-op adds none).

    Returns:
      The state with the pairs written at ``ptr`` onwards (wrapping), ``count`` updated.
    """
    pool = state.pool
    capacity = pool.obs_a.shape[0]
    num = seg_a.obs.shape[0]
    slot = jnp.where(keep, (pool.ptr + jnp.arange(num)) % capacity, capacity)  # Out of range: dropped.

    def write(store, new):
        return store.at[slot].set(new.astype(store.dtype), mode="drop")

    added = jnp.where(keep, num, 0)
    pool = pool.replace(
        obs_a=write(pool.obs_a, seg_a.obs),
        act_a=write(pool.act_a, seg_a.action),
        obs_b=write(pool.obs_b, seg_b.obs),
        act_b=write(pool.act_b, seg_b.action),
        ptr=(pool.ptr + added) % capacity,
        count=jnp.minimum(pool.count + added, capacity),
    )
    return state.replace(pool=pool)


def surf_iterations(reward_update: int, count: jax.Array, batch_size: int, kept: jax.Array) -> jax.Array:
    """SURF's gradient steps per session: ``ceil(reward_update * labels / batch_size)``, none without new labels.

    ``train_PEBBLE_semi_dataaug.py`` (alinlab/SURF 2088ee8), ``learn_reward``: ``num_iters =
    int(np.ceil(self.cfg.reward_update * self.labeled_feedback / self.reward_model.train_batch_size))``,
    with ``reward_update=1000`` in its walker command and ``train_batch_size = 128``. SURF (as B-Pref)
    holds no session once the budget is spent (``run``: ``if self.total_feedback < self.cfg.max_feedback``);
    here a session whose seed kept no new pair (``kept`` 0) runs no step. The trainer discards such a
    session's training anyway, so this only spares its cost: about 10 s per session on cheetah_run,
    40 of the 50 sessions of a 1M run (RESULTS.md, "Faithful baselines").
    """
    return jnp.where(kept > 0, (reward_update * count + batch_size - 1) // batch_size, 0)


def _central_length(stored_length: int, crop: int) -> int:
    """H of segments stored at length ``H + 2 * crop``, checked to leave crops of >= 1 step."""
    length = stored_length - 2 * crop
    _check(crop >= 0 and length - crop >= 1, "surf.crop", crop, f"< stored length {stored_length} / 3")
    return length


def crop_masks(key: jax.Array, shape: tuple[int, ...], stored_length: int, crop: int) -> tuple[jax.Array, jax.Array]:
    """Random temporal crops of both segments of pairs, as 0/1 step masks (SURF's ``get_cropping_mask``).

    With ``H = stored_length - 2 * crop``, each pair draws one length uniform in
    ``[H - crop, H + crop]``, and each of its two segments its own start uniform in
    ``[0, stored_length - length]``: both crops have the same length (as SURF's code), so the
    logit compares sums over equally many steps.

    Args:
      key: PRNG key.
      shape: leading shape of the pairs, e.g. ``(M, B)``.
      stored_length: L, the stored segment length.
      crop: the crop c.

    Returns:
      ``(mask_a, mask_b)``, each ``shape + (L,)`` float32, ones on the cropped steps.
    """
    length = _central_length(stored_length, crop)
    key_length, key_a, key_b = jax.random.split(key, 3)
    lengths = jax.random.randint(key_length, shape, length - crop, length + crop + 1)
    steps = jnp.arange(stored_length)

    def mask(key_start: jax.Array) -> jax.Array:
        starts = jax.random.randint(key_start, shape, 0, stored_length - lengths + 1)
        inside = (steps >= starts[..., None]) & (steps < (starts + lengths)[..., None])
        return inside.astype(jnp.float32)

    return mask(key_a), mask(key_b)


def _masked_pair_logits(cfg: RewardConfig, member_params: Any, obs_a, act_a, obs_b, act_b, mask_a, mask_b):
    """One member's logits ``G(b) - G(a)`` with G the sum over the masked steps, and its rewards."""
    apply = network(cfg).apply
    reward_a = apply(member_params, obs_a, act_a)
    reward_b = apply(member_params, obs_b, act_b)
    logits = jnp.sum(reward_b * mask_b, axis=-1) - jnp.sum(reward_a * mask_a, axis=-1)
    return logits, reward_a, reward_b


def cropped_bt_loss(cfg: RewardConfig, surf: SURFConfig) -> LossTerm:
    """The Bradley-Terry term on temporally cropped segments (SURF's temporal data augmentation).

    As ``bt_loss`` (same metrics ``bt_loss`` and ``bt_accuracy``), but every member sums its
    rewards over its own fresh crops (``crop_masks``, drawn from the term's key) of the stored
    segments of length ``L = H + 2 * crop``. With ``crop = 0`` it equals ``bt_loss``.

    Args:
      cfg: the reward settings.
      surf: the SURF settings (``crop``).

    Returns:
      ``(params, batch, key) -> (loss, metrics)``.

    References:
      Park et al., SURF, ICLR 2022, section 4.2 (temporal cropping).
    """

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        mask_a, mask_b = crop_masks(key, batch.labels.shape, batch.obs_a.shape[2], surf.crop)

        def one(member_params, obs_a, act_a, obs_b, act_b, member_mask_a, member_mask_b):
            return _masked_pair_logits(cfg, member_params, obs_a, act_a, obs_b, act_b, member_mask_a, member_mask_b)[0]

        logits = jax.vmap(one)(params, batch.obs_a, batch.act_a, batch.obs_b, batch.act_b, mask_a, mask_b)
        return bt_term(logits, batch)

    return loss_fn


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


def pseudo_label_term(
    cfg: RewardConfig,
    surf: SURFConfig,
    pool_obs_a: jax.Array,
    pool_act_a: jax.Array,
    pool_obs_b: jax.Array,
    pool_act_b: jax.Array,
    pool_count: jax.Array | int | None = None,
) -> LossTerm:
    """SURF's semi-supervised term on unlabelled pairs with confident pseudo-labels.

    Each call draws, per member, ``ratio * B`` pairs among the first ``pool_count`` of the pool
    uniformly with replacement (B the labelled minibatch size, read from the batch's shape;
    SURF walks through a shuffled order of its pool instead, which differs only in that a pair
    may repeat within a pass). Each member labels them
    itself from its sums over the central H steps, without gradient (``pseudo_labels``), and
    is trained on fresh crops of them (``crop_masks``):
    ``loss_m = mean over the drawn pairs of CE(cropped logits, label) * confident`` (the mean
    counts the unconfident pairs too, as SURF's ``mean(CE * mask)``); the term is
    ``weight * sum_m loss_m``.

    Args:
      cfg: the reward settings.
      surf: the SURF settings.
      pool_obs_a: (U, L, obs_size) first segments of the unlabelled pairs, stored at
        ``L = H + 2 * crop``, sampled by the caller once per session.
      pool_act_a: (U, L, act_size) their actions.
      pool_obs_b: (U, L, obs_size) second segments.
      pool_act_b: (U, L, act_size) their actions.
      pool_count: filled pairs (may be traced); None: all U.

    Returns:
      ``(params, batch, key) -> (loss, metrics)`` with metrics ``pseudo_loss`` (the term) and
      ``pseudo_fraction`` (the fraction of drawn pairs above the threshold, over members).

    References:
      Park et al., SURF, ICLR 2022, section 4.1 (semi-supervised reward learning).
    """
    pool_obs_a, pool_act_a, pool_obs_b, pool_act_b = map(jnp.asarray, (pool_obs_a, pool_act_a, pool_obs_b, pool_act_b))
    pool_size, stored_length = pool_obs_a.shape[:2]
    length = _central_length(stored_length, surf.crop)
    central = slice(surf.crop, surf.crop + length)

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        members, labelled = batch.labels.shape
        shape = (members, surf.ratio * labelled)
        key_index, key_crop = jax.random.split(key)
        index = jax.random.randint(key_index, shape, 0, pool_size if pool_count is None else jnp.maximum(pool_count, 1))
        mask_a, mask_b = crop_masks(key_crop, shape, stored_length, surf.crop)

        def one(member_params, member_index, member_mask_a, member_mask_b):
            logits, reward_a, reward_b = _masked_pair_logits(
                cfg,
                member_params,
                pool_obs_a[member_index],
                pool_act_a[member_index],
                pool_obs_b[member_index],
                pool_act_b[member_index],
                member_mask_a,
                member_mask_b,
            )
            central_logits = jnp.sum(reward_b[:, central], axis=-1) - jnp.sum(reward_a[:, central], axis=-1)
            return logits, jax.lax.stop_gradient(central_logits)

        logits, central_logits = jax.vmap(one)(params, index, mask_a, mask_b)
        labels, confident = pseudo_labels(central_logits, surf.threshold)
        per_member = jnp.mean(bt_cross_entropy(logits, labels) * confident, axis=1)
        loss = surf.weight * jnp.sum(per_member)
        return loss, {"pseudo_loss": loss, "pseudo_fraction": jnp.mean(confident)}

    return loss_fn
