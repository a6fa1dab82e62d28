"""Training the reward ensemble of :mod:`rebel_jax.reward_model` on its label store, states and pixels alike.

A session is either **early-stopped epochs** (:func:`train`: B-Pref's ``train_PEBBLE.learn_reward``,
rll-research/BPref@f3ece2e; SURF's pixel branch, alinlab/SURF@214bc1d:pixel_train_PEBBLE.py:267-278) or a
**fixed number of minibatch steps** (:func:`train_iterations`: SURF's ``semi_train_reward``,
alinlab/SURF@2088ee8). Both take loss terms ``(params, batch, key) -> (loss, metrics)`` over a
:class:`~rebel_jax.reward_model.PrefBatch` whose per-step rewards the step computes once under the
parameters being differentiated (:func:`loss_and_logits`), and both make one optimiser step per minibatch:

- every member reads its own random order of the stored pairs (B-Pref; SURF, pixel_reward_model.py:816-820);
- the training accuracy counts each minibatch's hard labels right *before* its step (B-Pref's and SURF's);
- the loss is a sum of per-member losses, so each member's gradient is that of its own part. With
  ``cfg.member_loop`` the members' gradients are computed one member at a time (``lax.map``: one member's
  activations in memory), else all at once (``vmap``); with ``cfg.per_member_adam`` each member then steps
  in turn (SURF's Adam, :func:`member_adam_step`), else one Adam step moves them all.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax

from rebel_jax.reward_model import (
    LossTerm,
    MemberAdamState,
    PairStore,
    PrefBatch,
    RewardState,
    bt_loss,
    hard_correct,
    total_loss,
    with_rewards,
)


def member_adam_step(
    lr: float, state: MemberAdamState, params: Any, grad: Any, member: jax.Array, b1=0.9, b2=0.999, eps=1e-8
) -> tuple[Any, MemberAdamState]:
    """``opt.step()`` of torch 1.9's Adam (torch/optim/_functional.py ``adam``) over all members after
    ``zero_grad`` and member ``member``'s backward: ``grad`` is that member's gradient (no member axis), the
    others' are zeros; every member with a gradient (``seen``) takes a step, the others none."""
    seen = state.seen.at[member].set(True)
    count = state.count + seen
    t = count.astype(jnp.float32)

    def leaf(p, g_m, mu, nu):
        shape = (-1,) + (1,) * (p.ndim - 1)
        g = jnp.zeros_like(p).at[member].set(g_m)
        on = seen.reshape(shape)
        mu_new = jnp.where(on, b1 * mu + (1 - b1) * g, mu)
        nu_new = jnp.where(on, b2 * nu + (1 - b2) * g * g, nu)
        bias1, bias2 = (1 - b1**t).reshape(shape), (1 - b2**t).reshape(shape)
        step = lr / bias1 * mu_new / (jnp.sqrt(nu_new) / jnp.sqrt(bias2) + eps)
        return jnp.where(on, p - step, p), mu_new, nu_new  # a member never seen: t = 0, its NaN step unused

    out = jax.tree.map(leaf, params, grad, state.mu, state.nu)
    new_params, mu, nu = jax.tree.transpose(jax.tree.structure(params), jax.tree.structure((0, 0, 0)), out)
    return new_params, MemberAdamState(mu, nu, count, seen)


def loss_and_logits(cfg: Any, terms: Sequence[LossTerm]) -> LossTerm:
    """The training loss: the members' per-step rewards on the batch's pairs, then the sum of ``terms``.

    Returns:
      ``(params, batch, key) -> (loss, metrics)``; metrics hold the terms', ``loss`` and
      ``accuracy_logits`` (M, B): a term's (a cropped BT term's), else ``G(b) - G(a)`` on the whole segments.
    """
    total = total_loss(tuple(terms))

    def loss_fn(params: Any, batch: PrefBatch, key: jax.Array):
        batch = with_rewards(cfg, params, batch)
        loss, metrics = total(params, batch, key)
        whole = jnp.sum(batch.rewards_b, -1) - jnp.sum(batch.rewards_a, -1)
        return loss, dict(metrics, accuracy_logits=metrics.get("accuracy_logits", whole))

    return loss_fn


def _one_member(batch: PrefBatch, m: jax.Array) -> PrefBatch:
    """Member ``m``'s rows of a minibatch (leading axis 1), naming it in ``members``."""
    rows = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, m, 1), (batch.a, batch.b, batch.labels, batch.weight))
    return PrefBatch(*rows, members=m[None])


