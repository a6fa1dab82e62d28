"""The pixel reward ensemble of SURF's pixel branch, learned from preferences on frame-replay segments.

Read from alinlab/SURF 214bc1d, branch ``pixel`` (``pixel_reward_model.py``, ``pixel_train_PEBBLE.py``,
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
- SURF's label store keeps *indices* of segments in its replay (``buffer_seg1_index``, ``buffer_seg2_index``:
  ``(reward_capacity, 2)`` uint32 (episode, start), pixel_reward_model.py:200-203, written by ``put_queries``,
  :554-575) and gathers the frames at every use (``get_segment_batch``, :856-859; replay_buffer_drqv2.py:231-253:
  ``L + stack - 1`` frames and ``L`` actions per segment). That needs a replay that never evicts: SURF's holds
  1M transitions (config_pebble.yaml:18), more than its runs' 500k agent steps. This module keeps
  *copies* instead (:class:`PixelLabels`): each labelled segment's ``L + stack - 1`` frames, each stored once
  as uint8 as in the frame replay, and its ``L`` actions, gathered from the replay when the label is added.
  The frames are those SURF would gather at every use, so the replay may be a ring of recent transitions
  (``pixel_train``). SURF's unlabelled pool (``u_buffer_seg*_index``, pixel_reward_model_semi.py:69-74) is
  kept the same way.
- A session trains ``reward_update`` epochs (README: 20) of minibatches of 16 pairs
  (``train_batch_size = 16``, pixel_reward_model.py:214), each member its own permutation (:816-820,
  :855), stopping once the members' mean epoch accuracy exceeds 0.97 (pixel_train_PEBBLE.py:269-278).
  The accuracy counts each minibatch's predictions before its step (:909-919).
- The BT loss is PyTorch's ``CrossEntropyLoss`` on ``[G(a), G(b)]`` with hard labels (:908-911), the
  Bradley-Terry cross-entropy of :func:`rebel_jax.reward_model.bt_cross_entropy`.

Deviations (documented where they are made): by default one Adam step on the *sum* of the members' losses where
SURF steps its one Adam once per member (:851-913: zero gradients for the other members, whose Adam
moments still move them; ``per_member_adam`` does SURF's); the candidates of disagreement sampling are scored a
chunk of pairs at a time.
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
    """Segment pairs scored at once when ranking disagreement candidates: bounds their frame stacks in memory
    (not a SURF setting)."""
    relabel_rows: int = 256
    """Replay rows relabelled at once (each row holds one transition per env), after every session: bounds the
    frame stacks in memory (SURF relabels 100 steps at a time, replay_buffer_drqv2.py:80-117). 256 rows took
    0.43 s for a cheetah replay of 25,000 rows x 4 envs, against 1.48 s at 8 rows (one H200, tf32,
    BENCHMARKS.md, "a pixel preference session by parts")."""
    precision: str = "tf32"
    """Matmul and convolution precision: ``tf32``, ``highest`` or ``bf16``."""
    per_member_adam: bool = False
    """SURF's Adam stepping (pixel_reward_model_semi.py:182-304, pixel_reward_model.py:851-913, torch 1.9.0 per
    its README): one Adam over all members, and per minibatch, member after member, ``zero_grad``, that member's
    backward and a step. ``zero_grad`` leaves zeros (not None) in torch 1.9, so every step also moves the other
    members by their moments alone and advances their step counts (:class:`MemberAdamState`). Off (default):
    one standard Adam step of all members on the sum of their losses, as B-Pref's state reward model
    (reward_model.py) and every pixel run so far. The member steps run one after another, so this implies
    ``member_loop``'s memory."""
    member_loop: bool = True
    """Compute the members' losses and gradients one member at a time (``lax.map``) instead of all at once
    (``vmap``): the same minibatches, crops and numbers up to float rounding, with about one member's
    working memory in a reward-training step instead of ``ensemble_size`` members' (not a SURF setting;
    BENCHMARKS.md, "Pixel runs before any GPU time"). The Adam step of all members stays one. The members'
    forward passes outside training (:func:`predict`: relabelling, scoring, a session's accuracy) go one
    member at a time too (:func:`over_members`), so that none of their convolutions is grouped over the
    members (since 2026-11-26; not timed on a GPU)."""
    session_loop: bool = True
    """Run a ``vmap`` of a feedback session (the trainer's over seeds and grid columns) as a loop over its columns
    (``pixel_train.loop_in_place``: a ``fori_loop`` writing each column back into the carried state), one column's
    session at a time: the same numbers up to float rounding (not a SURF setting). Batched, every convolution of
    the reward members (training, candidate scoring, relabelling) becomes one grouped convolution
    (``feature_group_count`` = columns), as DrQ-v2's update did under the seed ``vmap`` (``drqv2.seed_loop``: 6.8x
    slower batched in tf32 on one H100, BENCHMARKS.md); looped, each is a plain one, and the working memory holds
    one column's copy of its state (``sequential_vmap``, used before, held every column's). Rounds with a session
    of the 4-column PEBBLE + REBEL cheetah program took 55-150 s batched and 10-24 s looped
    (one H100, BENCHMARKS.md)."""

    def validate(self) -> None:
        for name in ("ensemble_size", "hidden", "depth", "batch_size", "max_epochs", "chunk", "relabel_rows"):
            _check(getattr(self, name) >= 1, f"pixel_reward.{name}", getattr(self, name), ">= 1")
        _check(self.lr > 0, "pixel_reward.lr", self.lr, "> 0")
        _check(0 <= self.stop_accuracy <= 1, "pixel_reward.stop_accuracy", self.stop_accuracy, "[0, 1]")
        precisions = ("tf32", "highest", "bf16")
        _check(self.precision in precisions, "pixel_reward.precision", self.precision, ", ".join(precisions))
        for name in ("member_loop", "session_loop", "per_member_adam"):
            _check(isinstance(getattr(self, name), bool), f"pixel_reward.{name}", getattr(self, name), "True, False")


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
    """Labelled pairs as copies of their segments (SURF keeps indices, ``buffer_seg*_index``,
    pixel_reward_model.py:200-203; see the module docstring): ``S`` agent steps per segment, whose
    ``S + stack - 1`` frames are stored once each (:func:`frame_replay.segment_frames`)."""

    frames_a: jax.Array
    """(C, S + stack - 1, H, W, 3) uint8 segment a's frames, oldest first."""
    action_a: jax.Array
    """(C, S, A) float32 its actions."""
    frames_b: jax.Array
    """(C, S + stack - 1, H, W, 3) uint8 segment b's frames."""
    action_b: jax.Array
    """(C, S, A) float32 its actions."""
    labels: jax.Array
    """(C,) ``P(seg_b preferred)``."""
    ptr: jax.Array
    count: jax.Array

    @property
    def capacity(self) -> int:
        """C, pairs (static)."""
        return self.labels.shape[0]


