"""Training the reward ensemble of :mod:`rebel_jax.preference.reward_model` on its label store, states and pixels alike.

A session is either **early-stopped epochs** (:func:`train`: B-Pref's ``train_PEBBLE.learn_reward``,
rll-research/BPref@f3ece2e; SURF's pixel branch, alinlab/SURF@214bc1d:pixel_train_PEBBLE.py:267-278) or a
**fixed number of minibatch steps** (:func:`train_iterations`: SURF's ``semi_train_reward``,
alinlab/SURF@2088ee8). Both take loss terms ``(params, batch, key) -> (loss, metrics)`` over a
:class:`~rebel_jax.preference.reward_model.PrefBatch` whose per-step rewards the step computes once under the
parameters being differentiated (:func:`loss_and_logits`), and both make one optimiser step per minibatch:

- every member reads its own random order of the stored pairs (B-Pref; SURF, pixel_reward_model.py:816-820);
- the training accuracy counts each minibatch's hard labels right *before* its step (B-Pref's and SURF's);
- the loss is a sum of per-member losses, so each member's gradient is that of its own part. With
  ``cfg.member_loop`` the members' gradients are computed one member at a time (``lax.map``: one member's
  activations in memory), else all at once (``vmap``); with ``cfg.per_member_adam`` each member then steps
  in turn (SURF's Adam, :func:`member_adam_step`), else one step of the optimiser moves them all: Adam at
  ``cfg.lr`` by default, or any ``optax`` transformation a method passes as ``optimizer`` (its state made
  by :func:`rebel_jax.preference.reward_model.new_state` with the same transformation);
- a method may weight or mask the stored pairs (``pair_weight``, one weight per slot of the label store): a
  minibatch's weight is that weight times "slot < count";
- the loss terms' own metrics (every key but ``loss`` and ``accuracy_logits``, each reduced to its mean) come
  back beside the loop's, averaged over the minibatch steps (in member-by-member modes over the members too).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import flax.struct
import jax
import jax.numpy as jnp
import optax

from rebel_jax.preference.reward_model import (
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


LOOP_METRICS = ("loss", "accuracy_logits")
"""The metrics of :func:`loss_and_logits` the loop reads itself; every other one is a loss term's own."""


def term_metrics(metrics: dict) -> dict[str, jax.Array]:
    """The loss terms' own metrics of a step (not :data:`LOOP_METRICS`), each reduced to its mean."""
    return {k: jnp.mean(v).astype(jnp.float32) for k, v in metrics.items() if k not in LOOP_METRICS}


def _zero_metrics(grad_fn, params: Any, batch: PrefBatch, key: jax.Array) -> dict[str, jax.Array]:
    """Zeros shaped as :func:`term_metrics` of a step (their structure, found without computing them)."""
    shapes = jax.eval_shape(lambda p, b, k: term_metrics(grad_fn(p, b, k)[1]), params, batch, key)
    return jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)


