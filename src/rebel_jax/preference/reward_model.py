"""The reward ensemble learned from preferences with the Bradley-Terry model, on states or on pixels.

The model is an ensemble of M reward networks ``r(s, a)`` whose parameters are stacked on a leading
member axis: on a state task each is :class:`RewardMLP` (PEBBLE / B-Pref's ``gen_net``, configured by
:class:`RewardConfig`), on a pixel task an encoder plus an MLP over frame stacks
(:class:`rebel_jax.preference.pixel_reward.PixelRewardNet`, configured by
:class:`rebel_jax.preference.pixel_reward.PixelRewardConfig`). Everything else is written once here, for both: the
label store (:class:`PairStore`, pairs of segments as copies), the minibatch every loss term sees
(:class:`PrefBatch`), the members' predictions, the Bradley-Terry loss with its optional temporal crops
(:func:`bt_loss`, :func:`crop_masks`) and, in :mod:`rebel_jax.preference.reward_train`, the training loops. The
reward used by the agent is the ensemble mean.

A segment is a pytree with a leading shape and a method ``inputs() -> (obs, action)`` giving the
network's inputs per step: :class:`Steps` on states, :class:`rebel_jax.preference.pixel_reward.SegmentFrames`
(frames stored once, stacks rebuilt) on pixels. A config says which network it builds (``network()``)
and how its members are computed (``member_loop``, ``per_member_adam``).

Label convention (``teachers``): ``label = P(seg_b preferred to seg_a)`` in {0, 0.5, 1}.

The training loss is a sum of *terms*, each a pure ``(params, batch, key) -> (loss, metrics)`` over
the members in ``params`` (leading axis) and a :class:`PrefBatch` of labelled pairs whose per-step
rewards under ``params`` the training step has already computed (``batch.rewards_a``, ``rewards_b``).
:func:`bt_loss` is the Bradley-Terry term; the methods' further terms (SURF's pseudo-labels,
:mod:`rebel_jax.methods.surf`; REBEL's agent preference, :mod:`rebel_jax.methods.rebel`) live in their
methods' files, which import this one (never the other way round).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, Literal

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import optax

from rebel_jax.core.errors import check as _check

LossTerm = Callable[[Any, "PrefBatch", jax.Array], tuple[jax.Array, dict[str, jax.Array]]]


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """The state reward ensemble and its per-session training (B-Pref's walker settings by default)."""

    ensemble_size: int = 3
    """Ensemble members M."""
    hidden: int = 256
    """Width of each hidden layer."""
    depth: int = 3
    """Hidden layers (LeakyReLU) before the squashed output (see ``output``)."""
    lr: float = 3e-4
    """Adam learning rate, one optimiser over all members."""
    batch_size: int = 128
    """Labelled pairs per minibatch and member."""
    max_epochs: int = 50
    """Most epochs over all stored labels per feedback session."""
    stop_accuracy: float = 0.97
    """Stop a session early once the members' mean training accuracy of an epoch exceeds this."""
    label_capacity: int = 1000
    """Stored labelled pairs (>= the total feedback budget; older pairs are overwritten beyond it)."""
    output: Literal["tanh", "sigmoid"] = "tanh"
    """Output squashing: ``tanh`` (B-Pref's, r in (-1, 1)) or ``sigmoid`` (r in (0, 1), the
    non-negative reward that REBEL's bound assumes)."""
    init: Literal["torch", "lecun"] = "torch"
    """Initial weights: ``torch``, PyTorch's ``nn.Linear`` default that B-Pref's ``gen_net`` gets
    (kernel and bias uniform in +-1/sqrt(fan_in)); ``lecun``, flax's default (lecun-normal
    kernels, zero biases; this project's earlier rule, about 9x the initial reward spread)."""

    member_loop: ClassVar[bool] = False
    """The members are computed together (``vmap``); see ``PixelRewardConfig.member_loop``."""
    per_member_adam: ClassVar[bool] = False
    """One Adam step of all members on the sum of their losses; see ``PixelRewardConfig.per_member_adam``."""

    def validate(self) -> None:
        for name in ("ensemble_size", "hidden", "depth", "batch_size", "max_epochs", "label_capacity"):
            _check(getattr(self, name) >= 1, f"reward.{name}", getattr(self, name), ">= 1")
        _check(self.lr > 0, "reward.lr", self.lr, "> 0")
        _check(0 <= self.stop_accuracy <= 1, "reward.stop_accuracy", self.stop_accuracy, "[0, 1]")
        _check(self.output in ("tanh", "sigmoid"), "reward.output", self.output, "tanh, sigmoid")
        _check(self.init in ("torch", "lecun"), "reward.init", self.init, "torch, lecun")

    def network(self) -> RewardMLP:
        """One member's flax module."""
        return RewardMLP(hidden=self.hidden, depth=self.depth, output=self.output, initializer=self.init)


def torch_linear_init(fan_in: int) -> tuple[Callable, Callable]:
    """PyTorch's ``nn.Linear.reset_parameters``: kernel and bias uniform in ``+-1/sqrt(fan_in)``.

    (``kaiming_uniform_(a=sqrt(5))`` gives the kernel bound ``sqrt(6 / ((1 + 5) fan_in))``.)

    Returns:
      ``(kernel_init, bias_init)`` for ``flax.linen.Dense``.
    """
    bound = 1.0 / math.sqrt(fan_in)

    def uniform(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return uniform, uniform


class RewardMLP(nn.Module):
    """One state member: ``squash(MLP(concat(obs, action)))``, a scalar per step (B-Pref's ``gen_net``).

    ``squash`` is ``tanh`` (B-Pref's ``activation='tanh'``) or ``sigmoid`` (its ``'sig'``);
    ``initializer`` is ``RewardConfig.init``.
    """

    hidden: int
    depth: int
    output: str = "tanh"
    initializer: str = "torch"

    def _dense(self, features: int, fan_in: int) -> nn.Dense:
        if self.initializer == "lecun":
            return nn.Dense(features)
        kernel_init, bias_init = torch_linear_init(fan_in)
        return nn.Dense(features, kernel_init=kernel_init, bias_init=bias_init)

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        x = jnp.concatenate([obs, action], axis=-1)
        for _ in range(self.depth):
            x = nn.leaky_relu(self._dense(self.hidden, x.shape[-1])(x))
        squash = jax.nn.sigmoid if self.output == "sigmoid" else jnp.tanh
        return squash(self._dense(1, x.shape[-1])(x))[..., 0]


@flax.struct.dataclass
class Steps:
    """State segments: observations and actions, any leading shape, S steps each."""

    obs: jax.Array
    """(..., S, obs_size)."""
    action: jax.Array
    """(..., S, act_size)."""

    def inputs(self) -> tuple[jax.Array, jax.Array]:
        """The network's inputs per step: ``(obs, action)``."""
        return self.obs, self.action


@flax.struct.dataclass
class PairStore:
    """Fixed-capacity store of pairs of segments (copies); the label store, and SURF's unlabelled pool."""

    a: Any
    """The first segments: :class:`Steps` or ``SegmentFrames``, leading (C,)."""
    b: Any
    """The second segments."""
    labels: jax.Array
    """(C,) ``P(seg_b preferred)`` in {0, 0.5, 1} (unused in a pool)."""
    ptr: jax.Array
    """Next slot to write (wraps at C)."""
    count: jax.Array
    """Filled slots, <= C."""

    @property
    def capacity(self) -> int:
        """C, pairs (static)."""
        return self.labels.shape[0]


@flax.struct.dataclass
class RewardState:
    """The ensemble's parameters (leading member axis), its optimiser state, its labels and (SURF) its pool."""

    params: Any
    opt_state: Any
    data: PairStore
    pool: PairStore | None = None
    """SURF's unlabelled pairs (``labels`` unused), or None."""


@flax.struct.dataclass
class PrefBatch:
    """A minibatch of labelled pairs per member, the input of every loss term."""

    a: Any
    """The first segments, leading (M, B)."""
    b: Any
    """The second segments, leading (M, B)."""
    labels: jax.Array
    """(M, B) soft targets ``P(seg_b preferred)``."""
    weight: jax.Array
    """(M, B) 1 for real pairs, 0 for padding of the last minibatch."""
    members: jax.Array
    """(M,) int32 the ensemble indices of the members in ``params`` (all of them, or one with ``member_loop``):
    a term that draws from its key draws for the whole ensemble and keeps these rows, so that a member's draws
    do not depend on which other members are computed with it."""
    rewards_a: jax.Array | None = None
    """(M, B, S) each member's per-step rewards on its ``a`` segments, computed from ``params`` by the step."""
    rewards_b: jax.Array | None = None
    """(M, B, S) the same on its ``b`` segments."""


def empty_store(segment: Any, capacity: int) -> PairStore:
    """An empty store of ``capacity`` pairs of segments shaped and typed as ``segment`` (one, no leading axis)."""
    zeros = jax.tree.map(lambda x: jnp.zeros((capacity, *x.shape), x.dtype), segment)
    scalar = jnp.zeros((), jnp.int32)
    return PairStore(a=zeros, b=zeros, labels=jnp.zeros(capacity), ptr=scalar, count=scalar)


def init_params(cfg: Any, key: jax.Array, obs: jax.Array, action: jax.Array) -> Any:
    """Fresh parameters of the ``cfg.ensemble_size`` members (one init key each) from example inputs."""
    keys = jax.random.split(key, cfg.ensemble_size)
    return jax.vmap(cfg.network().init, in_axes=(0, None, None))(keys, obs, action)


@flax.struct.dataclass
class MemberAdamState:
    """One torch Adam over the members' parameters (leading member axis), each member its own step count
    (``per_member_adam``; :func:`rebel_jax.preference.reward_train.member_adam_step`)."""

    mu: Any
    nu: Any
    count: jax.Array
    """(M,) int32 steps each member has taken (torch's per-parameter ``state["step"]``)."""
    seen: jax.Array
    """(M,) bool: the member has had a backward, so its gradient is a tensor (zeros after ``zero_grad``), not
    None, and ``step`` moves it (torch's Adam skips parameters whose gradient is None)."""


def member_adam_init(params: Any) -> MemberAdamState:
    members = jax.tree.leaves(params)[0].shape[0]
    zeros = jax.tree.map(jnp.zeros_like, params)
    return MemberAdamState(zeros, zeros, jnp.zeros(members, jnp.int32), jnp.zeros(members, bool))


def new_state(
    cfg: Any, params: Any, data: PairStore, pool: PairStore | None = None, optimizer: Any = None
) -> RewardState:
    """The ensemble with a fresh optimiser state (:class:`MemberAdamState` with ``cfg.per_member_adam``, else
    that of ``optimizer``, an ``optax`` transformation: Adam at ``cfg.lr`` by default)."""
    optimizer = optax.adam(cfg.lr) if optimizer is None else optimizer
    opt_state = member_adam_init(params) if cfg.per_member_adam else optimizer.init(params)
    return RewardState(params=params, opt_state=opt_state, data=data, pool=pool)


def init(
    cfg: RewardConfig, key: jax.Array, obs_size: int, act_size: int, segment_length: int, optimizer: Any = None
) -> RewardState:
    """A fresh state ensemble with an empty label store of ``cfg.label_capacity`` pairs and no pool.

    Args:
      cfg: the reward settings.
      key: PRNG key.
      obs_size: observation size.
      act_size: action size.
      segment_length: steps S of the stored segments.
      optimizer: the members' optimiser (:func:`new_state`).

    Returns:
      The ``RewardState`` (SURF adds its pool with :func:`init_pool`).
    """
    params = init_params(cfg, key, jnp.zeros(obs_size), jnp.zeros(act_size))
    segment = Steps(obs=jnp.zeros((segment_length, obs_size)), action=jnp.zeros((segment_length, act_size)))
    return new_state(cfg, params, empty_store(segment, cfg.label_capacity), optimizer=optimizer)


def over_members(cfg: Any, fn: Callable, params: Any) -> jax.Array:
    """``fn(member_params)`` of every member of ``params`` (leading member axis), stacked: one member at a time
    (``lax.map``) with ``cfg.member_loop``, else all at once (``vmap``)."""
    return jax.lax.map(fn, params) if cfg.member_loop else jax.vmap(fn)(params)


def predict(cfg: Any, params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """Per-member rewards.

    Args:
      cfg: the reward settings (the network).
      params: ensemble parameters with a leading member axis.
      obs: (..., obs_size) states, or (..., H, W, C) uint8 frame stacks.
      action: (..., act_size).

    Returns:
      (M, ...) rewards.
    """
    return over_members(cfg, lambda member: cfg.network().apply(member, obs, action), params)


def mean_reward(cfg: Any, params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """The ensemble-mean reward the agent learns from (used to relabel the buffer): (...) for ``predict``'s inputs."""
    return jnp.mean(predict(cfg, params, obs, action), axis=0)


def step_rewards(cfg: Any, member_params: Any, segments: Any) -> jax.Array:
    """(..., S) one member's per-step rewards ``r(s_h, a_h)`` on segments (``segments.inputs()``)."""
    return cfg.network().apply(member_params, *segments.inputs())


def pair_rewards(cfg: Any, params: Any, seg_a: Any, seg_b: Any) -> tuple[jax.Array, jax.Array]:
    """(M, B, S) each member's per-step rewards on both segments of its own pairs (fields of ``seg_*`` lead (M, B))."""

    def one(member_params, a, b):
        return step_rewards(cfg, member_params, a), step_rewards(cfg, member_params, b)

    return jax.vmap(one)(params, seg_a, seg_b)


def with_rewards(cfg: Any, params: Any, batch: PrefBatch) -> PrefBatch:
    """``batch`` with the per-step rewards of ``params``' members on its pairs (what a training step gives terms)."""
    rewards_a, rewards_b = pair_rewards(cfg, params, batch.a, batch.b)
    return batch.replace(rewards_a=rewards_a, rewards_b=rewards_b)


def pref_probs(cfg: Any, params: Any, seg_a: Any, seg_b: Any) -> jax.Array:
    """Bradley-Terry preference probabilities of each member (``pref_prob_fn`` of queries).

    Args:
      cfg: the reward settings.
      params: ensemble parameters.
      seg_a: state segments with ``obs`` (N, H, obs_size) and ``action`` (N, H, act_size).
      seg_b: the other segment of each pair.

    Returns:
      (M, N) ``P(seg_b preferred) = sigmoid(G(b) - G(a))``, ``G`` the undiscounted segment sum.
    """
    return jax.nn.sigmoid(_pair_logits(cfg, params, seg_a, seg_b))


def _pair_logits(cfg: Any, params: Any, seg_a: Any, seg_b: Any) -> jax.Array:
    """(M, N) every member's logits ``G(b) - G(a)`` on the same pairs of state segments."""
    return_a = jnp.sum(predict(cfg, params, seg_a.obs, seg_a.action), axis=-1)
    return_b = jnp.sum(predict(cfg, params, seg_b.obs, seg_b.action), axis=-1)
    return return_b - return_a


def bt_cross_entropy(logits: jax.Array, labels: jax.Array) -> jax.Array:
    """Bradley-Terry cross-entropy with soft targets, elementwise.

    ``-(y log sigmoid(z) + (1 - y) log sigmoid(-z))`` with ``z = G(b) - G(a)`` and ``y = P(b
    preferred)``: the softmax cross-entropy of B-Pref (and SURF's ``CrossEntropyLoss``) over logits
    ``[G(a), G(b)]``.
    """
    return -(labels * jax.nn.log_sigmoid(logits) + (1.0 - labels) * jax.nn.log_sigmoid(-logits))


def hard_correct(logits: jax.Array, labels: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Correct predictions and counts on hard (0 or 1) labels; 0.5 labels are not counted."""
    hard = jnp.broadcast_to(labels != 0.5, logits.shape).astype(logits.dtype)
    correct = ((logits > 0) == (labels > 0.5)).astype(logits.dtype) * hard
    return correct, hard


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

    References:
      Park et al., SURF, ICLR 2022, section 4.2 (alinlab/SURF@2088ee8).
    """
    length = central_length(stored_length, crop)
    key_length, key_a, key_b = jax.random.split(key, 3)
    lengths = jax.random.randint(key_length, shape, length - crop, length + crop + 1)
    steps = jnp.arange(stored_length)

    def mask(key_start: jax.Array) -> jax.Array:
        starts = jax.random.randint(key_start, shape, 0, stored_length - lengths + 1)
        inside = (steps >= starts[..., None]) & (steps < (starts + lengths)[..., None])
        return inside.astype(jnp.float32)

    return mask(key_a), mask(key_b)


def central_length(stored_length: int, crop: int) -> int:
    """H of segments stored at length ``H + 2 * crop``, checked to leave crops of >= 1 step."""
    length = stored_length - 2 * crop
    _check(crop >= 0 and length - crop >= 1, "surf.crop", crop, f"< stored length {stored_length} / 3")
    return length


def bt_term(logits: jax.Array, labels: jax.Array, weight: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The BT term and its metrics from the members' (M, N) logits on their pairs' ``labels`` and ``weight``.

    Each member's loss is the weighted mean of ``bt_cross_entropy`` over its pairs; the term is the sum over
    members (as B-Pref sums them before one backward pass, and SURF steps them one after another).
    """
    per_pair = bt_cross_entropy(logits, labels) * weight
    per_member = jnp.sum(per_pair, axis=1) / jnp.maximum(jnp.sum(weight, axis=1), 1.0)
    loss = jnp.sum(per_member)
    correct, hard = hard_correct(logits, labels)
    accuracy = jnp.sum(correct * weight) / jnp.maximum(jnp.sum(hard * weight), 1.0)
    return loss, {"bt_loss": loss, "bt_accuracy": accuracy}


def bt_loss(cfg: Any, crop: int = 0, copies: int = 0, crop_accuracy: bool = False) -> LossTerm:
    """The Bradley-Terry loss term (PEBBLE eq. 4, B-Pref's ``train_soft_reward``), optionally on temporal crops.

    The logit of a pair is ``G(b) - G(a)``, ``G`` a member's sum of its per-step rewards
    (``batch.rewards_*``) over the segment's steps. With ``crop`` (SURF's temporal cropping, segments stored
    ``2 crop`` steps longer) or ``copies`` (QPA's ``data_aug_ratio``: that many crops of every pair, the loss
    the mean over them) each member sums over its own fresh random crops (:func:`crop_masks`, drawn from
    the term's key for the whole ensemble, ``batch.members``' rows kept). With neither, the key is unused.

    Args:
      cfg: the reward settings.
      crop: the crop c of :func:`crop_masks` (0 with ``copies`` 0: the whole segments).
      copies: crops per pair (0: one, without a copy axis in the draws).
      crop_accuracy: the training accuracy counts the cropped logits (SURF's pixel code,
        alinlab/SURF@214bc1d:pixel_reward_model.py:909-919; one crop per pair only); off, the whole segments'
        (B-Pref's, SURF's state code).

    Returns:
      ``(params, batch, key) -> (loss, metrics)`` with metrics ``bt_loss`` (the term), ``bt_accuracy``
      (members' mean accuracy on the batch's hard labels, on the logits of the loss) and, with
      ``crop_accuracy``, ``accuracy_logits`` (M, B) (:func:`rebel_jax.preference.reward_train.train_epoch` reads them).

    References:
      Bradley & Terry, Biometrika 1952; Lee, Smith, Abbeel, PEBBLE, ICML 2021, eq. (4).
    """

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        del params  # Unused: the rewards of the batch are the parameters' already.
        rewards_a, rewards_b = batch.rewards_a, batch.rewards_b
        if not (crop or copies):
            logits = jnp.sum(rewards_b, -1) - jnp.sum(rewards_a, -1)
            return bt_term(logits, batch.labels, batch.weight)
        pairs = batch.labels.shape[1]
        shape = (cfg.ensemble_size, copies, pairs) if copies else (cfg.ensemble_size, pairs)
        mask_a, mask_b = crop_masks(key, shape, rewards_a.shape[-1], crop)
        mask_a, mask_b = mask_a[batch.members], mask_b[batch.members]
        if copies:  # (M, R, B, S) masks over (M, 1, B, S) rewards, flattened copy-major as the tiled labels
            rewards_a, rewards_b = rewards_a[:, None], rewards_b[:, None]
        logits = jnp.sum(rewards_b * mask_b, -1) - jnp.sum(rewards_a * mask_a, -1)
        labels, weight = batch.labels, batch.weight
        if copies:
            members = logits.shape[0]
            logits = logits.reshape(members, -1)
            labels, weight = jnp.tile(labels, (1, copies)), jnp.tile(weight, (1, copies))
        loss, metrics = bt_term(logits, labels, weight)
        return loss, dict(metrics, accuracy_logits=logits) if crop_accuracy and not copies else metrics

    return loss_fn


def total_loss(terms: Sequence[LossTerm]) -> LossTerm:
    """The sum of loss terms, term ``i`` called with ``jax.random.split(key, len(terms))[i]``.

    Returns:
      A loss term whose loss is the sum and whose metrics merge the terms' plus ``loss``.
    """

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        keys = jax.random.split(key, len(terms))
        loss, metrics = jnp.zeros(()), {}
        for term, term_key in zip(terms, keys, strict=True):
            term_loss, term_metrics = term(params, batch, term_key)
            loss = loss + term_loss
            metrics.update(term_metrics)
        return loss, dict(metrics, loss=loss)

    return loss_fn


def accuracy(cfg: Any, params: Any, seg_a: Any, seg_b: Any, labels: jax.Array, mask: jax.Array) -> jax.Array:
    """Members' mean accuracy on labelled pairs of state segments (hard labels with mask 1 only).

    Args:
      cfg: the reward settings.
      params: ensemble parameters.
      seg_a: segments with ``obs`` and ``action`` (N, H, ...).
      seg_b: the other segment of each pair.
      labels: (N,) ``P(seg_b preferred)``.
      mask: (N,) 1 for answered pairs.

    Returns:
      Scalar accuracy in [0, 1] (0 if no pair counts).
    """
    correct, hard = hard_correct(_pair_logits(cfg, params, seg_a, seg_b), labels[None])
    return jnp.sum(correct * mask) / jnp.maximum(jnp.sum(hard * mask), 1.0)


def write_pairs(store: PairStore, seg_a: Any, seg_b: Any, labels: jax.Array, mask: jax.Array) -> PairStore:
    """``store`` with the pairs of mask 1 written at ``ptr`` onwards (wrapping), ``count`` updated; pairs of
    mask 0 are dropped (skipped answers, as B-Pref; a pool's pairs of a seed whose session is a no-op).

    Args:
      store: the store.
      seg_a: the first segments, the store's type, leading (N,).
      seg_b: the second segments.
      labels: (N,) ``P(seg_b preferred)``.
      mask: (N,) 1 to keep a pair.
    """
    capacity = store.capacity
    keep = mask > 0
    rank = jnp.cumsum(keep.astype(jnp.int32)) - 1
    slot = jnp.where(keep, (store.ptr + rank) % capacity, capacity)  # Out of range: dropped.
    kept = jnp.sum(keep.astype(jnp.int32))

    def write(old, new):
        return old.at[slot].set(new.astype(old.dtype), mode="drop")

    return store.replace(
        a=jax.tree.map(write, store.a, seg_a),
        b=jax.tree.map(write, store.b, seg_b),
        labels=write(store.labels, labels),
        ptr=(store.ptr + kept) % capacity,
        count=jnp.minimum(store.count + kept, capacity),
    )


def add_labels(state: RewardState, seg_a: Any, seg_b: Any, labels: jax.Array, mask: jax.Array) -> RewardState:
    """Appends the answered pairs (mask 1) of state segments (``obs``, ``action``) to the label store.

    Args:
      state: the reward state.
      seg_a: segments with ``obs`` and ``action`` (N, H, ...).
      seg_b: the other segment of each pair.
      labels: (N,) ``P(seg_b preferred)``.
      mask: (N,) 1 for answered pairs, 0 for skipped ones.
    """
    new_a, new_b = Steps(seg_a.obs, seg_a.action), Steps(seg_b.obs, seg_b.action)
    return state.replace(data=write_pairs(state.data, new_a, new_b, labels, mask))


def init_pool(capacity: int, segment_length: int, obs_size: int, act_size: int) -> PairStore:
    """An empty pool of ``capacity`` unlabelled pairs of state segments of ``segment_length`` (L) steps (a method's
    pool, ``Method.pool_size``: SURF's).

    Returns:
      The :class:`~rebel_jax.preference.reward_model.PairStore` (``labels`` unused), to put in ``RewardState.pool``.
    """
    segment = Steps(obs=jnp.zeros((segment_length, obs_size)), action=jnp.zeros((segment_length, act_size)))
    return empty_store(segment, capacity)
