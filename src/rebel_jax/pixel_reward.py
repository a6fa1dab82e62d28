"""The pixel reward ensemble of SURF's pixel branch, learned from preferences on frame-replay segments.

Read from alinlab/SURF 866630a, branch ``pixel`` (``pixel_reward_model.py``, ``pixel_train_PEBBLE.py``,
``replay_buffer_drqv2.py``, ``cfgs/config_pebble.yaml``, ``README.md``):

- Each of the 3 members (``ensemble_size``, config_pebble.yaml:47) is a ``RewardPredictor``
  (pixel_reward_model.py:42-78): its own DrQ-v2 conv encoder (no trunk: ``feature_dim`` is unused,
  :53-57), the flattened features concatenated with the action, an MLP of 2 hidden ReLU layers of 256
  (``hidden_dim=256, hidden_depth=2``, :48-49, :28-39) and a tanh output (:58-59). Linear layers are
  orthogonal with zero bias (``weight_init``, :22-27, applied at :65); the encoder keeps DrQ-v2's init.
- Input: the 3-frame stack with the README's ``reward_stack=True`` (README.md:22, :32); the configs'
  default ``reward_stack: False`` would feed the newest frame alone (config_pebble.yaml:55).
- Adam, lr 3e-5 (README's ``reward_lr=3e-5``; the config default is 1e-4, config_pebble.yaml:41).
- Segments of 50 agent steps (config_pebble.yaml:37 ``segment: 50``), cut from the last 20 stored
  episodes (``reward_max_episodes: 20``, config_pebble.yaml:56; ``get_queries``, pixel_reward_model.py:540-552)
  with a start uniform over all ``L - H + 1`` starts (:547).
- The label store keeps *indices* of segments in the replay and gathers their frames when training
  (``buffer_seg1_index``, pixel_reward_model.py:201-203, :855-859): this module does the same, so a
  label costs four int32 and a float, not ``2 x 50`` frame stacks.
- A session trains ``reward_update`` epochs (README: 20) of minibatches of 16 pairs
  (``train_batch_size = 16``, pixel_reward_model.py:214), each member its own permutation (:816-820,
  :855), stopping once the members' mean epoch accuracy exceeds 0.97 (pixel_train_PEBBLE.py:269-278).
  The accuracy counts each minibatch's predictions before its step (:909-919).
- The BT loss is PyTorch's ``CrossEntropyLoss`` on ``[G(a), G(b)]`` with hard labels (:908-911), the
  Bradley-Terry cross-entropy of :func:`rebel_jax.reward_model.bt_cross_entropy`.

Deviations (documented where they are made): one Adam step on the *sum* of the members' losses where
SURF steps its one Adam once per member (:851-913: zero gradients for the other members, whose Adam
moments still move them); the candidates of disagreement sampling are scored a chunk of pairs at a time.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp
import optax

from rebel_jax import frame_replay, queries, reward_model, surf
from rebel_jax.errors import check as _check
from rebel_jax.networks import Encoder, dense_kwargs, orthogonal


@dataclasses.dataclass(frozen=True)
class PixelRewardConfig:
    """SURF's pixel reward ensemble and its session (alinlab/SURF branch ``pixel``; see the module docstring)."""

    ensemble_size: int = 3
    """Members (config_pebble.yaml:47)."""
    hidden: int = 256
    """Width of the MLP's hidden layers (pixel_reward_model.py:48)."""
    depth: int = 2
    """Hidden ReLU layers of the MLP (pixel_reward_model.py:49)."""
    lr: float = 3e-5
    """Adam learning rate (README's ``reward_lr=3e-5``)."""
    batch_size: int = 16
    """Labelled pairs per minibatch and member (``train_batch_size = 16``, pixel_reward_model.py:214)."""
    max_epochs: int = 20
    """Most epochs per session (README's ``reward_update=20``; pixel_train_PEBBLE.py:269)."""
    stop_accuracy: float = 0.97
    """Stop once the members' mean epoch accuracy exceeds this (pixel_train_PEBBLE.py:277)."""
    chunk: int = 8
    """Segment pairs scored at once when ranking disagreement candidates, and rows relabelled at once per
    env: bounds the frame stacks in memory (not a SURF setting)."""
    precision: str = "tf32"
    """Matmul and convolution precision: ``tf32``, ``highest`` or ``bf16``."""
    member_loop: bool = True
    """Compute the members' losses and gradients one member at a time (``lax.map``) instead of all at once
    (``vmap``): the same minibatches, crops and numbers up to float rounding, with about one member's
    working memory in a reward-training step instead of ``ensemble_size`` members' (not a SURF setting;
    BENCHMARKS.md, "Pixel runs before any GPU time"). The Adam step of all members stays one."""

    def validate(self) -> None:
        for name in ("ensemble_size", "hidden", "depth", "batch_size", "max_epochs", "chunk"):
            _check(getattr(self, name) >= 1, f"pixel_reward.{name}", getattr(self, name), ">= 1")
        _check(self.lr > 0, "pixel_reward.lr", self.lr, "> 0")
        _check(0 <= self.stop_accuracy <= 1, "pixel_reward.stop_accuracy", self.stop_accuracy, "[0, 1]")
        precisions = ("tf32", "highest", "bf16")
        _check(self.precision in precisions, "pixel_reward.precision", self.precision, ", ".join(precisions))


