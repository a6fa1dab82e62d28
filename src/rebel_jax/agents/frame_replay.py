"""Device-resident replay of pixel transitions that stores each frame once, as a pytree.

A frame-stack observation of ``stack`` frames would store every frame ``stack`` times, and twice
more as ``next_obs``; this buffer keeps a ring of single frames and rebuilds stacks and n-step
transitions when sampling, as SURF's pixel branch does with its episodes (alinlab/SURF 214bc1d,
branch ``pixel``, replay_buffer_drqv2.py:191-214: frames ``max(idx - stack, 0) .. idx`` padded with
the episode's first frame; DrQ-v2's ``nstep`` reward loop, facebookresearch/drqv2 c0c650b
replay_buffer.py:150-160).

Layout:

- ``frames`` (F, E, H, W, 3) uint8: a ring of frame rows. Each vector step writes the new frame of
  every environment (the newest frame of ``next_obs``); a step that starts an episode first writes
  the reset frame (the newest frame of ``obs``). ``F = T + ceil(T / episode_length) + stack + 1``
  keeps every frame a stored transition refers to.
- transition fields (T, E, ...) time-major as :mod:`rebel_jax.agents.replay`; ``frame_index`` (T,) is the
  frame row of each row's ``obs`` newest frame and ``episode_step`` (T,) its agent step in the
  episode. Both are per row: the trainer's environments start their episodes together
  (docs/ARCHITECTURE.md, "Episode-synchronous environments"), which this buffer requires.

Row ``t``'s stack is frame rows ``frame_index[t] - min(j, episode_step[t])`` for ``j = stack-1 .. 0``
(oldest first; the clamp repeats the reset frame, as the environment's stack does after a reset).
An n-step transition from row ``t`` uses rows ``t .. t+n-1`` of one episode (DrQ-v2 samples only
such windows, replay_buffer.py:150) and the stack ``n`` frames later.

It keeps :mod:`rebel_jax.agents.replay`'s contract (the field names, ``true_reward`` and ``learned_reward`` apart, and
``init``, ``add``, ``sample``, ``relabel``); ``learned_reward`` is None on a run that learns no reward (DrQ-v2).
"""

from __future__ import annotations

import math

import flax.struct
import jax
import jax.numpy as jnp

from rebel_jax.agents.drqv2 import PixelTransition, nstep_return


@flax.struct.dataclass
class FrameStep:
    """One vector step of E pixel environments.

    Attributes:
        obs: (E, H, W, 3 * stack) uint8 frame stacks before the action (oldest frame first).
        action: (E, action_size).
        next_obs: (E, H, W, 3 * stack) uint8 stacks after the action (before any reset).
        true_reward: (E,) the task's reward.
        terminal: (E,) 1.0 where the episode terminated at ``next_obs``.
        truncated: (E,) 1.0 where the time limit cut the episode at ``next_obs``.
        episode_step: () int32 agent step of ``obs`` in its episode, the same for every environment;
            0 starts an episode (the first step added must be 0).
        learned_reward: (E,) the reward model's reward (a buffer made with ``learned_reward=True``), else None.
    """

    obs: jax.Array
    action: jax.Array
    next_obs: jax.Array
    true_reward: jax.Array
    terminal: jax.Array
    truncated: jax.Array
    episode_step: jax.Array
    learned_reward: jax.Array | None = None


