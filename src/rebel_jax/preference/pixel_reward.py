"""The pixel reward network of SURF's pixel branch and its segments of the frame replay.

The ensemble, its label store, the Bradley-Terry loss and the training loops are
:mod:`rebel_jax.preference.reward_model`'s
and :mod:`rebel_jax.preference.reward_train`'s, shared with state tasks; this module holds what frames add: the network
(:class:`PixelRewardNet`, :class:`PixelRewardConfig`), the segments as stored frames (:class:`SegmentFrames`) or
as replay places (:class:`SegmentPlaces`), and their gathering, scoring and sampling.

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
  *copies* instead (a :class:`rebel_jax.preference.reward_model.PairStore` of :class:`SegmentFrames`): each labelled
  segment's ``L + stack - 1`` frames, each stored once as uint8 as in the frame replay, and its ``L`` actions,
  gathered from the replay when the label is added.
  The frames are those SURF would gather at every use, so the replay may be a ring of recent transitions
  (:mod:`rebel_jax.train`). SURF's unlabelled pool (``u_buffer_seg*_index``, pixel_reward_model_semi.py:69-74) is
  kept the same way.
- A session trains ``reward_update`` epochs (README: 20) of minibatches of 16 pairs
  (``train_batch_size = 16``, pixel_reward_model.py:214), each member its own permutation (:816-820,
  :855), stopping once the members' mean epoch accuracy exceeds 0.97 (pixel_train_PEBBLE.py:269-278).
  The accuracy counts each minibatch's predictions before its step (:909-919).
- The BT loss is PyTorch's ``CrossEntropyLoss`` on ``[G(a), G(b)]`` with hard labels (:908-911), the
  Bradley-Terry cross-entropy of :func:`rebel_jax.preference.reward_model.bt_cross_entropy`.

Deviations (documented where they are made): by default one Adam step on the *sum* of the members' losses where
SURF steps its one Adam once per member (:851-913: zero gradients for the other members, whose Adam
moments still move them; ``per_member_adam`` does SURF's); the candidates of disagreement sampling are scored a
chunk of pairs at a time.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

import flax.linen as nn
import flax.struct
import jax
import jax.numpy as jnp

from rebel_jax.agents import frame_replay
from rebel_jax.agents.networks import Encoder, dense_kwargs, orthogonal
from rebel_jax.core.errors import check as _check
from rebel_jax.preference import queries, reward_model


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
    BENCHMARKS.md, "A pixel session by parts")."""
    precision: str = "tf32"
    """Matmul and convolution precision: ``tf32``, ``highest`` or ``bf16``."""
    per_member_adam: bool = False
    """SURF's Adam stepping (pixel_reward_model_semi.py:182-304, pixel_reward_model.py:851-913, torch 1.9.0 per
    its README): one Adam over all members, and per minibatch, member after member, ``zero_grad``, that member's
    backward and a step. ``zero_grad`` leaves zeros (not None) in torch 1.9, so every step also moves the other
    members by their moments alone and advances their step counts (``reward_model.MemberAdamState``). Off (default):
    one standard Adam step of all members on the sum of their losses, as B-Pref's state reward model
    (reward_model.py) and every pixel run so far. The member steps run one after another, so this implies
    ``member_loop``'s memory."""
    member_loop: bool = True
    """Compute the members' losses and gradients one member at a time (``lax.map``) instead of all at once
    (``vmap``): the same minibatches, crops and numbers up to float rounding, with about one member's
    working memory in a reward-training step instead of ``ensemble_size`` members' (not a SURF setting;
    ``benchmarks/pixel_memory.py``, CPU estimates). The Adam step of all members stays one. The members'
    forward passes outside training (``reward_model.predict``: relabelling, scoring, a session's accuracy) go
    one member at a time too (``reward_model.over_members``), so that none of their convolutions is grouped over the
    members (since 2026-11-26; not timed on a GPU)."""
    session_loop: bool = True
    """Run a ``vmap`` of a feedback session (the trainer's over seeds and grid columns) as a loop over its columns
    (``pixel_feedback.loop_in_place``: a ``fori_loop`` writing each column back into the carried state), one column's
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

    def network(self) -> PixelRewardNet:
        """One member's flax module."""
        return PixelRewardNet(hidden=self.hidden, depth=self.depth, precision=self.precision)


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

    def inputs(self) -> tuple[jax.Array, jax.Array]:
        """The network's inputs per step: ``(stacks(), action)``."""
        return self.stacks(), self.action