class PixelRewardNet(nn.Module):
    """One member: ``tanh(MLP(concat(Encoder(stack), action)))``.

    SURF's ``RewardPredictor`` (pixel_reward_model.py:42-78)."""

    hidden: int
    depth: int
    precision: str = "tf32"

    @nn.compact
    def __call__(self, obs: jax.Array, action: jax.Array) -> jax.Array:
        """Args: obs (..., H, W, C) uint8 stacks; action (..., A). Returns: (...) rewards in (-1, 1)."""
        x = jnp.concatenate([Encoder(precision=self.precision)(obs), action.astype(jnp.float32)], axis=-1)
        # SURF's weight_init (pixel_reward_model.py:22-27): orthogonal Linear weights, zero biases.
        init = dict(kernel_init=orthogonal(), bias_init=nn.initializers.zeros)
        kw = dense_kwargs(self.precision)
        for _ in range(self.depth):
            x = nn.relu(nn.Dense(self.hidden, **init, **kw)(x))
        return jnp.tanh(nn.Dense(1, **init, **kw)(x)[..., 0].astype(jnp.float32))


@flax.struct.dataclass
class PixelLabels:
    """Labelled pairs as segment places in the frame replay (SURF's ``buffer_seg*_index``)."""

    row_a: jax.Array
    """(C,) int32 first buffer row of segment a."""
    env_a: jax.Array
    """(C,) int32 its environment."""
    row_b: jax.Array
    """(C,) int32 first buffer row of segment b."""
    env_b: jax.Array
    """(C,) int32 its environment."""
    labels: jax.Array
    """(C,) ``P(seg_b preferred)``."""
    ptr: jax.Array
    count: jax.Array


@flax.struct.dataclass
class PixelRewardState:
    """Members' parameters (leading member axis), one Adam state, the labels."""

    params: Any
    opt_state: Any
    data: PixelLabels
    pool: PixelLabels | None = None
    """SURF's unlabelled pairs (places; ``labels`` unused), or None."""


@flax.struct.dataclass
class SegmentPlaces:
    """N segments of H steps: start row and environment each (the frames stay in the replay)."""

    row: jax.Array
    """(N,) int32 first row."""
    env: jax.Array
    """(N,) int32 environment."""


def network(cfg: PixelRewardConfig) -> PixelRewardNet:
    return PixelRewardNet(hidden=cfg.hidden, depth=cfg.depth, precision=cfg.precision)


def init(
    cfg: PixelRewardConfig, key: jax.Array, obs_shape: tuple[int, int, int], action_size: int, capacity: int
) -> PixelRewardState:
    """Fresh members (one key each) and an empty store of ``capacity`` labels."""
    keys = jax.random.split(key, cfg.ensemble_size)
    obs, action = jnp.zeros((1, *obs_shape), jnp.uint8), jnp.zeros((1, action_size))
    params = jax.vmap(network(cfg).init, in_axes=(0, None, None))(keys, obs, action)
    return PixelRewardState(params=params, opt_state=optax.adam(cfg.lr).init(params), data=empty_places(capacity))


def empty_places(capacity: int) -> PixelLabels:
    """An empty store of ``capacity`` pairs."""
    zeros = jnp.zeros((capacity,), jnp.int32)
    scalar = jnp.zeros((), jnp.int32)
    return PixelLabels(zeros, zeros, zeros, zeros, jnp.zeros((capacity,)), scalar, scalar)