def _step(cfg: Any, grad_fn, params: Any, opt_state: Any, batch: PrefBatch, key: jax.Array, optimizer=None):
    """One optimiser step on a minibatch: ``(params, opt_state, logits (M, B) before the step, loss, terms'
    metrics)``; ``optimizer`` an ``optax`` transformation (default Adam at ``cfg.lr``)."""
    members = cfg.ensemble_size

    def member_grad(m, params):
        mine = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, m, 1), params)
        grads, metrics = grad_fn(mine, _one_member(batch, m), key)
        grad = jax.tree.map(lambda g: g[0], grads)
        return grad, metrics["accuracy_logits"][0], metrics["loss"], term_metrics(metrics)

    if cfg.per_member_adam:  # Member after member, each at the parameters the steps before it left.

        def one(m, carry):
            params, opt_state, logits, loss, terms = carry
            grad, member_logits, member_loss, member_terms = member_grad(m, params)
            params, opt_state = member_adam_step(cfg.lr, opt_state, params, grad, m)
            terms = jax.tree.map(lambda t, x: t + x / members, terms, member_terms)
            return params, opt_state, logits.at[m].set(member_logits), loss + member_loss, terms

        zeros = _zero_metrics(grad_fn, jax.tree.map(lambda x: x[:1], params), _one_member(batch, jnp.int32(0)), key)
        start = (params, opt_state, jnp.zeros(batch.labels.shape, jnp.float32), jnp.zeros(()), zeros)
        return jax.lax.fori_loop(0, members, one, start)
    if cfg.member_loop:
        grads, logits, losses, terms = jax.lax.map(lambda m: member_grad(m, params), jnp.arange(members))
        loss, terms = jnp.sum(losses), jax.tree.map(jnp.mean, terms)
    else:
        grads, metrics = grad_fn(params, batch, key)
        logits, loss, terms = metrics["accuracy_logits"], metrics["loss"], term_metrics(metrics)
    optimizer = optax.adam(cfg.lr) if optimizer is None else optimizer
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, logits, loss, terms


def _shuffles(key: jax.Array, members: int, count: jax.Array, capacity: int, padded: int) -> jax.Array:
    """Per-member random orders of the filled slots, padded: (M, padded) int32."""
    noise = jax.random.uniform(key, (members, capacity))
    noise = jnp.where(jnp.arange(capacity) < count, noise, 2.0)  # Empty slots sort last.
    order = jnp.argsort(noise, axis=1).astype(jnp.int32)
    return jnp.pad(order, ((0, 0), (0, padded - capacity)))


def _minibatch(
    data: PairStore, order: jax.Array, index: jax.Array, batch_size: int, pair_weight: jax.Array | None = None
) -> PrefBatch:
    """Minibatch ``index`` of every member's order; positions >= count get weight 0, the others the pair's weight
    (``pair_weight`` (C,) over the store's slots; 1 without)."""
    members = order.shape[0]
    start = index * batch_size
    slots = jax.lax.dynamic_slice(order, (0, start), (members, batch_size))
    weight = ((start + jnp.arange(batch_size)) < data.count).astype(data.labels.dtype)
    if pair_weight is not None:
        weight = weight * pair_weight.astype(weight.dtype)[slots]

    def take(x):
        return x[slots]

    return PrefBatch(
        a=jax.tree.map(take, data.a),
        b=jax.tree.map(take, data.b),
        labels=data.labels[slots],
        weight=jnp.broadcast_to(weight, (members, batch_size)) if pair_weight is None else weight,
        members=jnp.arange(members),
    )


@flax.struct.dataclass
class _Carry:
    params: Any
    opt_state: Any
    step: jax.Array
    correct: jax.Array
    loss: jax.Array
    terms: dict
    """The sums of the loss terms' own metrics over the steps run."""


def _start(grad_fn, state: RewardState, data: PairStore, order: jax.Array, b: int, key: jax.Array, correct) -> _Carry:
    """The loop's first carry: the state's parameters and optimiser state, no step, zero sums."""
    zeros = _zero_metrics(grad_fn, state.params, _minibatch(data, order, jnp.int32(0), b), key)
    return _Carry(state.params, state.opt_state, jnp.zeros((), jnp.int32), correct, jnp.zeros(()), zeros)


def _means(carry: _Carry, steps: jax.Array) -> dict[str, jax.Array]:
    """The terms' metrics of the loop, averaged over ``steps``."""
    return {k: v / jnp.maximum(steps, 1) for k, v in carry.terms.items()}