def _step(cfg: Any, grad_fn, params: Any, opt_state: Any, batch: PrefBatch, key: jax.Array):
    """One optimiser step on a minibatch: ``(params, opt_state, logits (M, B) before the step, loss)``."""
    members = cfg.ensemble_size

    def member_grad(m, params):
        mine = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, m, 1), params)
        grads, metrics = grad_fn(mine, _one_member(batch, m), key)
        return jax.tree.map(lambda g: g[0], grads), metrics["accuracy_logits"][0], metrics["loss"]

    if cfg.per_member_adam:  # Member after member, each at the parameters the steps before it left.

        def one(m, carry):
            params, opt_state, logits, loss = carry
            grad, member_logits, member_loss = member_grad(m, params)
            params, opt_state = member_adam_step(cfg.lr, opt_state, params, grad, m)
            return params, opt_state, logits.at[m].set(member_logits), loss + member_loss

        start = (params, opt_state, jnp.zeros(batch.labels.shape, jnp.float32), jnp.zeros(()))
        return jax.lax.fori_loop(0, members, one, start)
    if cfg.member_loop:
        grads, logits, losses = jax.lax.map(lambda m: member_grad(m, params), jnp.arange(members))
        loss = jnp.sum(losses)
    else:
        grads, metrics = grad_fn(params, batch, key)
        logits, loss = metrics["accuracy_logits"], metrics["loss"]
    updates, opt_state = optax.adam(cfg.lr).update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, logits, loss


def _shuffles(key: jax.Array, members: int, count: jax.Array, capacity: int, padded: int) -> jax.Array:
    """Per-member random orders of the filled slots, padded: (M, padded) int32."""
    noise = jax.random.uniform(key, (members, capacity))
    noise = jnp.where(jnp.arange(capacity) < count, noise, 2.0)  # Empty slots sort last.
    order = jnp.argsort(noise, axis=1).astype(jnp.int32)
    return jnp.pad(order, ((0, 0), (0, padded - capacity)))


def _minibatch(data: PairStore, order: jax.Array, index: jax.Array, batch_size: int) -> PrefBatch:
    """Minibatch ``index`` of every member's order; positions >= count get weight 0."""
    members = order.shape[0]
    start = index * batch_size
    slots = jax.lax.dynamic_slice(order, (0, start), (members, batch_size))
    weight = ((start + jnp.arange(batch_size)) < data.count).astype(data.labels.dtype)

    def take(x):
        return x[slots]

    return PrefBatch(
        a=jax.tree.map(take, data.a),
        b=jax.tree.map(take, data.b),
        labels=data.labels[slots],
        weight=jnp.broadcast_to(weight, (members, batch_size)),
        members=jnp.arange(members),
    )


@flax.struct.dataclass
class _Carry:
    params: Any
    opt_state: Any
    step: jax.Array
    correct: jax.Array
    loss: jax.Array