def predict(cfg: PixelRewardConfig, params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """(M, ...) per-member rewards of stacks ``obs`` (..., H, W, C) and actions (..., A)."""
    return jax.vmap(network(cfg).apply, in_axes=(0, None, None))(params, obs, action)


def mean_reward(cfg: PixelRewardConfig, params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """The ensemble mean, the reward the agent learns from (SURF's ``r_hat_batch``, pixel_reward_model.py:447-455)."""
    return jnp.mean(predict(cfg, params, obs, action), axis=0)


def segment_rows(start: jax.Array, horizon: int) -> jax.Array:
    """(..., H) rows of the segments starting at ``start`` (...)."""
    return start[..., None] + jnp.arange(horizon)


def member_step_rewards(
    cfg: PixelRewardConfig, member_params: Any, buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int
) -> jax.Array:
    """(N, H) one member's learned rewards ``r(s_h, a_h)`` on segments gathered from the replay."""
    rows = segment_rows(seg.row, horizon)
    env = jnp.broadcast_to(seg.env[:, None], rows.shape)
    obs = frame_replay.row_stacks(buffer, rows, env)
    return network(cfg).apply(member_params, obs, buffer.action[rows, env])


def member_returns(
    cfg: PixelRewardConfig, member_params: Any, buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int
) -> jax.Array:
    """(N,) one member's learned returns ``sum_h r(s_h, a_h)`` of segments gathered from the replay."""
    return jnp.sum(member_step_rewards(cfg, member_params, buffer, seg, horizon), axis=-1)


def ensemble_returns(
    cfg: PixelRewardConfig, params: Any, buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int
) -> jax.Array:
    """(M, N) every member's returns, ``cfg.chunk`` segments at a time (one chunk's stacks in memory)."""
    n = seg.row.shape[0]
    chunks = -(-n // cfg.chunk)
    pad = chunks * cfg.chunk - n
    padded = jax.tree.map(lambda x: jnp.pad(x, (0, pad)).reshape(chunks, cfg.chunk), seg)

    def one(part):
        return jax.vmap(member_returns, in_axes=(None, 0, None, None, None))(cfg, params, buffer, part, horizon)

    returns = jax.lax.map(one, padded)  # (chunks, M, chunk)
    return jnp.moveaxis(returns, 1, 0).reshape(cfg.ensemble_size, -1)[:, :n]


def place_rewards(cfg: PixelRewardConfig, params: Any, buffer: frame_replay.FrameBuffer, place, action) -> jax.Array:
    """(M, ...) members' rewards at replay places ``place`` (..., 2) = (row, env) with actions ``action`` (..., A):
    the ``predict_fn`` of REBEL's value term on pixels (the stacks are gathered here, not carried)."""
    obs = frame_replay.row_stacks(buffer, place[..., 0], place[..., 1])
    return predict(cfg, params, obs, action)


def true_returns(buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int) -> jax.Array:
    """(N, H) the stored task rewards of the segments (what the teacher reads)."""
    rows = segment_rows(seg.row, horizon)
    return buffer.true_reward[rows, seg.env[:, None]]


def sample_segments(
    key: jax.Array, buffer: frame_replay.FrameBuffer, n: int, horizon: int, episode_length: int, recent_episodes: int
) -> SegmentPlaces:
    """n segments uniform over the last ``recent_episodes`` complete episodes, starts uniform in [0, L - H].

    The trainer's environments start their episodes together at vector step 0 and the buffer never
    wraps (its rows hold the whole run), so episode ``b`` of env ``e`` is rows ``[b L, (b + 1) L)``;
    episodes rank by ``b`` then ``e``, the last ``recent_episodes`` of the complete ones are eligible
    (SURF: the last ``reward_max_episodes``, pixel_reward_model.py:542-546) and the start takes any of
    the ``L - H + 1`` places (pixel_reward_model.py:547).

    Args:
        key: PRNG key.
        buffer: a frame replay that has not wrapped.
        n: segments (static).
        horizon: H (static).
        episode_length: agent steps L per episode (static).
        recent_episodes: eligible most recent complete episodes.

    Returns:
        :class:`SegmentPlaces` (n,).
    """
    key_episode, key_start = jax.random.split(key)
    num_envs = buffer.num_envs
    complete = (buffer.size // episode_length) * num_envs
    low = jnp.maximum(complete - recent_episodes, 0)
    flat = jax.random.randint(key_episode, (n,), low, jnp.maximum(complete, 1))
    offset = jax.random.randint(key_start, (n,), 0, episode_length - horizon + 1)
    row = (flat // num_envs) * episode_length + offset
    return SegmentPlaces(row=row.astype(jnp.int32), env=(flat % num_envs).astype(jnp.int32))


def select(
    cfg: PixelRewardConfig,
    key: jax.Array,
    params: Any,
    buffer: frame_replay.FrameBuffer,
    num_queries: int,
    horizon: int,
    episode_length: int,
    recent_episodes: int,
    sampling: str,
    candidate_factor: int,
    first: jax.Array,
) -> tuple[SegmentPlaces, SegmentPlaces]:
    """The session's pairs: uniform, or the ``num_queries`` of ``candidate_factor x num_queries`` uniform
    candidates whose members' preference probabilities disagree most (B-Pref's, SURF's ``disagreement_sampling``,
    pixel_reward_model.py:740-757). The first session is uniform (pixel_train_PEBBLE.py:245-246): the
    first ``num_queries`` candidates, themselves a uniform draw.

    Only indices are drawn; a candidate's frames are gathered when it is scored, ``cfg.chunk`` pairs at a time.
    """
    if sampling == "uniform":
        both = sample_segments(key, buffer, 2 * num_queries, horizon, episode_length, recent_episodes)
        return jax.tree.map(lambda x: x[:num_queries], both), jax.tree.map(lambda x: x[num_queries:], both)
    _check(sampling == "disagreement", "query.sampling", sampling, "uniform, disagreement (pixel tasks)")
    c = candidate_factor * num_queries
    both = sample_segments(key, buffer, 2 * c, horizon, episode_length, recent_episodes)
    seg_a, seg_b = jax.tree.map(lambda x: x[:c], both), jax.tree.map(lambda x: x[c:], both)
    returns = ensemble_returns(cfg, params, buffer, both, horizon)
    probs = jax.nn.sigmoid(returns[:, c:] - returns[:, :c])  # (M, C) P(b preferred)
    score = jnp.where(first, -jnp.arange(c, dtype=probs.dtype), queries.disagreement(probs))
    _, top = jax.lax.top_k(score, num_queries)
    return jax.tree.map(lambda x: x[top], seg_a), jax.tree.map(lambda x: x[top], seg_b)


def add_labels(
    state: PixelRewardState, seg_a: SegmentPlaces, seg_b: SegmentPlaces, labels: jax.Array, mask: jax.Array
) -> PixelRewardState:
    """Appends the kept pairs (mask 1) at ``ptr`` (SURF's ``put_queries``, pixel_reward_model.py:554-575)."""
    return state.replace(data=append_places(state.data, seg_a, seg_b, labels, mask))


def append_places(
    data: PixelLabels, seg_a: SegmentPlaces, seg_b: SegmentPlaces, labels: jax.Array, mask: jax.Array
) -> PixelLabels:
    """``data`` with the pairs of mask 1 written at ``ptr`` onwards (wrapping)."""
    capacity = data.labels.shape[0]
    keep = mask > 0
    slot = jnp.where(keep, (data.ptr + jnp.cumsum(keep.astype(jnp.int32)) - 1) % capacity, capacity)
    kept = jnp.sum(keep.astype(jnp.int32))

    def write(store, new):
        return store.at[slot].set(new.astype(store.dtype), mode="drop")

    return data.replace(
        row_a=write(data.row_a, seg_a.row),
        env_a=write(data.env_a, seg_a.env),
        row_b=write(data.row_b, seg_b.row),
        env_b=write(data.env_b, seg_b.env),
        labels=write(data.labels, labels),
        ptr=(data.ptr + kept) % capacity,
        count=jnp.minimum(data.count + kept, capacity),
    )


def member_step_pairs(
    cfg: PixelRewardConfig,
    params: Any,
    buffer: frame_replay.FrameBuffer,
    seg_a: SegmentPlaces,
    seg_b: SegmentPlaces,
    horizon: int,
) -> tuple[jax.Array, jax.Array]:
    """(M, B, H) each member's per-step rewards on both segments of its own pairs (fields of ``seg_*`` are (M, B))."""

    def one(member_params, a, b):
        return (
            member_step_rewards(cfg, member_params, buffer, a, horizon),
            member_step_rewards(cfg, member_params, buffer, b, horizon),
        )

    return jax.vmap(one)(params, seg_a, seg_b)


def bt_loss(
    cfg: PixelRewardConfig,
    params: Any,
    buffer: frame_replay.FrameBuffer,
    seg_a: SegmentPlaces,
    seg_b: SegmentPlaces,
    labels: jax.Array,
    weight: jax.Array,
    horizon: int,
    crop: int = 0,
    key: jax.Array | None = None,
    members: jax.Array | None = None,
) -> tuple[jax.Array, dict]:
    """The BT term: the sum over members of each member's weighted mean cross-entropy on its pairs.

    With ``crop > 0`` (SURF) the segments are ``horizon = H + 2 crop`` long and each member sums its
    rewards over fresh random crops (:func:`rebel_jax.surf.crop_masks`, drawn from ``key``), SURF's
    ``get_cropping_mask`` (pixel_reward_model.py:822-833, applied at :901-904).

    SURF's ``CrossEntropyLoss(r_hat, labels)`` over ``[G(a), G(b)]`` per member (pixel_reward_model.py:908-911),
    summed over members (SURF steps them one after another).

    Args:
        params: the parameters of M members (leading axis): the whole ensemble, or one member of it
            (``pixel_reward.member_loop``).
        seg_a, seg_b, labels, weight: (M, B) each member's pairs.
        members: (M,) int32 the ensemble indices of ``params``' members; None: all ``ensemble_size``.
            Every draw from ``key`` is made for the whole ensemble and these members' rows are kept, so a
            member's crops do not depend on which other members are computed with it.

    Returns:
        The loss and ``{"bt_loss", "bt_accuracy", "logits", "rewards_a", "rewards_b", "weight", "members"}``:
        the members' per-step rewards on their pairs (M, B, H), uncropped, and the pairs' weights, which
        REBEL's ``rebel.normalize`` reads (:func:`rebel_jax.agent_preference.reward_spread`), and
        ``members``, which SURF's pseudo-label term reads.
    """
    members = jnp.arange(cfg.ensemble_size) if members is None else members
    rewards_a, rewards_b = member_step_pairs(cfg, params, buffer, seg_a, seg_b, horizon)
    if crop:
        mask_a, mask_b = surf.crop_masks(key, (cfg.ensemble_size, labels.shape[1]), horizon, crop)
        mask_a, mask_b = mask_a[members], mask_b[members]
        logits = jnp.sum(rewards_b * mask_b, -1) - jnp.sum(rewards_a * mask_a, -1)
    else:
        logits = jnp.sum(rewards_b, -1) - jnp.sum(rewards_a, -1)
    batch = reward_model.PrefBatch(None, None, None, None, labels=labels, weight=weight)
    loss, metrics = reward_model.bt_term(logits, batch)
    return loss, dict(metrics, logits=logits, rewards_a=rewards_a, rewards_b=rewards_b, weight=weight, members=members)


@flax.struct.dataclass
class _Carry:
    params: Any
    opt_state: Any
    step: jax.Array
    correct: jax.Array
    loss: jax.Array


def train_epoch(
    cfg: PixelRewardConfig,
    state: PixelRewardState,
    buffer: frame_replay.FrameBuffer,
    key: jax.Array,
    horizon: int,
    terms: Sequence[Callable] = (),
    crop: int = 0,
) -> tuple[PixelRewardState, dict]:
    """One epoch: per-member permutations of the stored labels in minibatches of ``batch_size``.

    SURF's ``train_reward`` (pixel_reward_model.py:835-923): ``ceil(count / 16)`` minibatches, member m
    reading slots ``perm_m[i B : (i + 1) B]``; the accuracy counts each minibatch's hard labels right
    before its step, over all stored labels (0.5 labels do not count).

    ``terms`` are further loss terms ``(params, batch, key) -> (loss, metrics)`` added to the BT term at
    every step, ``batch`` being the BT term's metrics (:func:`bt_loss`): REBEL's ``lambda * V``
    (:func:`rebel_jax.agent_preference.agent_value_term` with pixel rewards), SURF's pseudo-labels.
    A term's loss must be a sum over the members of ``params`` (leading axis), each member's part
    depending on that member's parameters only; a term that draws from its key draws for the whole
    ensemble and keeps the rows of ``batch["members"]``.

    The loss is a sum of per-member losses, so each member's gradient is that of its own part. With
    ``cfg.member_loop`` the step computes them one member at a time (``lax.map``: one member's
    activations in memory), else all at once (``vmap`` inside the members' functions); every member
    sees the same minibatch and draws either way, the step keys being shared by the members.

    Returns:
        The state and ``{"accuracy", "loss"}`` (mean loss over the minibatches).
    """
    data = state.data
    capacity = data.labels.shape[0]
    b = cfg.batch_size
    num_batches = (data.count + b - 1) // b
    padded = -(-capacity // b) * b
    key_order, key_terms = jax.random.split(key)
    uniform = jax.random.uniform(key_order, (cfg.ensemble_size, capacity))
    noise = jnp.where(jnp.arange(capacity) < data.count, uniform, 2.0)
    order = jnp.pad(jnp.argsort(noise, axis=1).astype(jnp.int32), ((0, 0), (0, padded - capacity)))
    optimizer = optax.adam(cfg.lr)

    def loss_fn(params, seg_a, seg_b, labels, weight, step_key, members):
        key_crop, key_terms = jax.random.split(step_key)
        loss, metrics = bt_loss(cfg, params, buffer, seg_a, seg_b, labels, weight, horizon, crop, key_crop, members)
        for i, term in enumerate(terms):
            term_loss, _ = term(params, metrics, jax.random.fold_in(key_terms, i))
            loss = loss + term_loss
        return loss, dict(metrics, loss=loss)

    grad_fn = jax.grad(loss_fn, has_aux=True)

    def ensemble_grads(params, seg_a, seg_b, labels, weight, step_key):
        """Every member's gradient, the (M, B) logits and the loss summed over the members."""
        if not cfg.member_loop:
            grads, metrics = grad_fn(params, seg_a, seg_b, labels, weight, step_key, None)
            return grads, metrics["logits"], metrics["loss"]

        def one(m):
            mine = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, m, 1), (params, seg_a, seg_b, labels, weight))
            grads, metrics = grad_fn(*mine, step_key, m[None])
            return jax.tree.map(lambda g: g[0], grads), metrics["logits"][0], metrics["loss"]

        grads, logits, losses = jax.lax.map(one, jnp.arange(cfg.ensemble_size))
        return grads, logits, jnp.sum(losses)

    def body(carry: _Carry) -> _Carry:
        start = carry.step * b
        slots = jax.lax.dynamic_slice(order, (0, start), (cfg.ensemble_size, b))
        weight = jnp.broadcast_to(((start + jnp.arange(b)) < data.count).astype(jnp.float32), slots.shape)
        seg_a = SegmentPlaces(data.row_a[slots], data.env_a[slots])
        seg_b = SegmentPlaces(data.row_b[slots], data.env_b[slots])
        labels = data.labels[slots]
        step_key = jax.random.fold_in(key_terms, carry.step)
        grads, logits, loss = ensemble_grads(carry.params, seg_a, seg_b, labels, weight, step_key)
        correct = ((logits > 0) == (labels > 0.5)) & (labels != 0.5)
        updates, opt_state = optimizer.update(grads, carry.opt_state, carry.params)
        return _Carry(
            params=optax.apply_updates(carry.params, updates),
            opt_state=opt_state,
            step=carry.step + 1,
            correct=carry.correct + jnp.sum(correct * weight, axis=1),
            loss=carry.loss + loss,
        )

    start = _Carry(state.params, state.opt_state, jnp.zeros((), jnp.int32), jnp.zeros(cfg.ensemble_size), jnp.zeros(()))
    end = jax.lax.while_loop(lambda c: c.step < num_batches, body, start)
    hard = jnp.sum((jnp.arange(capacity) < data.count) & (data.labels != 0.5))
    metrics = {"accuracy": jnp.mean(end.correct) / jnp.maximum(hard, 1), "loss": end.loss / jnp.maximum(num_batches, 1)}
    return state.replace(params=end.params, opt_state=end.opt_state), metrics


def train(
    cfg: PixelRewardConfig,
    state: PixelRewardState,
    buffer: frame_replay.FrameBuffer,
    key: jax.Array,
    horizon: int,
    terms: Sequence[Callable] = (),
    crop: int = 0,
    max_epochs: int | None = None,
    stop_accuracy: float | None = None,
) -> tuple[PixelRewardState, dict]:
    """A session: epochs (``fold_in(key, e)``) until ``max_epochs`` or accuracy > ``stop_accuracy``
    (pixel_train_PEBBLE.py:267-278); nothing while no label is stored.

    Returns:
        The state and ``{"epochs", "train_accuracy", "loss"}`` of the last epoch.
    """

    epochs_most = cfg.max_epochs if max_epochs is None else max_epochs
    stop = cfg.stop_accuracy if stop_accuracy is None else stop_accuracy

    def cond(carry):
        _, epoch, accuracy, _ = carry
        return (epoch < epochs_most) & (accuracy <= stop) & (state.data.count > 0)

    def body(carry):
        st, epoch, _, _ = carry
        st, metrics = train_epoch(cfg, st, buffer, jax.random.fold_in(key, epoch), horizon, terms, crop)
        return st, epoch + 1, metrics["accuracy"], metrics["loss"]

    st, epochs, accuracy, loss = jax.lax.while_loop(
        cond, body, (state, jnp.zeros((), jnp.int32), jnp.asarray(-1.0), jnp.zeros(()))
    )
    return st, {"epochs": epochs, "train_accuracy": jnp.maximum(accuracy, 0.0), "loss": loss}


def candidate_bytes(num_pairs: int, horizon: int, height: int, width: int, stack: int = 3) -> int:
    """uint8 bytes of ``num_pairs`` pairs' frame stacks if gathered at once (what scoring by chunks avoids):
    ``2 x pairs x H x height x width x 3 stack``; 10 x 10 candidates of 50 steps at 84x84: 635 MB."""
    return 2 * num_pairs * horizon * height * width * 3 * stack


def frame_bytes(height: int, width: int) -> int:
    """One stored RGB frame."""
    return height * width * 3


def pseudo_label_term(
    cfg: PixelRewardConfig,
    surf_cfg: surf.SURFConfig,
    buffer: frame_replay.FrameBuffer,
    pool: PixelLabels,
    horizon: int,
) -> Callable:
    """SURF's pseudo-label term on the unlabelled pool (places), as :func:`rebel_jax.surf.pseudo_label_term`.

    Each step every member draws ``surf.ratio x batch_size`` pool pairs (SURF's ``mu``, 1 in its pixel
    config, cfgs/config_pebble_semi.yaml:67), labels them from its own sums over the central ``H``
    steps without gradient, and is trained on fresh crops with weight ``surf.weight`` (``lambda_u``)
    on the pairs at or above ``surf.threshold`` (pixel_reward_model_semi.py:291-301).

    Returns:
        ``(params, batch, key) -> (loss, metrics)``, ``batch`` the BT term's metrics: its ``members`` name
        the ensemble members of ``params`` (all of them, or one with ``pixel_reward.member_loop``).
    """
    c = surf_cfg.crop
    central = slice(c, horizon - c)

    def loss_fn(params, batch, key):
        # Drawn for the whole ensemble; the rows of the members in ``params`` kept (bt_loss's "members").
        shape = (cfg.ensemble_size, surf_cfg.ratio * cfg.batch_size)
        key_index, key_crop = jax.random.split(key)
        index = jax.random.randint(key_index, shape, 0, jnp.maximum(pool.count, 1))
        mask_a, mask_b = surf.crop_masks(key_crop, shape, horizon, c)
        members = batch["members"]
        index, mask_a, mask_b = index[members], mask_a[members], mask_b[members]

        def one(member_params, idx, m_a, m_b):
            reward_a = member_step_rewards(
                cfg, member_params, buffer, SegmentPlaces(pool.row_a[idx], pool.env_a[idx]), horizon
            )
            reward_b = member_step_rewards(
                cfg, member_params, buffer, SegmentPlaces(pool.row_b[idx], pool.env_b[idx]), horizon
            )
            logits = jnp.sum(reward_b * m_b, -1) - jnp.sum(reward_a * m_a, -1)
            central_logits = jnp.sum(reward_b[:, central], -1) - jnp.sum(reward_a[:, central], -1)
            return logits, jax.lax.stop_gradient(central_logits)

        logits, central_logits = jax.vmap(one)(params, index, mask_a, mask_b)
        labels, confident = surf.pseudo_labels(central_logits, surf_cfg.threshold)
        per_member = jnp.mean(reward_model.bt_cross_entropy(logits, labels) * confident, axis=1)
        loss = surf_cfg.weight * jnp.sum(per_member)
        return loss, {"pseudo_loss": loss, "pseudo_fraction": jnp.mean(confident)}

    return loss_fn