@flax.struct.dataclass
class FrameBuffer:
    """Frame ring and transition rows; see the module docstring.

    Attributes:
        frames: (F, E, H, W, 3) uint8 single frames.
        frame_index: (T,) int32 frame row of each row's ``obs`` newest frame.
        episode_step: (T,) int32 agent step of each row's ``obs`` in its episode.
        action: (T, E, action_size) float32.
        learned_reward: (T, E) float32 the reward model's reward (preference runs), or None.
        terminal, truncated: (T, E) float 0/1.
        ptr: () int32 next transition row; size: () rows filled (at most T).
        frame_ptr: () int32 next frame row.
        true_reward: (T, E) float32 the task's reward.
        stack: frames per observation (static).
    """

    frames: jax.Array
    frame_index: jax.Array
    episode_step: jax.Array
    action: jax.Array
    learned_reward: jax.Array | None
    terminal: jax.Array
    truncated: jax.Array
    ptr: jax.Array
    size: jax.Array
    frame_ptr: jax.Array
    true_reward: jax.Array
    stack: int = flax.struct.field(pytree_node=False, default=3)

    @property
    def rows(self) -> int:
        """T, transition rows (static)."""
        return self.true_reward.shape[0]

    @property
    def num_envs(self) -> int:
        """E (static)."""
        return self.true_reward.shape[1]

    @property
    def frame_rows(self) -> int:
        """F, frame rows (static)."""
        return self.frames.shape[0]


def frame_rows(rows: int, episode_length: int, stack: int) -> int:
    """F: one frame per row, a reset frame per episode start the rows can hold, the stack's look-back, one spare."""
    return rows + math.ceil(rows / episode_length) + stack + 1


def init(
    capacity: int,
    num_envs: int,
    frame_shape: tuple[int, int, int],
    action_size: int,
    episode_length: int,
    stack: int = 3,
    learned_reward: bool = False,
) -> FrameBuffer:
    """An empty buffer of ``capacity // num_envs`` transition rows.

    Args:
        capacity: transitions to hold (rounded down to a multiple of ``num_envs``).
        num_envs: environments per row.
        frame_shape: (H, W, 3) of one frame.
        action_size: action dimension.
        episode_length: agent steps per episode (sizes the reset frames; shorter episodes need more).
        stack: frames per observation.
        learned_reward: also keep a learned reward beside the task's (a preference run).

    Returns:
        A zero-filled :class:`FrameBuffer`.
    """
    if num_envs < 1 or capacity < num_envs or episode_length < 1 or stack < 1:
        raise ValueError(
            f"need 1 <= num_envs <= capacity, episode_length >= 1, stack >= 1; got {num_envs}, {capacity}, "
            f"{episode_length}, {stack}"
        )
    rows = capacity // num_envs
    return FrameBuffer(
        frames=jnp.zeros((frame_rows(rows, episode_length, stack), num_envs, *frame_shape), jnp.uint8),
        frame_index=jnp.zeros((rows,), jnp.int32),
        episode_step=jnp.zeros((rows,), jnp.int32),
        action=jnp.zeros((rows, num_envs, action_size), jnp.float32),
        learned_reward=jnp.zeros((rows, num_envs), jnp.float32) if learned_reward else None,
        terminal=jnp.zeros((rows, num_envs), jnp.float32),
        truncated=jnp.zeros((rows, num_envs), jnp.float32),
        ptr=jnp.zeros((), jnp.int32),
        size=jnp.zeros((), jnp.int32),
        frame_ptr=jnp.zeros((), jnp.int32),
        true_reward=jnp.zeros((rows, num_envs), jnp.float32),
        stack=stack,
    )


def nbytes(buffer: FrameBuffer) -> int:
    """Device bytes of the buffer (all its arrays)."""
    return sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(buffer))