def train_epoch(
    cfg: Any, state: RewardState, key: jax.Array, terms: Sequence[LossTerm] | None = None
) -> tuple[RewardState, dict[str, jax.Array]]:
    """One epoch over the stored labels in per-member shuffled minibatches (B-Pref's ``train_reward``; SURF's
    ``train_reward``, pixel_reward_model.py:835-923: ``ceil(count / batch_size)`` minibatches).

    The epoch's training accuracy counts, per member, the hard labels its logits got right in each minibatch
    *before* that minibatch's update, over all stored hard labels.

    Args:
      cfg: the reward settings.
      state: the reward state.
      key: PRNG key of this epoch.
      terms: loss terms; default ``(bt_loss(cfg),)``.

    Returns:
      The updated state and metrics ``accuracy`` (members' mean) and ``loss`` (mean over minibatches).
    """
    terms = (bt_loss(cfg),) if terms is None else tuple(terms)
    grad_fn = jax.grad(loss_and_logits(cfg, terms), has_aux=True)
    data = state.data
    capacity, b = data.capacity, cfg.batch_size
    num_batches = (data.count + b - 1) // b
    key_order, key_loss = jax.random.split(key)
    order = _shuffles(key_order, cfg.ensemble_size, data.count, capacity, -(-capacity // b) * b)

    def body(carry: _Carry) -> _Carry:
        batch = _minibatch(data, order, carry.step, b)
        key_step = jax.random.fold_in(key_loss, carry.step)
        params, opt_state, logits, loss = _step(cfg, grad_fn, carry.params, carry.opt_state, batch, key_step)
        correct, _ = hard_correct(logits, batch.labels)
        correct = carry.correct + jnp.sum(correct * batch.weight, axis=1)
        return _Carry(params, opt_state, carry.step + 1, correct, carry.loss + loss)

    zero = jnp.zeros((), jnp.int32)
    start = _Carry(state.params, state.opt_state, zero, jnp.zeros(cfg.ensemble_size), jnp.zeros(()))
    end = jax.lax.while_loop(lambda c: c.step < num_batches, body, start)
    num_hard = jnp.sum((jnp.arange(capacity) < data.count) & (data.labels != 0.5))
    train_accuracy = jnp.mean(end.correct) / jnp.maximum(num_hard, 1)
    metrics = {"accuracy": train_accuracy, "loss": end.loss / jnp.maximum(num_batches, 1)}
    return state.replace(params=end.params, opt_state=end.opt_state), metrics


def train(
    cfg: Any,
    state: RewardState,
    key: jax.Array,
    terms: Sequence[LossTerm] | None = None,
    max_epochs: int | jax.Array | None = None,
    stop_accuracy: float | None = None,
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
      max_epochs: most epochs (may be traced, e.g. 0 for a session without new labels); default ``cfg``'s.
      stop_accuracy: default ``cfg``'s (``inf``: no early stop).

    Returns:
      The trained state and metrics ``epochs`` (int32), ``train_accuracy`` and ``loss`` of the
      last epoch run (0 if none ran).

    References:
      Lee, Smith, Abbeel. B-Pref, 2021 (``train_PEBBLE.learn_reward``).
    """
    most = cfg.max_epochs if max_epochs is None else max_epochs
    stop = cfg.stop_accuracy if stop_accuracy is None else stop_accuracy

    def cond(carry) -> jax.Array:
        _, epoch, accuracy, _ = carry
        return (epoch < most) & (accuracy <= stop) & (state.data.count > 0)

    def body(carry):
        st, epoch, _, _ = carry
        st, metrics = train_epoch(cfg, st, jax.random.fold_in(key, epoch), terms)
        return st, epoch + 1, metrics["accuracy"], metrics["loss"]

    start = (state, jnp.zeros((), jnp.int32), jnp.asarray(-1.0), jnp.zeros(()))
    end, epochs, accuracy, loss = jax.lax.while_loop(cond, body, start)
    return end, {"epochs": epochs, "train_accuracy": jnp.maximum(accuracy, 0.0), "loss": loss}


def train_iterations(
    cfg: Any, state: RewardState, key: jax.Array, terms: Sequence[LossTerm], num_iters: jax.Array
) -> tuple[RewardState, dict[str, jax.Array]]:
    """SURF's session (``semi_train_reward``): ``num_iters`` minibatch steps, no early stopping.

    Step ``i`` takes minibatch ``i mod b`` (``b = ceil(count / batch_size)``) of per-member
    orders drawn afresh for every pass ``i // b`` over the labels (SURF reshuffles whenever a
    pass ends; with ``count <= batch_size`` every step sees all labels). The terms close over
    their own data (e.g. ``surf.pseudo_label_term`` over the pool). The accuracy counts, as SURF's,
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
    grad_fn = jax.grad(loss_and_logits(cfg, terms), has_aux=True)
    data = state.data
    capacity, b = data.capacity, cfg.batch_size
    padded = -(-capacity // b) * b
    num_batches = jnp.maximum((data.count + b - 1) // b, 1)
    num_iters = jnp.where(data.count > 0, num_iters, 0)
    key_order, key_loss = jax.random.split(key)

    def body(carry: _Carry) -> _Carry:
        pass_key = jax.random.fold_in(key_order, carry.step // num_batches)
        order = _shuffles(pass_key, cfg.ensemble_size, data.count, capacity, padded)
        batch = _minibatch(data, order, carry.step % num_batches, b)
        key_step = jax.random.fold_in(key_loss, carry.step)
        params, opt_state, logits, loss = _step(cfg, grad_fn, carry.params, carry.opt_state, batch, key_step)
        correct, hard = hard_correct(logits, batch.labels)
        accuracy = jnp.sum(correct * batch.weight) / jnp.maximum(jnp.sum(hard * batch.weight), 1.0)
        return _Carry(params, opt_state, carry.step + 1, carry.correct + accuracy, carry.loss + loss)

    start = _Carry(state.params, state.opt_state, jnp.zeros((), jnp.int32), jnp.zeros(()), jnp.zeros(()))
    end = jax.lax.while_loop(lambda c: c.step < num_iters, body, start)
    steps = jnp.maximum(end.step, 1)
    metrics = {"epochs": end.step, "train_accuracy": end.correct / steps, "loss": end.loss / steps}
    return state.replace(params=end.params, opt_state=end.opt_state), metrics