def train_epoch(
    cfg: Any,
    state: RewardState,
    key: jax.Array,
    terms: Sequence[LossTerm] | None = None,
    optimizer: optax.GradientTransformation | None = None,
    pair_weight: jax.Array | None = None,
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
      optimizer: the optimiser of the members' step (default Adam at ``cfg.lr``; see the module's docstring).
      pair_weight: (C,) a weight per slot of the label store (default 1).

    Returns:
      The updated state and metrics ``accuracy`` (members' mean), ``loss`` (mean over minibatches) and the
      terms' own metrics (means over minibatches).
    """
    terms = (bt_loss(cfg),) if terms is None else tuple(terms)
    grad_fn = jax.grad(loss_and_logits(cfg, terms), has_aux=True)
    data = state.data
    capacity, b = data.capacity, cfg.batch_size
    num_batches = (data.count + b - 1) // b
    key_order, key_loss = jax.random.split(key)
    order = _shuffles(key_order, cfg.ensemble_size, data.count, capacity, -(-capacity // b) * b)

    def body(carry: _Carry) -> _Carry:
        batch = _minibatch(data, order, carry.step, b, pair_weight)
        key_step = jax.random.fold_in(key_loss, carry.step)
        params, opt_state, logits, loss, step_terms = _step(
            cfg, grad_fn, carry.params, carry.opt_state, batch, key_step, optimizer
        )
        correct, _ = hard_correct(logits, batch.labels)
        correct = carry.correct + jnp.sum(correct * (batch.weight > 0), axis=1)
        sums = jax.tree.map(jnp.add, carry.terms, step_terms)
        return _Carry(params, opt_state, carry.step + 1, correct, carry.loss + loss, sums)

    start = _start(grad_fn, state, data, order, b, key_loss, jnp.zeros(cfg.ensemble_size))
    end = jax.lax.while_loop(lambda c: c.step < num_batches, body, start)
    num_hard = jnp.sum((jnp.arange(capacity) < data.count) & (data.labels != 0.5))
    train_accuracy = jnp.mean(end.correct) / jnp.maximum(num_hard, 1)
    metrics = {"accuracy": train_accuracy, "loss": end.loss / jnp.maximum(num_batches, 1), **_means(end, end.step)}
    return state.replace(params=end.params, opt_state=end.opt_state), metrics


def train(
    cfg: Any,
    state: RewardState,
    key: jax.Array,
    terms: Sequence[LossTerm] | None = None,
    max_epochs: int | jax.Array | None = None,
    stop_accuracy: float | None = None,
    optimizer: optax.GradientTransformation | None = None,
    pair_weight: jax.Array | None = None,
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
      optimizer, pair_weight: as :func:`train_epoch`.

    Returns:
      The trained state and metrics ``epochs`` (int32), ``train_accuracy`` and ``loss`` of the
      last epoch run (0 if none ran), and the terms' own metrics of that epoch.

    References:
      Lee, Smith, Abbeel. B-Pref, 2021 (``train_PEBBLE.learn_reward``).
    """
    most = cfg.max_epochs if max_epochs is None else max_epochs
    stop = cfg.stop_accuracy if stop_accuracy is None else stop_accuracy

    def cond(carry) -> jax.Array:
        _, epoch, accuracy, _, _ = carry
        return (epoch < most) & (accuracy <= stop) & (state.data.count > 0)

    def epoch_fn(st, epoch):
        return train_epoch(cfg, st, jax.random.fold_in(key, epoch), terms, optimizer, pair_weight)

    def body(carry):
        st, epoch, _, _, _ = carry
        st, metrics = epoch_fn(st, epoch)
        return st, epoch + 1, metrics["accuracy"], metrics["loss"], _terms_of(metrics)

    zeros = jax.tree.map(jnp.zeros_like, _terms_of(jax.eval_shape(epoch_fn, state, jnp.zeros((), jnp.int32))[1]))
    start = (state, jnp.zeros((), jnp.int32), jnp.asarray(-1.0), jnp.zeros(()), zeros)
    end, epochs, accuracy, loss, last = jax.lax.while_loop(cond, body, start)
    return end, {"epochs": epochs, "train_accuracy": jnp.maximum(accuracy, 0.0), "loss": loss, **last}


def _terms_of(metrics: dict) -> dict:
    """The terms' own metrics of :func:`train_epoch`'s (not its ``accuracy`` and ``loss``)."""
    return {k: v for k, v in metrics.items() if k not in ("accuracy", "loss")}


def train_iterations(
    cfg: Any,
    state: RewardState,
    key: jax.Array,
    terms: Sequence[LossTerm],
    num_iters: jax.Array,
    optimizer: optax.GradientTransformation | None = None,
    pair_weight: jax.Array | None = None,
) -> tuple[RewardState, dict[str, jax.Array]]:
    """SURF's session (``semi_train_reward``): ``num_iters`` minibatch steps, no early stopping.

    Step ``i`` takes minibatch ``i mod b`` (``b = ceil(count / batch_size)``) of per-member
    orders drawn afresh for every pass ``i // b`` over the labels (SURF reshuffles whenever a
    pass ends; with ``count <= batch_size`` every step sees all labels). The terms close over
    their own data (e.g. SURF's ``pseudo_label_term`` over the pool). The accuracy counts, as SURF's,
    each member's correct hard labels over all steps, before each step's update.

    Args:
      cfg: the reward settings.
      state: the reward state with its labels.
      key: PRNG key of the session.
      terms: loss terms.
      num_iters: () int, may be traced (see :func:`steps_per_label`).
      optimizer, pair_weight: as :func:`train_epoch`.

    Returns:
      The trained state and metrics ``epochs`` (the steps run, int32), ``train_accuracy`` and
      ``loss`` (mean over steps; 0 if none ran), and the terms' own metrics (means over the steps).
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
        batch = _minibatch(data, order, carry.step % num_batches, b, pair_weight)
        key_step = jax.random.fold_in(key_loss, carry.step)
        params, opt_state, logits, loss, step_terms = _step(
            cfg, grad_fn, carry.params, carry.opt_state, batch, key_step, optimizer
        )
        correct, hard = hard_correct(logits, batch.labels)
        trained = batch.weight > 0
        accuracy = jnp.sum(correct * trained) / jnp.maximum(jnp.sum(hard * trained), 1.0)
        sums = jax.tree.map(jnp.add, carry.terms, step_terms)
        return _Carry(params, opt_state, carry.step + 1, carry.correct + accuracy, carry.loss + loss, sums)

    order0 = _shuffles(key_order, cfg.ensemble_size, data.count, capacity, padded)
    start = _start(grad_fn, state, data, order0, b, key_loss, jnp.zeros(()))
    end = jax.lax.while_loop(lambda c: c.step < num_iters, body, start)
    steps = jnp.maximum(end.step, 1)
    metrics = {
        "epochs": end.step,
        "train_accuracy": end.correct / steps,
        "loss": end.loss / steps,
        **_means(end, steps),
    }
    return state.replace(params=end.params, opt_state=end.opt_state), metrics


def steps_per_label(reward_update: int, count: jax.Array, batch_size: int, kept: jax.Array) -> jax.Array:
    """SURF's (and QPA's) gradient steps per session: ``ceil(reward_update * labels / batch_size)``, none without new
    labels.

    ``train_PEBBLE_semi_dataaug.py`` (alinlab/SURF 2088ee8), ``learn_reward``: ``num_iters =
    int(np.ceil(self.cfg.reward_update * self.labeled_feedback / self.reward_model.train_batch_size))``,
    with ``reward_update=1000`` in its walker command and ``train_batch_size = 128``. SURF (as B-Pref)
    holds no session once the budget is spent (``run``: ``if self.total_feedback < self.cfg.max_feedback``);
    here a session whose seed kept no new pair (``kept`` 0) runs no step. The trainer discards such a
    session's training anyway, so this only spares its cost: about 10 s per session on cheetah_run,
    40 of the 50 sessions of a 1M run (RESULTS.md, question 1).
    """
    return jnp.where(kept > 0, (reward_update * count + batch_size - 1) // batch_size, 0)