def add(buffer: FrameBuffer, step: FrameStep) -> FrameBuffer:
    """Write one row: the reset frame if the step starts an episode, the new frames, the transition.

    Both frame writes are unconditional (no ``lax.cond``, which under ``vmap`` would copy the
    buffer): the reset frame goes to ``frame_ptr`` and the new frame to ``frame_ptr + first``, so
    outside an episode start the new frame overwrites the first write.

    Args:
        buffer: the buffer.
        step: a :class:`FrameStep`.

    Returns:
        The buffer with the row written and the rings advanced.
    """
    first = (step.episode_step == 0).astype(jnp.int32)
    f = buffer.frame_rows
    frames = jax.lax.dynamic_update_index_in_dim(buffer.frames, step.obs[..., -3:], buffer.frame_ptr, axis=0)
    frames = jax.lax.dynamic_update_index_in_dim(frames, step.next_obs[..., -3:], (buffer.frame_ptr + first) % f, 0)
    # The obs' newest frame: the reset frame just written, or the previous step's new frame.
    index = (buffer.frame_ptr + first - 1) % f

    def write(field: jax.Array, value) -> jax.Array:
        value = jnp.asarray(value).astype(field.dtype)
        return jax.lax.dynamic_update_index_in_dim(field, value, buffer.ptr, axis=0)

    return buffer.replace(
        frames=frames,
        frame_index=write(buffer.frame_index, index),
        episode_step=write(buffer.episode_step, step.episode_step),
        action=write(buffer.action, step.action),
        learned_reward=None if buffer.learned_reward is None else write(buffer.learned_reward, step.learned_reward),
        terminal=write(buffer.terminal, step.terminal),
        truncated=write(buffer.truncated, step.truncated),
        true_reward=write(buffer.true_reward, step.true_reward),
        ptr=(buffer.ptr + 1) % buffer.rows,
        size=jnp.minimum(buffer.size + 1, buffer.rows),
        frame_ptr=(buffer.frame_ptr + first + 1) % f,
    )


def valid_rows(buffer: FrameBuffer, nstep: int) -> jax.Array:
    """(T,) bool: rows that start an n-step window of written rows within one episode.

    Row ``t`` is valid when it is filled, the ``nstep - 1`` rows after it are written after it (not
    stale rows of the previous lap) and belong to its episode (their agent step counts on).
    """
    t = jnp.arange(buffer.rows)
    end = (t + nstep - 1) % buffer.rows
    written = t < buffer.size
    complete = (buffer.ptr - 1 - t) % buffer.rows >= nstep - 1
    same_episode = buffer.episode_step[end] == buffer.episode_step + nstep - 1
    return written & complete & same_episode


def stack_rows(newest: jax.Array, episode_step: jax.Array, stack: int) -> jax.Array:
    """(..., stack) frame rows of the stacks whose newest frame is row ``newest`` (...), ``episode_step``
    agent steps after the reset (oldest first; clamped to the reset frame, as the environment's stack is)."""
    back = jnp.arange(stack - 1, -1, -1)
    return newest[..., None] - jnp.minimum(back, episode_step[..., None])


def channel_stack(frames: jax.Array) -> jax.Array:
    """(..., stack, H, W, 3) frames -> (..., H, W, 3 * stack) stacks, oldest frame's channels first."""
    frames = jnp.moveaxis(frames, -4, -2)  # (..., H, W, stack, 3)
    return frames.reshape(*frames.shape[:-2], -1)


def _stacks(buffer: FrameBuffer, newest: jax.Array, episode_step: jax.Array, env: jax.Array) -> jax.Array:
    """(B, H, W, 3 * stack) stacks whose newest frame is row ``newest``, ``episode_step`` frames after the reset."""
    rows = stack_rows(newest, episode_step, buffer.stack) % buffer.frame_rows
    return channel_stack(buffer.frames[rows, env[:, None]])  # frames (B, stack, H, W, 3)


def episode_stacks(frames: jax.Array, stack: int) -> jax.Array:
    """The observation stacks of episodes kept as their newest frames from the reset on.

    Args:
        frames: (N, T, H, W, 3) uint8, frame h the newest frame of the observation at agent step h
            (frame 0 the reset frame), as REBEL's on-policy store keeps them (``pixel_feedback``).
        stack: frames per observation.

    Returns:
        (N, T, H, W, 3 * stack) stacks, as the environment built them (the reset frame repeated at first).
    """
    steps = jnp.arange(frames.shape[1])
    rows = stack_rows(steps, steps, stack)  # (T, stack)
    return channel_stack(frames[:, rows])


