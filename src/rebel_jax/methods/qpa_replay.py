"""QPA's hybrid experience replay on both replays: a share of each agent batch from the newest rows.

QPA (huxiao09/QPA@7e9e49e) draws ``int(her_ratio * batch_size)`` transitions of each SAC batch from the last
``max_reward_buffer_size`` episodes' worth of transitions (``sample_onpolicy``, replay_buffer.py:107-108) and the
rest uniformly (agent/sac.py:274-285), while the label budget lasts (train_QPA.py:258-262). Here the recent part
is the batch's last positions (:func:`recent_positions`); on state tasks a batch is one-step SAC transitions
(:func:`state_batch`), on pixel tasks DrQ-v2's n-step transitions of the frame replay (:func:`pixel_batch`).
Kept apart from :mod:`rebel_jax.methods.qpa`, which calls these from its state and pixel hooks.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp

from rebel_jax import drqv2, frame_replay, replay


def recent_positions(count: jax.Array, labels: int, batch_size: int, her_ratio: float) -> jax.Array:
    """(B,) bool: the batch's last ``int(her_ratio * batch_size)`` positions, while ``0 < count < labels``: labels
    stored, the budget not spent (QPA's ``total_feedback < max_feedback`` past its first feedback session)."""
    hybrid = (count > 0) & (count < labels)
    return hybrid & (jnp.arange(batch_size) >= batch_size - int(her_ratio * batch_size))


def recent_rows(rows: int, size: jax.Array, episodes: int, episode_length: int, num_envs: int) -> jax.Array:
    """Rows holding the last ``episodes`` episodes' worth of transitions, ``ceil(episodes L / E)``, at most those
    filled: QPA's last ``episodes x L`` transitions (replay_buffer.py:108) over E environments. () int32.

    Args:
      rows: the replay's rows (T); size: () those filled.
      episode_length: L, steps per episode as the replay counts them (agent steps on pixel tasks).
    """
    window = min(rows, math.ceil(episodes * episode_length / num_envs))
    return jnp.clip(window, 1, jnp.maximum(size, 1)).astype(jnp.int32)


def state_batch(cfg: Any, count: jax.Array, buffer: replay.Buffer, key: jax.Array) -> replay.Transition:
    """A SAC batch of ``sac.batch_size`` uniform rows, its :func:`recent_positions` from the last
    ``qpa.recent_episodes`` episodes' rows (:func:`recent_rows`); the learned reward.

    Args:
      cfg: the run's config (``qpa``, ``sac``, ``feedback``, ``env``).
      count: () labels stored.
    """
    size, qpa = cfg.sac.batch_size, cfg.qpa
    recent = recent_positions(count, cfg.feedback.labels, size, qpa.her_ratio)
    window = recent_rows(buffer.rows, buffer.size, qpa.recent_episodes, cfg.env.episode_length, buffer.num_envs)
    key_row, key_back, key_env = jax.random.split(key, 3)
    back = jax.random.randint(key_back, (size,), 0, window)
    row = jax.random.randint(key_row, (size,), 0, buffer.size)
    row = jnp.where(recent, (buffer.ptr - 1 - back) % buffer.rows, row)
    env = jax.random.randint(key_env, (size,), 0, buffer.num_envs)
    fields = (buffer.obs, buffer.action, buffer.learned_reward, buffer.next_obs, buffer.terminal)
    obs, action, reward, next_obs, terminal = (field[row, env] for field in fields)
    return replay.Transition(obs, action, reward, next_obs, 1.0 - terminal)


def _draw_valid(key: jax.Array, valid: jax.Array, n: int) -> tuple[jax.Array, jax.Array]:
    """n rows uniform over the rows where ``valid`` (T,) holds, as :func:`rebel_jax.frame_replay.sample` draws
    them; and () whether any row is valid."""
    cumulative = jnp.cumsum(valid.astype(jnp.int32))
    draw = jax.random.randint(key, (n,), 0, jnp.maximum(cumulative[-1], 1))
    row = jnp.searchsorted(cumulative, draw, side="right").astype(jnp.int32)  # the (draw+1)-th valid row
    return jnp.minimum(row, valid.shape[0] - 1), cumulative[-1] > 0


def pixel_batch(
    cfg: Any, count: jax.Array, buffer: frame_replay.FrameBuffer, key: jax.Array, episode_length: int
) -> drqv2.PixelTransition:
    """DrQ-v2's n-step transitions (:func:`rebel_jax.frame_replay.gather`) of ``drqv2.batch_size`` starts uniform
    over the valid rows (:func:`rebel_jax.frame_replay.valid_rows`), its :func:`recent_positions` uniform over the
    valid rows among the last :func:`recent_rows` (over all valid rows while none of those is: the newest
    ``nstep - 1`` rows start no complete window). Environments uniform.

    Args:
      cfg: the run's config (``qpa``, ``drqv2``, ``feedback``).
      count: () labels stored.
      episode_length: L in agent steps.
    """
    size, qpa, nstep = cfg.drqv2.batch_size, cfg.qpa, cfg.drqv2.nstep
    recent = recent_positions(count, cfg.feedback.labels, size, qpa.her_ratio)
    window = recent_rows(buffer.rows, buffer.size, qpa.recent_episodes, episode_length, buffer.num_envs)
    key_row, key_recent, key_env = jax.random.split(key, 3)
    valid = frame_replay.valid_rows(buffer, nstep)
    age = (buffer.ptr - 1 - jnp.arange(buffer.rows)) % buffer.rows  # 0: the newest row
    row, _ = _draw_valid(key_row, valid, size)
    newest, any_newest = _draw_valid(key_recent, valid & (age < window), size)
    row = jnp.where(recent & any_newest, newest, row)
    env = jax.random.randint(key_env, (size,), 0, buffer.num_envs)
    return frame_replay.gather(buffer, row, env, nstep, cfg.drqv2.gamma)


def hybrid_batch(cfg: Any, count: jax.Array, buffer: Any, key: jax.Array, episode_length: int) -> Any:
    """QPA's hybrid batch from either replay: :func:`pixel_batch` from the frame ring, :func:`state_batch` from the
    state ring (``episode_length`` the task's, in agent steps)."""
    if isinstance(buffer, frame_replay.FrameBuffer):
        return pixel_batch(cfg, count, buffer, key, episode_length)
    return state_batch(cfg, count, buffer, key)