def init(
    cfg: PixelRewardConfig,
    key: jax.Array,
    obs_shape: tuple[int, int, int],
    action_size: int,
    capacity: int,
    length: int,
    optimizer=None,
) -> reward_model.RewardState:
    """Fresh members (one key each) and an empty store of ``capacity`` labelled pairs of ``length``-step
    segments (``obs_shape`` (H, W, 3 stack) sizes their frames); ``optimizer`` as ``reward_model.new_state``'s."""
    obs, action = jnp.zeros((1, *obs_shape), jnp.uint8), jnp.zeros((1, action_size))
    params = reward_model.init_params(cfg, key, obs, action)
    store = empty_store(capacity, length, obs_shape, action_size)
    return reward_model.new_state(cfg, params, store, optimizer=optimizer)


def empty_store(
    capacity: int, length: int, obs_shape: tuple[int, int, int], action_size: int
) -> reward_model.PairStore:
    """An empty store of ``capacity`` pairs of ``length``-step segments of stacks ``obs_shape`` (H, W, 3 stack):
    each segment's ``length + stack - 1`` frames (uint8) and ``length`` actions."""
    height, width, channels = obs_shape
    frames = jnp.zeros((length + channels // 3 - 1, height, width, 3), jnp.uint8)
    return reward_model.empty_store(SegmentFrames(frames, jnp.zeros((length, action_size), jnp.float32)), capacity)


def store_bytes(capacity: int, length: int, height: int, width: int, action_size: int, stack: int = 3) -> int:
    """Bytes of a store of ``capacity`` pairs (:func:`empty_store`): 200 pairs of 50 steps at 84x84 with 6
    actions, 440 MB; SURF's indices were 16 bytes a pair (pixel_reward_model.py:201-203)."""
    per_segment = (length + stack - 1) * frame_bytes(height, width) + length * action_size * 4
    return capacity * (2 * per_segment + 4) + 8


def segment_rows(start: jax.Array, horizon: int) -> jax.Array:
    """(..., H) rows of the segments starting at ``start`` (...), before the replay's modulo."""
    return start[..., None] + jnp.arange(horizon)


def gather_segments(buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int) -> SegmentFrames:
    """The frames and actions of ``horizon``-step segments at places ``seg`` (N,), copied from the replay
    (SURF's ``get_segment``, replay_buffer_drqv2.py:231-242: ``L + stack - 1`` frames, ``L`` actions)."""
    rows = segment_rows(seg.row, horizon) % buffer.rows
    frames = frame_replay.segment_frames(buffer, seg.row, seg.env, horizon)
    return SegmentFrames(frames=frames, action=buffer.action[rows, seg.env[:, None]])


def member_returns(cfg: PixelRewardConfig, member_params: Any, seg: SegmentFrames) -> jax.Array:
    """(...,) one member's learned returns ``sum_h r(s_h, a_h)`` of segments."""
    return jnp.sum(reward_model.step_rewards(cfg, member_params, seg), axis=-1)


def _chunked_returns(cfg: PixelRewardConfig, params: Any, n: int, segments: Callable) -> jax.Array:
    """(M, n) every member's returns of ``n`` segments, ``segments(index (chunk,)) -> SegmentFrames`` giving
    ``cfg.chunk`` of them at a time (one chunk's frames and stacks in memory; padding repeats the last)."""
    chunks = -(-n // cfg.chunk)
    index = jnp.minimum(jnp.arange(chunks * cfg.chunk), n - 1).reshape(chunks, cfg.chunk)

    def one(part):
        seg = segments(part)
        return reward_model.over_members(cfg, lambda member: member_returns(cfg, member, seg), params)

    returns = jax.lax.map(one, index)  # (chunks, M, chunk)
    return jnp.moveaxis(returns, 1, 0).reshape(cfg.ensemble_size, -1)[:, :n]


def ensemble_returns(
    cfg: PixelRewardConfig, params: Any, buffer: frame_replay.FrameBuffer, seg: SegmentPlaces, horizon: int
) -> jax.Array:
    """(M, N) every member's returns of segments at replay places, ``cfg.chunk`` segments gathered at a time."""

    def segments(index):
        return gather_segments(buffer, jax.tree.map(lambda x: x[index], seg), horizon)

    return _chunked_returns(cfg, params, seg.row.shape[0], segments)


def stored_side(data: reward_model.PairStore, index: jax.Array) -> SegmentFrames:
    """Segments ``index`` of both sides of the store, side a first: ``i < C`` is pair ``i``'s a, else pair
    ``i - C``'s b (no concatenated copy of the store)."""
    c = data.capacity
    pair, first = index % c, (index < c)
    frames = jnp.where(first[:, None, None, None, None], data.a.frames[pair], data.b.frames[pair])
    action = jnp.where(first[:, None, None], data.a.action[pair], data.b.action[pair])
    return SegmentFrames(frames=frames, action=action)


def stored_returns(cfg: PixelRewardConfig, params: Any, data: reward_model.PairStore) -> jax.Array:
    """(M, 2C) every member's returns of the stored segments, a sides then b sides, by chunks."""
    return _chunked_returns(cfg, params, 2 * data.capacity, lambda index: stored_side(data, index))


def place_rewards(cfg: PixelRewardConfig, params: Any, buffer: frame_replay.FrameBuffer, place, action) -> jax.Array:
    """(M, ...) members' rewards at replay places ``place`` (..., 2) = (row, env) with actions ``action`` (..., A):
    the ``predict_fn`` of REBEL's value term on pixels (the stacks are gathered here, not carried)."""
    obs = frame_replay.row_stacks(buffer, place[..., 0] % buffer.rows, place[..., 1])
    return reward_model.predict(cfg, params, obs, action)


def frame_rewards(cfg: PixelRewardConfig, params: Any, frames: jax.Array, action: jax.Array) -> jax.Array:
    """(M, N, S) members' rewards on segments given as frames (N, S + stack - 1, H, W, 3) and actions
    (N, S, A): the ``predict_fn`` of REBEL's ``V*`` on the stored segments."""
    return reward_model.predict(cfg, params, SegmentFrames(frames, action).stacks(), action)


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
    state: reward_model.RewardState,
    buffer: frame_replay.FrameBuffer,
    seg_a: SegmentPlaces,
    seg_b: SegmentPlaces,
    labels: jax.Array,
    mask: jax.Array,
) -> reward_model.RewardState:
    """Appends the kept pairs (mask 1) at ``ptr``, their frames and actions copied from ``buffer`` (SURF's
    ``put_queries`` stores the places, pixel_reward_model.py:554-575)."""
    return state.replace(data=append_segments(state.data, buffer, seg_a, seg_b, labels, mask))


def append_segments(
    data: reward_model.PairStore,
    buffer: frame_replay.FrameBuffer,
    seg_a: SegmentPlaces,
    seg_b: SegmentPlaces,
    labels: jax.Array,
    mask: jax.Array,
) -> reward_model.PairStore:
    """``data`` with the pairs of mask 1 written at ``ptr`` onwards (wrapping), gathered from ``buffer``
    (``S`` steps each, the store's length). Pairs of mask 0 are gathered but dropped."""
    length = data.a.action.shape[1]
    new_a, new_b = gather_segments(buffer, seg_a, length), gather_segments(buffer, seg_b, length)
    return reward_model.write_pairs(data, new_a, new_b, labels, mask)


def candidate_bytes(num_pairs: int, horizon: int, height: int, width: int, stack: int = 3) -> int:
    """uint8 bytes of ``num_pairs`` pairs' frame stacks if gathered at once (what scoring by chunks avoids):
    ``2 x pairs x H x height x width x 3 stack``; 10 x 10 candidates of 50 steps at 84x84: 635 MB."""
    return 2 * num_pairs * horizon * height * width * 3 * stack


def frame_bytes(height: int, width: int) -> int:
    """One stored RGB frame."""
    return height * width * 3