def gather(
    buffer: FrameBuffer, row: jax.Array, env: jax.Array, nstep: int, gamma: float, learned_reward: bool = True
) -> PixelTransition:
    """The n-step transitions starting at (``row``, ``env``), each a valid row (:func:`valid_rows`).

    Args:
        buffer: the buffer.
        row, env: (B,) int indices.
        nstep: steps of the return.
        gamma: discount per step.
        learned_reward: the n-step return of ``learned_reward`` (True) or of ``true_reward`` (False).

    Returns:
        A :class:`~rebel_jax.agents.drqv2.PixelTransition`: stacks at ``row`` and ``nstep`` rows later, the
        first action, DrQ-v2's n-step reward sum and bootstrap discount (``1 - terminal`` per step).
    """
    k, newest = buffer.episode_step[row], buffer.frame_index[row]
    window = (row[:, None] + jnp.arange(nstep)[None]) % buffer.rows
    stored = buffer.learned_reward if learned_reward else buffer.true_reward
    rewards, terminals = stored[window, env[:, None]], buffer.terminal[window, env[:, None]]
    reward, discount = nstep_return(rewards, 1.0 - terminals, gamma)
    return PixelTransition(
        obs=_stacks(buffer, newest, k, env),
        action=buffer.action[row, env],
        reward=reward,
        discount=discount,
        next_obs=_stacks(buffer, newest + nstep, k + nstep, env),
    )


def sample(
    buffer: FrameBuffer, key: jax.Array, batch_size: int, learned_reward: bool, nstep: int, gamma: float
) -> PixelTransition:
    """Uniform sample, with replacement, over the valid (row, env) pairs (DrQ-v2 samples a stored
    episode, then a start in it; with equal-length episodes that is uniform over starts too).

    Args:
        buffer: a buffer with at least one valid row.
        key: PRNG key.
        batch_size: transitions to draw.
        learned_reward, nstep, gamma: as :func:`gather`.

    Returns:
        A :class:`~rebel_jax.agents.drqv2.PixelTransition` batch.
    """
    key_row, key_env = jax.random.split(key)
    row, _ = _draw_valid(key_row, valid_rows(buffer, nstep), batch_size)
    env = jax.random.randint(key_env, (batch_size,), 0, buffer.num_envs)
    return gather(buffer, row, env, nstep, gamma, learned_reward)


def _draw_valid(key: jax.Array, valid: jax.Array, n: int) -> tuple[jax.Array, jax.Array]:
    """n rows uniform over the rows where ``valid`` (T,) holds; and () whether any row is valid."""
    cumulative = jnp.cumsum(valid.astype(jnp.int32))
    draw = jax.random.randint(key, (n,), 0, jnp.maximum(cumulative[-1], 1))
    row = jnp.searchsorted(cumulative, draw, side="right").astype(jnp.int32)  # the (draw+1)-th valid row
    return jnp.minimum(row, valid.shape[0] - 1), cumulative[-1] > 0


def sample_recent(
    buffer: FrameBuffer, key: jax.Array, batch_size: int, nstep: int, gamma: float, recent: jax.Array, window
) -> PixelTransition:
    """:func:`sample` with the learned reward, except that the batch positions where ``recent`` holds are drawn
    from the valid rows among the newest ``window`` (from all valid rows while none of those is: the newest
    ``nstep - 1`` rows start no complete window). A hybrid batch, as QPA's (huxiao09/QPA@7e9e49e:agent/sac.py:274-285).

    Args:
        recent: (batch_size,) bool, the positions drawn from the newest rows.
        window: () int, how many of the newest rows.
    """
    key_row, key_recent, key_env = jax.random.split(key, 3)
    valid = valid_rows(buffer, nstep)
    age = (buffer.ptr - 1 - jnp.arange(buffer.rows)) % buffer.rows  # 0: the newest row
    row, _ = _draw_valid(key_row, valid, batch_size)
    newest, any_newest = _draw_valid(key_recent, valid & (age < window), batch_size)
    row = jnp.where(recent & any_newest, newest, row)
    env = jax.random.randint(key_env, (batch_size,), 0, buffer.num_envs)
    return gather(buffer, row, env, nstep, gamma)


