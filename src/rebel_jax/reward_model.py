"""Reward ensemble learned from preferences with the Bradley-Terry model (PEBBLE / B-Pref).

The model is an ensemble of M MLPs ``r(s, a)`` over ``concat(s, a)`` (LeakyReLU hidden layers,
tanh output, or sigmoid for a non-negative reward) whose parameters are stacked on a leading
member axis and trained by ONE Adam (B-Pref sums the members' losses into one backward pass;
Adam being per-coordinate, this equals M separate optimisers). The reward used by the agent is
the ensemble mean.

Label convention (``teachers``): ``label = P(seg_b preferred to seg_a)`` in {0, 0.5, 1}.

The training loss is a sum of *terms*, each a pure ``(params, batch, key) -> (loss, metrics)``
over the whole ensemble's ``params`` and a ``PrefBatch`` of labelled pairs (with a leading
member axis: every member sees its own shuffle, as in B-Pref). ``bt_loss`` is the
Bradley-Terry term. The methods' further terms live in their own modules, which import this
one (never the other way round), close over their own data and are passed to ``train``:

- :mod:`rebel_jax.agent_preference`: REBEL's agent preference ``lambda * V``, the learned
  reward's value on trajectories of the current policy;
- :mod:`rebel_jax.surf`: SURF's temporal cropping of the labelled pairs, its
  confidence-thresholded pseudo-labels on unlabelled pairs and the pool that holds them.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from typing import Any, Literal

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import optax

from rebel_jax.errors import check as _check

LossTerm = Callable[[Any, "PrefBatch", jax.Array], tuple[jax.Array, dict[str, jax.Array]]]


@dataclasses.dataclass(frozen=True)
class RewardConfig:
    """The reward ensemble and its per-session training (B-Pref's walker settings by default)."""

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

    def validate(self) -> None:
        for name in ("ensemble_size", "hidden", "depth", "batch_size", "max_epochs", "label_capacity"):
            _check(getattr(self, name) >= 1, f"reward.{name}", getattr(self, name), ">= 1")
        _check(self.lr > 0, "reward.lr", self.lr, "> 0")
        _check(0 <= self.stop_accuracy <= 1, "reward.stop_accuracy", self.stop_accuracy, "[0, 1]")
        _check(self.output in ("tanh", "sigmoid"), "reward.output", self.output, "tanh, sigmoid")
        _check(self.init in ("torch", "lecun"), "reward.init", self.init, "torch, lecun")


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
    """One member: ``squash(MLP(concat(obs, action)))``, a scalar per step (B-Pref's ``gen_net``).

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
class LabelData:
    """Fixed-capacity store of labelled pairs; only kept (unskipped) pairs are stored."""

    obs_a: jax.Array
    """(C, H, obs_size) observations of the first segments."""
    act_a: jax.Array
    """(C, H, act_size) actions of the first segments."""
    obs_b: jax.Array
    """(C, H, obs_size) observations of the second segments."""
    act_b: jax.Array
    """(C, H, act_size) actions of the second segments."""
    labels: jax.Array
    """(C,) ``P(seg_b preferred)`` in {0, 0.5, 1}."""
    ptr: jax.Array
    """Next slot to write (wraps at C)."""
    count: jax.Array
    """Filled slots, <= C."""


@flax.struct.dataclass
class RewardState:
    """The ensemble's parameters (leading member axis), its Adam state, its labels and (SURF) its pool."""

    params: Any
    opt_state: Any
    data: LabelData
    pool: Any = None
    """SURF's unlabelled pairs (:class:`rebel_jax.surf.UnlabelledPool`, ``surf.init_pool``), or None."""


@flax.struct.dataclass
class PrefBatch:
    """A minibatch of labelled pairs per member: every field has leading axes (M, B)."""

    obs_a: jax.Array
    act_a: jax.Array
    obs_b: jax.Array
    act_b: jax.Array
    labels: jax.Array
    """(M, B) soft targets ``P(seg_b preferred)``."""
    weight: jax.Array
    """(M, B) 1 for real pairs, 0 for padding of the last minibatch."""


def network(cfg: RewardConfig) -> RewardMLP:
    """One member's flax module (apply it per member, or ``vmap`` it over the member axis)."""
    return RewardMLP(hidden=cfg.hidden, depth=cfg.depth, output=cfg.output, initializer=cfg.init)


def _optimizer(cfg: RewardConfig) -> optax.GradientTransformation:
    return optax.adam(cfg.lr)


def init(cfg: RewardConfig, key: jax.Array, obs_size: int, act_size: int, segment_length: int) -> RewardState:
    """A fresh ensemble (one init key per member) with an empty label store and no pool.

    Args:
      cfg: the reward settings.
      key: PRNG key.
      obs_size: observation size.
      act_size: action size.
      segment_length: H of the stored segments.

    Returns:
      The ``RewardState`` (SURF adds its pool with ``surf.init_pool``).
    """
    keys = jax.random.split(key, cfg.ensemble_size)
    params = jax.vmap(network(cfg).init, in_axes=(0, None, None))(keys, jnp.zeros(obs_size), jnp.zeros(act_size))
    shape = (cfg.label_capacity, segment_length)
    data = LabelData(
        obs_a=jnp.zeros(shape + (obs_size,)),
        act_a=jnp.zeros(shape + (act_size,)),
        obs_b=jnp.zeros(shape + (obs_size,)),
        act_b=jnp.zeros(shape + (act_size,)),
        labels=jnp.zeros(cfg.label_capacity),
        ptr=jnp.zeros((), jnp.int32),
        count=jnp.zeros((), jnp.int32),
    )
    return RewardState(params=params, opt_state=_optimizer(cfg).init(params), data=data)


def predict(cfg: RewardConfig, params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """Per-member rewards.

    Args:
      cfg: the reward settings (architecture).
      params: ensemble parameters with a leading member axis.
      obs: (..., obs_size).
      action: (..., act_size).

    Returns:
      (M, ...) rewards in (-1, 1) (``tanh`` output) or (0, 1) (``sigmoid``).
    """
    return jax.vmap(network(cfg).apply, in_axes=(0, None, None))(params, obs, action)


def mean_reward(cfg: RewardConfig, params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """The ensemble-mean reward the agent learns from (used to relabel the buffer).

    Args: as ``predict``.

    Returns:
      (...) mean over members.
    """
    return jnp.mean(predict(cfg, params, obs, action), axis=0)


def _pair_logits(cfg: RewardConfig, params: Any, obs_a, act_a, obs_b, act_b) -> jax.Array:
    """Per-member BT logits ``G(b) - G(a)`` with ``G`` the undiscounted segment sum: (M, N)."""
    return_a = jnp.sum(predict(cfg, params, obs_a, act_a), axis=-1)
    return_b = jnp.sum(predict(cfg, params, obs_b, act_b), axis=-1)
    return return_b - return_a


def _member_logits(cfg: RewardConfig, params: Any, batch: PrefBatch) -> jax.Array:
    """Logits of member m on member m's own minibatch: (M, B)."""

    def one(member_params, obs_a, act_a, obs_b, act_b):
        apply = network(cfg).apply
        return jnp.sum(apply(member_params, obs_b, act_b), -1) - jnp.sum(apply(member_params, obs_a, act_a), -1)

    return jax.vmap(one)(params, batch.obs_a, batch.act_a, batch.obs_b, batch.act_b)


def pref_probs(cfg: RewardConfig, params: Any, seg_a: Any, seg_b: Any) -> jax.Array:
    """Bradley-Terry preference probabilities of each member (``pref_prob_fn`` of queries).

    Args:
      cfg: the reward settings.
      params: ensemble parameters.
      seg_a: segments with ``obs`` (N, H, obs_size) and ``action`` (N, H, act_size).
      seg_b: the other segment of each pair.

    Returns:
      (M, N) ``P(seg_b preferred) = sigmoid(G(b) - G(a))``.
    """
    return jax.nn.sigmoid(_pair_logits(cfg, params, seg_a.obs, seg_a.action, seg_b.obs, seg_b.action))


def bt_cross_entropy(logits: jax.Array, labels: jax.Array) -> jax.Array:
    """Bradley-Terry cross-entropy with soft targets, elementwise.

    ``-(y log sigmoid(z) + (1 - y) log sigmoid(-z))`` with ``z = G(b) - G(a)`` and ``y = P(b
    preferred)``: the softmax cross-entropy of B-Pref over logits ``[G(a), G(b)]``.
    """
    return -(labels * jax.nn.log_sigmoid(logits) + (1.0 - labels) * jax.nn.log_sigmoid(-logits))


def _hard_correct(logits: jax.Array, labels: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Correct predictions and counts on hard (0 or 1) labels; 0.5 labels are not counted."""
    hard = jnp.broadcast_to(labels != 0.5, logits.shape).astype(logits.dtype)
    correct = ((logits > 0) == (labels > 0.5)).astype(logits.dtype) * hard
    return correct, hard


def bt_loss(cfg: RewardConfig) -> LossTerm:
    """The Bradley-Terry loss term (PEBBLE eq. 4, B-Pref's ``train_soft_reward``).

    Each member's loss is the weighted mean over its minibatch of ``bt_cross_entropy``; the
    term is the sum over members (as B-Pref sums them before one backward pass).

    Args:
      cfg: the reward settings.

    Returns:
      ``(params, batch, key) -> (loss, metrics)`` with metrics ``bt_loss`` (the term) and
      ``bt_accuracy`` (members' mean accuracy on the batch's hard labels).

    References:
      Bradley & Terry, Biometrika 1952; Lee, Smith, Abbeel, PEBBLE, ICML 2021, eq. (4).
    """

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array) -> tuple[jax.Array, dict[str, jax.Array]]:
        del key  # Unused.
        return bt_term(_member_logits(cfg, params, batch), batch)

    return loss_fn


def bt_term(logits: jax.Array, batch: PrefBatch) -> tuple[jax.Array, dict[str, jax.Array]]:
    """The BT term and its metrics from the members' (M, B) logits on their own minibatches.

    Shared by ``bt_loss`` and SURF's ``cropped_bt_loss``, which differ only in the logits.
    """
    per_pair = bt_cross_entropy(logits, batch.labels) * batch.weight
    per_member = jnp.sum(per_pair, axis=1) / jnp.maximum(jnp.sum(batch.weight, axis=1), 1.0)
    loss = jnp.sum(per_member)
    correct, hard = _hard_correct(logits, batch.labels)
    accuracy = jnp.sum(correct * batch.weight) / jnp.maximum(jnp.sum(hard * batch.weight), 1.0)
    return loss, {"bt_loss": loss, "bt_accuracy": accuracy}


def total_loss(terms: Sequence[LossTerm]) -> LossTerm:
    """The sum of loss terms, each called with its own subkey.

    Args:
      terms: loss terms ``(params, batch, key) -> (loss, metrics)``.

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


def accuracy(cfg: RewardConfig, params: Any, seg_a: Any, seg_b: Any, labels: jax.Array, mask: jax.Array) -> jax.Array:
    """Members' mean accuracy on labelled pairs (hard labels with mask 1 only).

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
    logits = _pair_logits(cfg, params, seg_a.obs, seg_a.action, seg_b.obs, seg_b.action)
    correct, hard = _hard_correct(logits, labels[None])
    return jnp.sum(correct * mask) / jnp.maximum(jnp.sum(hard * mask), 1.0)


def add_labels(state: RewardState, seg_a: Any, seg_b: Any, labels: jax.Array, mask: jax.Array) -> RewardState:
    """Appends the answered pairs (mask 1) to the label store; skipped pairs are dropped, as B-Pref.

    Args:
      state: the reward state.
      seg_a: segments with ``obs`` and ``action`` (N, H, ...).
      seg_b: the other segment of each pair.
      labels: (N,) ``P(seg_b preferred)``.
      mask: (N,) 1 for answered pairs, 0 for skipped ones.

    Returns:
      The state with the kept pairs written at ``ptr`` onwards (wrapping), ``count`` updated.
    """
    data = state.data
    capacity = data.labels.shape[0]
    keep = mask > 0
    rank = jnp.cumsum(keep.astype(jnp.int32)) - 1
    slot = jnp.where(keep, (data.ptr + rank) % capacity, capacity)  # Out of range: dropped.
    kept = jnp.sum(keep.astype(jnp.int32))

    def write(store, new):
        return store.at[slot].set(new.astype(store.dtype), mode="drop")

    data = data.replace(
        obs_a=write(data.obs_a, seg_a.obs),
        act_a=write(data.act_a, seg_a.action),
        obs_b=write(data.obs_b, seg_b.obs),
        act_b=write(data.act_b, seg_b.action),
        labels=write(data.labels, labels),
        ptr=(data.ptr + kept) % capacity,
        count=jnp.minimum(data.count + kept, capacity),
    )
    return state.replace(data=data)


@flax.struct.dataclass
class _EpochCarry:
    params: Any
    opt_state: Any
    batch: jax.Array
    correct: jax.Array
    loss: jax.Array


def _shuffles(key: jax.Array, members: int, count: jax.Array, capacity: int, padded: int) -> jax.Array:
    """Per-member random orders of the filled slots, padded: (M, padded) int32."""
    noise = jax.random.uniform(key, (members, capacity))
    noise = jnp.where(jnp.arange(capacity) < count, noise, 2.0)  # Empty slots sort last.
    order = jnp.argsort(noise, axis=1).astype(jnp.int32)
    return jnp.pad(order, ((0, 0), (0, padded - capacity)))


def _minibatch(data: LabelData, order: jax.Array, index: jax.Array, batch_size: int) -> PrefBatch:
    """Minibatch ``index`` of every member's order; positions >= count get weight 0."""
    members = order.shape[0]
    start = index * batch_size
    slots = jax.lax.dynamic_slice(order, (0, start), (members, batch_size))
    weight = ((start + jnp.arange(batch_size)) < data.count).astype(data.labels.dtype)
    return PrefBatch(
        obs_a=data.obs_a[slots],
        act_a=data.act_a[slots],
        obs_b=data.obs_b[slots],
        act_b=data.act_b[slots],
        labels=data.labels[slots],
        weight=jnp.broadcast_to(weight, (members, batch_size)),
    )


def _adam_step(cfg: RewardConfig, grad_fn, optimizer, carry: _EpochCarry, batch: PrefBatch, key: jax.Array):
    """One Adam step on a minibatch: (params, opt_state, correct, counted, loss).

    ``correct`` and ``counted`` (M, B) are the members' right and counted hard labels *before* the
    step (B-Pref's and SURF's accuracy), weighted by the minibatch's padding mask.
    """
    logits = _member_logits(cfg, carry.params, batch)
    correct, hard = _hard_correct(logits, batch.labels)
    grads, metrics = grad_fn(carry.params, batch, key)
    updates, opt_state = optimizer.update(grads, carry.opt_state, carry.params)
    params = optax.apply_updates(carry.params, updates)
    return params, opt_state, correct * batch.weight, hard * batch.weight, metrics["loss"]


def train_epoch(
    cfg: RewardConfig, state: RewardState, key: jax.Array, terms: Sequence[LossTerm] | None = None
) -> tuple[RewardState, dict[str, jax.Array]]:
    """One epoch over the stored labels in per-member shuffled minibatches (B-Pref's ``train_reward``).

    The epoch's training accuracy counts, per member, the hard labels its logits got right in
    each minibatch *before* that minibatch's update (as B-Pref), over all stored hard labels.

    Args:
      cfg: the reward settings.
      state: the reward state.
      key: PRNG key of this epoch.
      terms: loss terms; default ``(bt_loss(cfg),)``.

    Returns:
      The updated state and metrics ``accuracy`` (members' mean) and ``loss`` (mean over minibatches).
    """
    terms = (bt_loss(cfg),) if terms is None else tuple(terms)
    grad_fn = jax.grad(total_loss(terms), has_aux=True)
    optimizer = _optimizer(cfg)
    data = state.data
    capacity = data.labels.shape[0]
    num_batches_max = -(-capacity // cfg.batch_size)
    key_order, key_loss = jax.random.split(key)
    order = _shuffles(key_order, cfg.ensemble_size, data.count, capacity, num_batches_max * cfg.batch_size)
    num_batches = (data.count + cfg.batch_size - 1) // cfg.batch_size

    def body(carry: _EpochCarry) -> _EpochCarry:
        batch = _minibatch(data, order, carry.batch, cfg.batch_size)
        key_step = jax.random.fold_in(key_loss, carry.batch)
        params, opt_state, correct, _, loss = _adam_step(cfg, grad_fn, optimizer, carry, batch, key_step)
        correct = carry.correct + jnp.sum(correct, axis=1)
        return _EpochCarry(params, opt_state, carry.batch + 1, correct, carry.loss + loss)

    start = _EpochCarry(
        params=state.params,
        opt_state=state.opt_state,
        batch=jnp.zeros((), jnp.int32),
        correct=jnp.zeros(cfg.ensemble_size),
        loss=jnp.zeros(()),
    )
    end = jax.lax.while_loop(lambda c: c.batch < num_batches, body, start)
    filled = jnp.arange(capacity) < data.count
    num_hard = jnp.sum(filled & (data.labels != 0.5))
    train_accuracy = jnp.mean(end.correct) / jnp.maximum(num_hard, 1)
    metrics = {"accuracy": train_accuracy, "loss": end.loss / jnp.maximum(num_batches, 1)}
    return state.replace(params=end.params, opt_state=end.opt_state), metrics


@flax.struct.dataclass
class _TrainCarry:
    state: RewardState
    epoch: jax.Array
    accuracy: jax.Array
    loss: jax.Array


def train(
    cfg: RewardConfig, state: RewardState, key: jax.Array, terms: Sequence[LossTerm] | None = None
) -> tuple[RewardState, dict[str, jax.Array]]:
    """One feedback session: up to ``max_epochs`` epochs, stopping once accuracy > ``stop_accuracy``.

    Epoch ``e`` uses ``jax.random.fold_in(key, e)``, so the result is that of the Python loop
    ``for e in range(max_epochs): state, m = train_epoch(cfg, state, fold_in(key, e), terms);
    if m["accuracy"] > stop_accuracy: break``. The loop is a ``lax.while_loop``: under ``vmap``
    over seeds it runs until every seed has stopped, and JAX's batching of ``while_loop``
    keeps the carry of a seed whose condition is already false unchanged (its updates are
    masked), so every seed equals its unbatched run. Nothing is trained while no label is stored.

    Args:
      cfg: the reward settings.
      state: the reward state with its labels.
      key: PRNG key of the session.
      terms: loss terms, default ``(bt_loss(cfg),)``; e.g. add REBEL's ``lambda * V`` term.

    Returns:
      The trained state and metrics ``epochs`` (int32), ``train_accuracy`` and ``loss`` of the
      last epoch run (0 if none ran).

    References:
      Lee, Smith, Abbeel. B-Pref, 2021 (``train_PEBBLE.learn_reward``).
    """

    def cond(carry: _TrainCarry) -> jax.Array:
        running = (carry.epoch < cfg.max_epochs) & (carry.accuracy <= cfg.stop_accuracy)
        return running & (state.data.count > 0)

    def body(carry: _TrainCarry) -> _TrainCarry:
        new_state, metrics = train_epoch(cfg, carry.state, jax.random.fold_in(key, carry.epoch), terms)
        return _TrainCarry(new_state, carry.epoch + 1, metrics["accuracy"], metrics["loss"])

    start = _TrainCarry(state, jnp.zeros((), jnp.int32), jnp.asarray(-1.0), jnp.zeros(()))
    end = jax.lax.while_loop(cond, body, start)
    metrics = {"epochs": end.epoch, "train_accuracy": jnp.maximum(end.accuracy, 0.0), "loss": end.loss}
    return end.state, metrics


def train_iterations(
    cfg: RewardConfig, state: RewardState, key: jax.Array, terms: Sequence[LossTerm], num_iters: jax.Array
) -> tuple[RewardState, dict[str, jax.Array]]:
    """SURF's session (``semi_train_reward``): ``num_iters`` minibatch steps, no early stopping.

    Step ``i`` takes minibatch ``i mod b`` (``b = ceil(count / batch_size)``) of per-member
    orders drawn afresh for every pass ``i // b`` over the labels (SURF reshuffles whenever a
    pass ends; with ``count <= batch_size`` every step sees all labels). The terms close over
    their own data (e.g. ``pseudo_label_term`` over the pool). The accuracy counts, as SURF's,
    each member's correct hard labels over all steps, before each step's update.

    Args:
      cfg: the reward settings.
      state: the reward state with its labels.
      key: PRNG key of the session.
      terms: loss terms.
      num_iters: () int, may be traced (see :func:`rebel_jax.surf.surf_iterations`).

    Returns:
      The trained state and metrics ``epochs`` (the steps run, int32), ``train_accuracy`` and
      ``loss`` (mean over steps; 0 if none ran).
    """
    grad_fn = jax.grad(total_loss(tuple(terms)), has_aux=True)
    optimizer = _optimizer(cfg)
    data = state.data
    capacity = data.labels.shape[0]
    padded = -(-capacity // cfg.batch_size) * cfg.batch_size
    num_batches = jnp.maximum((data.count + cfg.batch_size - 1) // cfg.batch_size, 1)
    num_iters = jnp.where(data.count > 0, num_iters, 0)
    key_order, key_loss = jax.random.split(key)

    def body(carry: _EpochCarry) -> _EpochCarry:
        order = _shuffles(
            jax.random.fold_in(key_order, carry.batch // num_batches), cfg.ensemble_size, data.count, capacity, padded
        )
        batch = _minibatch(data, order, carry.batch % num_batches, cfg.batch_size)
        key_step = jax.random.fold_in(key_loss, carry.batch)
        params, opt_state, correct, hard, loss = _adam_step(cfg, grad_fn, optimizer, carry, batch, key_step)
        accuracy = jnp.sum(correct) / jnp.maximum(jnp.sum(hard), 1.0)
        return _EpochCarry(params, opt_state, carry.batch + 1, carry.correct + accuracy, carry.loss + loss)

    start = _EpochCarry(
        params=state.params,
        opt_state=state.opt_state,
        batch=jnp.zeros((), jnp.int32),
        correct=jnp.zeros(()),
        loss=jnp.zeros(()),
    )
    end = jax.lax.while_loop(lambda c: c.batch < num_iters, body, start)
    steps = jnp.maximum(end.batch, 1)
    metrics = {"epochs": end.batch, "train_accuracy": end.correct / steps, "loss": end.loss / steps}
    return state.replace(params=end.params, opt_state=end.opt_state), metrics