@flax.struct.dataclass
class PixelRewardState:
    """Members' parameters (leading member axis), one Adam state, the labels."""

    params: Any
    opt_state: Any
    data: PixelLabels
    pool: PixelLabels | None = None
    """SURF's unlabelled pairs (copies, as ``data``; ``labels`` unused), or None."""


@flax.struct.dataclass
class SegmentPlaces:
    """N segments of H steps in the replay: start row and environment each (queries while a session runs)."""

    row: jax.Array
    """(N,) int32 first row (taken modulo the replay's rows where read)."""
    env: jax.Array
    """(N,) int32 environment."""


@flax.struct.dataclass
class SegmentFrames:
    """Segments as data: ``S + stack - 1`` frames (stored once) and ``S`` actions each, any leading shape."""

    frames: jax.Array
    """(..., S + stack - 1, H, W, 3) uint8, oldest first."""
    action: jax.Array
    """(..., S, A)."""

    def stacks(self) -> jax.Array:
        """(..., S, H, W, 3 * stack) the observation stacks (:func:`frame_replay.segment_stacks`)."""
        stack = self.frames.shape[-4] - self.action.shape[-2] + 1
        return frame_replay.segment_stacks(self.frames, stack)


def network(cfg: PixelRewardConfig) -> PixelRewardNet:
    return PixelRewardNet(hidden=cfg.hidden, depth=cfg.depth, precision=cfg.precision)