def row_stacks(buffer: FrameBuffer, row: jax.Array, env: jax.Array) -> jax.Array:
    """The ``obs`` frame stacks of rows ``row`` of environments ``env`` (any equal shapes).

    Args:
        buffer: the buffer.
        row, env: int indices of shapes that broadcast together (a segment: ``(N, H)`` consecutive rows
            of one env).

    Returns:
        (..., H, W, 3 * stack) uint8 stacks, rebuilt from the stored frames as :func:`gather` does.
    """
    row, env = jnp.broadcast_arrays(row, env)
    shape = row.shape
    row, env = row.reshape(-1), env.reshape(-1)
    stacks = _stacks(buffer, buffer.frame_index[row], buffer.episode_step[row], env)
    return stacks.reshape(*shape, *stacks.shape[1:])


def segment_frames(buffer: FrameBuffer, row: jax.Array, env: jax.Array, length: int) -> jax.Array:
    """The frames of ``length``-step segments, each frame once: ``length + stack - 1`` per segment.

    Segment ``i`` is rows ``row[i] .. row[i] + length - 1`` (modulo the rows) of env ``env[i]``, inside one
    episode. Its stacks share frames: step ``j``'s stack is frames ``j .. j + stack - 1`` of the result
    (:func:`segment_stacks`), the first ``stack - 1`` clamped to the reset frame as the stacks are. SURF's
    ``get_segment`` returns the same ``L + stack - 1`` frames (replay_buffer_drqv2.py:231-242).

    Args:
        buffer: the buffer.
        row, env: (N,) int first rows and environments.
        length: agent steps per segment (static).

    Returns:
        (N, length + stack - 1, H, W, 3) uint8 frames, oldest first.
    """
    start = row % buffer.rows
    newest, k = buffer.frame_index[start], buffer.episode_step[start]
    # Frame i is the newest frame of step i - (stack - 1), not earlier than the reset frame newest - k.
    i = jnp.arange(length + buffer.stack - 1)
    frame = newest[:, None] - k[:, None] + jnp.maximum(k[:, None] + i - (buffer.stack - 1), 0)
    return buffer.frames[frame % buffer.frame_rows, env[:, None]]


def segment_stacks(frames: jax.Array, stack: int) -> jax.Array:
    """(..., L, H, W, 3 * stack) the stacks of segments kept as frames (..., L + stack - 1, H, W, 3)
    (:func:`segment_frames`): step ``j``'s stack is frames ``j .. j + stack - 1``."""
    steps = frames.shape[-4] - stack + 1
    window = jnp.arange(steps)[:, None] + jnp.arange(stack)
    return channel_stack(jnp.take(frames, window, axis=-4))


def relabel(buffer: FrameBuffer, reward_fn, chunk_rows: int = 64) -> FrameBuffer:
    """Recomputes ``learned_reward`` of every row with ``reward_fn(obs stacks (n, E, H, W, C), action (n, E, A))``,
    (n, E) rewards.

    Rows go ``chunk_rows`` at a time through a ``lax.map``, so only one chunk's stacks exist at once
    (SURF's ``relabel_with_predictor`` goes 100 steps at a time, replay_buffer_drqv2.py:80-117).
    Unwritten rows are relabelled too; nothing samples them.
    """
    rows = buffer.rows
    chunk_rows = min(chunk_rows, rows)  # a replay smaller than one chunk is one step, not a padded one
    chunks = -(-rows // chunk_rows)
    envs = jnp.arange(buffer.num_envs)

    def chunk(i):
        row = jnp.minimum(i * chunk_rows + jnp.arange(chunk_rows), rows - 1)
        grid = jnp.broadcast_to(row[:, None], (chunk_rows, buffer.num_envs))
        obs = row_stacks(buffer, grid, jnp.broadcast_to(envs, grid.shape))
        return reward_fn(obs, buffer.action[row])

    reward = jax.lax.map(chunk, jnp.arange(chunks)).reshape(chunks * chunk_rows, buffer.num_envs)[:rows]
    return buffer.replace(learned_reward=reward.astype(buffer.learned_reward.dtype))