def init(
    cfg: PixelRewardConfig,
    key: jax.Array,
    obs_shape: tuple[int, int, int],
    action_size: int,
    capacity: int,
    length: int,
) -> PixelRewardState:
    """Fresh members (one key each) and an empty store of ``capacity`` labelled pairs of ``length``-step
    segments (``obs_shape`` (H, W, 3 stack) sizes their frames)."""
    keys = jax.random.split(key, cfg.ensemble_size)
    obs, action = jnp.zeros((1, *obs_shape), jnp.uint8), jnp.zeros((1, action_size))
    params = jax.vmap(network(cfg).init, in_axes=(0, None, None))(keys, obs, action)
    data = empty_store(capacity, length, obs_shape, action_size)
    opt_state = member_adam_init(params) if cfg.per_member_adam else optax.adam(cfg.lr).init(params)
    return PixelRewardState(params=params, opt_state=opt_state, data=data)


@flax.struct.dataclass
class MemberAdamState:
    """One torch Adam over the members' parameters (leading member axis), each member's its own step count."""

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


def empty_store(capacity: int, length: int, obs_shape: tuple[int, int, int], action_size: int) -> PixelLabels:
    """An empty store of ``capacity`` pairs of ``length``-step segments of stacks ``obs_shape`` (H, W, 3 stack)."""
    height, width, channels = obs_shape
    frames = jnp.zeros((capacity, length + channels // 3 - 1, height, width, 3), jnp.uint8)
    action = jnp.zeros((capacity, length, action_size), jnp.float32)
    scalar = jnp.zeros((), jnp.int32)
    return PixelLabels(frames, action, frames, action, jnp.zeros((capacity,)), scalar, scalar)


def store_bytes(capacity: int, length: int, height: int, width: int, action_size: int, stack: int = 3) -> int:
    """Bytes of a store of ``capacity`` pairs (:func:`empty_store`): 200 pairs of 50 steps at 84x84 with 6
    actions, 440 MB; SURF's indices were 16 bytes a pair (pixel_reward_model.py:201-203)."""
    per_segment = (length + stack - 1) * frame_bytes(height, width) + length * action_size * 4
    return capacity * (2 * per_segment + 4) + 8


def over_members(cfg: PixelRewardConfig, fn: Callable, params: Any) -> jax.Array:
    """``fn(member_params)`` of every member of ``params`` (leading member axis), stacked: one member at a time
    (``lax.map``) with ``cfg.member_loop``, else all at once (``vmap``, whose convolutions are grouped over the
    members)."""
    return jax.lax.map(fn, params) if cfg.member_loop else jax.vmap(fn)(params)


def predict(cfg: PixelRewardConfig, params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """(M, ...) per-member rewards of stacks ``obs`` (..., H, W, C) and actions (..., A)."""
    return over_members(cfg, lambda member: network(cfg).apply(member, obs, action), params)


def mean_reward(cfg: PixelRewardConfig, params: Any, obs: jax.Array, action: jax.Array) -> jax.Array:
    """The ensemble mean, the reward the agent learns from (SURF's ``r_hat_batch``, pixel_reward_model.py:447-455)."""
    return jnp.mean(predict(cfg, params, obs, action), axis=0)


def segment_rows(start: jax.Array, horizon: int) -> jax.Array:
    """(..., H) rows of the segments starting at ``start`` (...), before the replay's modulo."""
    return start[..., None] + jnp.arange(horizon)


def gather_segments(buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int) -> SegmentFrames:
    """The frames and actions of ``horizon``-step segments at places ``seg`` (N,), copied from the replay
    (SURF's ``get_segment``, replay_buffer_drqv2.py:231-242: ``L + stack - 1`` frames, ``L`` actions)."""
    rows = segment_rows(seg.row, horizon) % buffer.rows
    frames = frame_replay.segment_frames(buffer, seg.row, seg.env, horizon)
    return SegmentFrames(frames=frames, action=buffer.action[rows, seg.env[:, None]])


def member_step_rewards(cfg: PixelRewardConfig, member_params: Any, seg: SegmentFrames) -> jax.Array:
    """(..., S) one member's learned rewards ``r(s_h, a_h)`` on segments (stacks rebuilt from their frames)."""
    return network(cfg).apply(member_params, seg.stacks(), seg.action)


def member_returns(cfg: PixelRewardConfig, member_params: Any, seg: SegmentFrames) -> jax.Array:
    """(...,) one member's learned returns ``sum_h r(s_h, a_h)`` of segments."""
    return jnp.sum(member_step_rewards(cfg, member_params, seg), axis=-1)


def _chunked_returns(cfg: PixelRewardConfig, params: Any, n: int, segments: Callable) -> jax.Array:
    """(M, n) every member's returns of ``n`` segments, ``segments(index (chunk,)) -> SegmentFrames`` giving
    ``cfg.chunk`` of them at a time (one chunk's frames and stacks in memory; padding repeats the last)."""
    chunks = -(-n // cfg.chunk)
    index = jnp.minimum(jnp.arange(chunks * cfg.chunk), n - 1).reshape(chunks, cfg.chunk)

    def one(part):
        seg = segments(part)
        return over_members(cfg, lambda member: member_returns(cfg, member, seg), params)

    returns = jax.lax.map(one, index)  # (chunks, M, chunk)
    return jnp.moveaxis(returns, 1, 0).reshape(cfg.ensemble_size, -1)[:, :n]


def ensemble_returns(
    cfg: PixelRewardConfig, params: Any, buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int
) -> jax.Array:
    """(M, N) every member's returns of segments at replay places, ``cfg.chunk`` segments gathered at a time."""

    def segments(index):
        return gather_segments(buffer, jax.tree.map(lambda x: x[index], seg), horizon)

    return _chunked_returns(cfg, params, seg.row.shape[0], segments)


def stored_side(data: PixelLabels, index: jax.Array) -> SegmentFrames:
    """Segments ``index`` of both sides of the store, side a first: ``i < C`` is pair ``i``'s a, else pair
    ``i - C``'s b (no concatenated copy of the store)."""
    c = data.capacity
    pair, first = index % c, (index < c)
    frames = jnp.where(first[:, None, None, None, None], data.frames_a[pair], data.frames_b[pair])
    action = jnp.where(first[:, None, None], data.action_a[pair], data.action_b[pair])
    return SegmentFrames(frames=frames, action=action)


def stored_returns(cfg: PixelRewardConfig, params: Any, data: PixelLabels) -> jax.Array:
    """(M, 2C) every member's returns of the stored segments, a sides then b sides, by chunks."""
    return _chunked_returns(cfg, params, 2 * data.capacity, lambda index: stored_side(data, index))


def place_rewards(cfg: PixelRewardConfig, params: Any, buffer: frame_replay.FrameBuffer, place, action) -> jax.Array:
    """(M, ...) members' rewards at replay places ``place`` (..., 2) = (row, env) with actions ``action`` (..., A):
    the ``predict_fn`` of REBEL's value term on pixels (the stacks are gathered here, not carried)."""
    obs = frame_replay.row_stacks(buffer, place[..., 0] % buffer.rows, place[..., 1])
    return predict(cfg, params, obs, action)


def frame_rewards(cfg: PixelRewardConfig, params: Any, frames: jax.Array, action: jax.Array) -> jax.Array:
    """(M, N, S) members' rewards on segments given as frames (N, S + stack - 1, H, W, 3) and actions
    (N, S, A): the ``predict_fn`` of REBEL's ``V*`` on the stored segments."""
    return predict(cfg, params, SegmentFrames(frames, action).stacks(), action)


def true_returns(buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int) -> jax.Array:
    """(N, H) the stored task rewards of the segments (what the teacher reads)."""
    rows = segment_rows(seg.row, horizon) % buffer.rows
    return buffer.true_reward[rows, seg.env[:, None]]


def sample_segments(
    key: jax.Array, buffer: frame_replay.FrameBuffer, n: int, horizon: int, episode_length: int, recent_episodes: int
) -> SegmentPlaces:
    """n segments uniform over the last ``recent_episodes`` complete episodes the replay holds, starts
    uniform in [0, L - H].

    The trainer's environments start their episodes together every ``L`` vector steps, so the newest row
    ``ptr - 1``'s agent step ``k`` places the episode ends: the last complete one ends ``(k + 1) mod L`` rows
    before the newest row's end, and the ``size`` rows the replay holds contain ``(size - (k + 1) mod L) // L``
    complete episodes per env (a ring that wrapped holds a part of its oldest episode; it is never drawn).
    Episodes rank by age ``b`` (oldest held first) then env ``e``; the last ``recent_episodes`` of the
    complete ones are eligible (SURF: the last ``reward_max_episodes``, pixel_reward_model.py:540-552) and
    the start takes any of the ``L - H + 1`` places (:547). Before the replay wraps, episode ``b`` is rows
    ``[b L, (b + 1) L)``.

    Args:
        key: PRNG key.
        buffer: a frame replay (a ring; rows are returned modulo its rows).
        n: segments (static).
        horizon: H (static).
        episode_length: agent steps L per episode (static).
        recent_episodes: eligible most recent complete episodes.

    Returns:
        :class:`SegmentPlaces` (n,).
    """
    key_episode, key_start = jax.random.split(key)
    num_envs, rows = buffer.num_envs, buffer.rows
    newest = (buffer.ptr - 1) % rows
    partial = (buffer.episode_step[newest] + 1) % episode_length  # rows of the running episode
    held = jnp.maximum(buffer.size - partial, 0) // episode_length  # complete episodes per env
    complete = held * num_envs
    low = jnp.maximum(complete - recent_episodes, 0)
    flat = jax.random.randint(key_episode, (n,), low, jnp.maximum(complete, 1))
    offset = jax.random.randint(key_start, (n,), 0, episode_length - horizon + 1)
    first = newest - partial - held * episode_length + 1  # first row of the oldest complete episode held
    row = (first + (flat // num_envs) * episode_length + offset) % rows
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
    pixel_reward_model.py:740-757). The first feedback session is uniform (pixel_train_PEBBLE.py:245-246): the
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
    state: PixelRewardState,
    buffer: frame_replay.FrameBuffer,
    seg_a: SegmentPlaces,
    seg_b: SegmentPlaces,
    labels: jax.Array,
    mask: jax.Array,
) -> PixelRewardState:
    """Appends the kept pairs (mask 1) at ``ptr``, their frames and actions copied from ``buffer`` (SURF's
    ``put_queries`` stores the places, pixel_reward_model.py:554-575)."""
    return state.replace(data=append_segments(state.data, buffer, seg_a, seg_b, labels, mask))


def append_segments(
    data: PixelLabels,
    buffer: frame_replay.FrameBuffer,
    seg_a: SegmentPlaces,
    seg_b: SegmentPlaces,
    labels: jax.Array,
    mask: jax.Array,
) -> PixelLabels:
    """``data`` with the pairs of mask 1 written at ``ptr`` onwards (wrapping), gathered from ``buffer``
    (``S`` steps each, the store's length). Pairs of mask 0 are gathered but dropped."""
    capacity, length = data.capacity, data.action_a.shape[1]
    keep = mask > 0
    slot = jnp.where(keep, (data.ptr + jnp.cumsum(keep.astype(jnp.int32)) - 1) % capacity, capacity)
    kept = jnp.sum(keep.astype(jnp.int32))
    new_a, new_b = gather_segments(buffer, seg_a, length), gather_segments(buffer, seg_b, length)

    def write(store, new):
        return store.at[slot].set(new.astype(store.dtype), mode="drop")

    return data.replace(
        frames_a=write(data.frames_a, new_a.frames),
        action_a=write(data.action_a, new_a.action),
        frames_b=write(data.frames_b, new_b.frames),
        action_b=write(data.action_b, new_b.action),
        labels=write(data.labels, labels),
        ptr=(data.ptr + kept) % capacity,
        count=jnp.minimum(data.count + kept, capacity),
    )


def member_step_pairs(
    cfg: PixelRewardConfig, params: Any, seg_a: SegmentFrames, seg_b: SegmentFrames
) -> tuple[jax.Array, jax.Array]:
    """(M, B, S) each member's per-step rewards on both segments of its own pairs (fields of ``seg_*`` lead (M, B))."""

    def one(member_params, a, b):
        return member_step_rewards(cfg, member_params, a), member_step_rewards(cfg, member_params, b)

    return jax.vmap(one)(params, seg_a, seg_b)


def bt_loss(
    cfg: PixelRewardConfig,
    params: Any,
    seg_a: SegmentFrames,
    seg_b: SegmentFrames,
    labels: jax.Array,
    weight: jax.Array,
    crop: int = 0,
    key: jax.Array | None = None,
    members: jax.Array | None = None,
) -> tuple[jax.Array, dict]:
    """The BT term: the sum over members of each member's weighted mean cross-entropy on its pairs.

    With ``crop > 0`` (SURF) the segments are ``S = H + 2 crop`` long and each member sums its
    rewards over fresh random crops (:func:`rebel_jax.surf.crop_masks`, drawn from ``key``), SURF's
    ``get_cropping_mask`` (pixel_reward_model.py:822-833, applied at :901-904).

    SURF's ``CrossEntropyLoss(r_hat, labels)`` over ``[G(a), G(b)]`` per member (pixel_reward_model.py:908-911),
    summed over members (SURF steps them one after another).

    Args:
        params: the parameters of M members (leading axis): the whole ensemble, or one member of it
            (``pixel_reward.member_loop``).
        seg_a, seg_b: each member's segments, fields leading (M, B).
        labels, weight: (M, B) each member's pairs' labels and weights.
        members: (M,) int32 the ensemble indices of ``params``' members; None: all ``ensemble_size``.
            Every draw from ``key`` is made for the whole ensemble and these members' rows are kept, so a
            member's crops do not depend on which other members are computed with it.

    Returns:
        The loss and ``{"bt_loss", "bt_accuracy", "logits", "rewards_a", "rewards_b", "weight", "members"}``:
        the members' per-step rewards on their pairs (M, B, S), uncropped, and the pairs' weights, which
        REBEL's ``rebel.normalize`` reads (:func:`rebel_jax.agent_preference.reward_spread`), and
        ``members``, which SURF's pseudo-label term reads.
    """
    members = jnp.arange(cfg.ensemble_size) if members is None else members
    rewards_a, rewards_b = member_step_pairs(cfg, params, seg_a, seg_b)
    if crop:
        length = rewards_a.shape[-1]
        mask_a, mask_b = surf.crop_masks(key, (cfg.ensemble_size, labels.shape[1]), length, crop)
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
    key: jax.Array,
    terms: Sequence[Callable] = (),
    crop: int = 0,
) -> tuple[PixelRewardState, dict]:
    """One epoch: per-member permutations of the stored labels in minibatches of ``batch_size``, each
    minibatch's segments read from the label store's copies (SURF gathers them from its replay, :856-859).

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
        loss, metrics = bt_loss(cfg, params, seg_a, seg_b, labels, weight, crop, key_crop, members)
        for i, term in enumerate(terms):
            term_loss, _ = term(params, metrics, jax.random.fold_in(key_terms, i))
            loss = loss + term_loss
        return loss, dict(metrics, loss=loss)

    grad_fn = jax.grad(loss_fn, has_aux=True)

    def member_grad(m, params, seg_a, seg_b, labels, weight, step_key):
        """Member ``m``'s gradient (no member axis), its (B,) logits and its loss, computed from its rows alone."""
        mine = jax.tree.map(lambda x: jax.lax.dynamic_slice_in_dim(x, m, 1), (params, seg_a, seg_b, labels, weight))
        grads, metrics = grad_fn(*mine, step_key, m[None])
        return jax.tree.map(lambda g: g[0], grads), metrics["logits"][0], metrics["loss"]

    def ensemble_grads(params, seg_a, seg_b, labels, weight, step_key):
        """Every member's gradient, the (M, B) logits and the loss summed over the members."""
        if not cfg.member_loop:
            grads, metrics = grad_fn(params, seg_a, seg_b, labels, weight, step_key, None)
            return grads, metrics["logits"], metrics["loss"]
        batch = (params, seg_a, seg_b, labels, weight, step_key)
        grads, logits, losses = jax.lax.map(lambda m: member_grad(m, *batch), jnp.arange(cfg.ensemble_size))
        return grads, logits, jnp.sum(losses)

    def member_steps(params, opt_state, seg_a, seg_b, labels, weight, step_key):
        """``per_member_adam``: member after member (pixel_reward_model_semi.py:182-304), its gradient at the
        parameters the steps before it left, then one Adam step of all members; the (M, B) logits each right
        before its member's step, and the loss summed over the members."""

        def one(m, carry):
            params, opt_state, logits, loss = carry
            grad, member_logits, member_loss = member_grad(m, params, seg_a, seg_b, labels, weight, step_key)
            params, opt_state = member_adam_step(cfg.lr, opt_state, params, grad, m)
            return params, opt_state, logits.at[m].set(member_logits), loss + member_loss

        start = (params, opt_state, jnp.zeros(labels.shape, jnp.float32), jnp.zeros(()))
        return jax.lax.fori_loop(0, cfg.ensemble_size, one, start)

    def body(carry: _Carry) -> _Carry:
        start = carry.step * b
        slots = jax.lax.dynamic_slice(order, (0, start), (cfg.ensemble_size, b))
        weight = jnp.broadcast_to(((start + jnp.arange(b)) < data.count).astype(jnp.float32), slots.shape)
        seg_a = SegmentFrames(data.frames_a[slots], data.action_a[slots])  # (M, B, S + stack - 1, H, W, 3)
        seg_b = SegmentFrames(data.frames_b[slots], data.action_b[slots])
        labels = data.labels[slots]
        step_key = jax.random.fold_in(key_terms, carry.step)
        if cfg.per_member_adam:
            params, opt_state, logits, loss = member_steps(
                carry.params, carry.opt_state, seg_a, seg_b, labels, weight, step_key
            )
        else:
            grads, logits, loss = ensemble_grads(carry.params, seg_a, seg_b, labels, weight, step_key)
            updates, opt_state = optimizer.update(grads, carry.opt_state, carry.params)
            params = optax.apply_updates(carry.params, updates)
        correct = ((logits > 0) == (labels > 0.5)) & (labels != 0.5)
        return _Carry(
            params=params,
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
    key: jax.Array,
    terms: Sequence[Callable] = (),
    crop: int = 0,
    max_epochs: int | jax.Array | None = None,
    stop_accuracy: float | None = None,
) -> tuple[PixelRewardState, dict]:
    """A session: epochs (``fold_in(key, e)``) until ``max_epochs`` (may be traced) or accuracy >
    ``stop_accuracy`` (pixel_train_PEBBLE.py:267-278); nothing while no label is stored.

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
        st, metrics = train_epoch(cfg, st, jax.random.fold_in(key, epoch), terms, crop)
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


def pseudo_label_term(cfg: PixelRewardConfig, surf_cfg: surf.SURFConfig, pool: PixelLabels) -> Callable:
    """SURF's pseudo-label term on the unlabelled pool (copies of ``H + 2 crop``-step segments, as the label
    store), as :func:`rebel_jax.surf.pseudo_label_term`.

    Each step every member draws ``surf.ratio x batch_size`` pool pairs (SURF's ``mu``, 1 in its pixel
    config, cfgs/config_pebble_semi.yaml:67), labels them from its own sums over the central ``H``
    steps without gradient, and is trained on fresh crops with weight ``surf.weight`` (``lambda_u``)
    on the pairs at or above ``surf.threshold`` (pixel_reward_model_semi.py:291-301).

    Returns:
        ``(params, batch, key) -> (loss, metrics)``, ``batch`` the BT term's metrics: its ``members`` name
        the ensemble members of ``params`` (all of them, or one with ``pixel_reward.member_loop``).
    """
    c, horizon = surf_cfg.crop, pool.action_a.shape[1]
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
            reward_a = member_step_rewards(cfg, member_params, SegmentFrames(pool.frames_a[idx], pool.action_a[idx]))
            reward_b = member_step_rewards(cfg, member_params, SegmentFrames(pool.frames_b[idx], pool.action_b[idx]))
            logits = jnp.sum(reward_b * m_b, -1) - jnp.sum(reward_a * m_a, -1)
            central_logits = jnp.sum(reward_b[:, central], -1) - jnp.sum(reward_a[:, central], -1)
            return logits, jax.lax.stop_gradient(central_logits)

        logits, central_logits = jax.vmap(one)(params, index, mask_a, mask_b)
        labels, confident = surf.pseudo_labels(central_logits, surf_cfg.threshold)
        per_member = jnp.mean(reward_model.bt_cross_entropy(logits, labels) * confident, axis=1)
        loss = surf_cfg.weight * jnp.sum(per_member)
        return loss, {"pseudo_loss": loss, "pseudo_fraction": jnp.mean(confident)}

    return loss_fn
