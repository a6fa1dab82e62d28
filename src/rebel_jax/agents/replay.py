"""Fixed-capacity, device-resident replay buffer of state transitions as a pytree (the state ring).

Layout (a contract other modules rely on): every data field is shaped ``(T, E, ...)`` with
``E = num_envs`` and ``T = capacity // num_envs``, time-major with an env axis, so one
environment's consecutive steps are a contiguous slice along ``T``. Each :func:`add` writes
one row (one transition per environment) at ``ptr``, as a ring buffer.

**The replay contract**, shared with the frame ring of pixel tasks (:mod:`rebel_jax.agents.frame_replay`):

- the same field names: ``action``, ``true_reward`` (the task's reward, which only the scripted teacher and
  the logged metrics read), ``learned_reward`` (the reward model's, which the agent learns from on a
  preference run), ``terminal``, ``truncated``, ``episode_step``, ``ptr``, ``size``; the ``rows`` and
  ``num_envs`` properties. The observations differ: ``obs`` / ``next_obs`` here, one ``frames`` ring there;
- the same functions: ``init``, ``add`` (one vector step, a ``Step`` / ``FrameStep`` with ``true_reward`` and
  ``learned_reward`` fields), ``sample(buffer, key, batch_size, learned_reward, ...)`` (the agent's minibatch
  with the learned or the true reward as its ``reward``), ``sample_recent`` (a batch with a share from the newest
  rows, QPA's hybrid replay) and ``relabel(buffer, reward_fn, chunk_rows)``
  (``learned_reward`` of every row recomputed by ``reward_fn(obs, action)`` over any leading axes).
"""

from __future__ import annotations

from collections.abc import Callable

import flax.struct
import jax
import jax.numpy as jnp


@flax.struct.dataclass
class Transition:
    """A batch of transitions, each field with leading batch axis (B, ...); SAC's input.

    Also exported as ``rebel_jax.agents.sac.Transition`` (it lives here so that replay does not
    depend on sac).

    Attributes:
        obs: (B, obs_size).
        action: (B, action_size).
        reward: (B,) the reward the learner optimises (true or learned).
        next_obs: (B, obs_size).
        discount: (B,) 0 where the episode terminated at ``next_obs``, 1 otherwise;
            time-limit truncation is not termination.
    """

    obs: jax.Array
    action: jax.Array
    reward: jax.Array
    next_obs: jax.Array
    discount: jax.Array


@flax.struct.dataclass
class Step:
    """One vector step: a transition for each of the E environments.

    Attributes:
        obs: (E, obs_size).
        action: (E, action_size).
        next_obs: (E, obs_size) the true next observation (before any auto-reset).
        true_reward: (E,) the task's reward.
        terminal: (E,) 1.0 where the episode terminated at ``next_obs``.
        truncated: (E,) 1.0 where the episode was cut by the time limit at ``next_obs``.
        episode_step: (E,) int32 step index of ``obs`` within its episode.
        learned_reward: (E,) learned reward, or None to store zeros (relabel later).
        qpos: (E, nq) physics positions at ``obs``, or None (stored only by a buffer made with ``qpos_size``).
        scene: (E, k) what a clip's frame of ``obs`` needs beyond ``qpos`` (a Meta-World task's mocap, moved body and
            goal site: ``MetaWorldEnv.scene``), or None (stored only by a buffer made with ``scene_size``).
    """

    obs: jax.Array
    action: jax.Array
    next_obs: jax.Array
    true_reward: jax.Array
    terminal: jax.Array
    truncated: jax.Array
    episode_step: jax.Array
    learned_reward: jax.Array | None = None
    qpos: jax.Array | None = None
    scene: jax.Array | None = None


@flax.struct.dataclass
class Buffer:
    """Replay storage; data fields are (T, E, ...), see the module docstring.

    Attributes:
        obs, next_obs: (T, E, obs_size) float32.
        action: (T, E, action_size) float32.
        true_reward: (T, E) the task's reward.
        learned_reward: (T, E) reward of the current reward model (zeros on a run without one).
        terminal, truncated: (T, E) float 0/1.
        episode_step: (T, E) int32 step index of ``obs`` within its episode.
        ptr: () int32 next row to write.
        size: () int32 rows filled (at most T).
        qpos: (T, E, nq) physics positions at ``obs`` (what clips for a human are rendered from), or None
            when not stored (the default: only the human teacher needs them).
        scene: (T, E, k) what a clip's frame of ``obs`` needs beyond ``qpos`` (see :class:`Step`), or None when not
            stored (the default; the tasks whose ``qpos`` is all a frame needs).
    """

    obs: jax.Array
    action: jax.Array
    next_obs: jax.Array
    true_reward: jax.Array
    learned_reward: jax.Array
    terminal: jax.Array
    truncated: jax.Array
    episode_step: jax.Array
    ptr: jax.Array
    size: jax.Array
    qpos: jax.Array | None = None
    scene: jax.Array | None = None

    @property
    def rows(self) -> int:
        """T, the number of rows (static)."""
        return self.true_reward.shape[0]

    @property
    def num_envs(self) -> int:
        """E, the number of environments (static)."""
        return self.true_reward.shape[1]


def init(
    capacity: int, num_envs: int, obs_size: int, action_size: int, qpos_size: int = 0, scene_size: int = 0
) -> Buffer:
    """An empty buffer of ``capacity // num_envs`` rows.

    Args:
        capacity: transitions to hold (rounded down to a multiple of ``num_envs``).
        num_envs: environments per row.
        obs_size, action_size: problem sizes.
        qpos_size: physics positions stored per transition; 0 stores none (``qpos`` is None).
        scene_size: numbers of a frame's scene stored per transition; 0 stores none (``scene`` is None).

    Returns:
        A zero-filled :class:`Buffer` with ``ptr = size = 0``.
    """
    if num_envs < 1 or capacity < num_envs:
        raise ValueError(f"need 1 <= num_envs <= capacity; got num_envs={num_envs}, capacity={capacity}")
    rows = capacity // num_envs

    def zeros(*shape, dtype=jnp.float32):
        return jnp.zeros((rows, num_envs, *shape), dtype)

    return Buffer(
        obs=zeros(obs_size),
        action=zeros(action_size),
        next_obs=zeros(obs_size),
        true_reward=zeros(),
        learned_reward=zeros(),
        terminal=zeros(),
        truncated=zeros(),
        episode_step=zeros(dtype=jnp.int32),
        ptr=jnp.zeros((), jnp.int32),
        size=jnp.zeros((), jnp.int32),
        qpos=zeros(qpos_size) if qpos_size else None,
        scene=zeros(scene_size) if scene_size else None,
    )


def add(buffer: Buffer, step: Step) -> Buffer:
    """Write one row (E transitions) at ``ptr`` and advance the ring.

    Args:
        buffer: the buffer.
        step: a :class:`Step` with leading axis E on every field.

    Returns:
        The buffer with the row written, ``ptr`` advanced modulo T and ``size`` grown.
    """
    learned = step.learned_reward if step.learned_reward is not None else jnp.zeros_like(step.true_reward)
    values = dict(
        obs=step.obs,
        action=step.action,
        next_obs=step.next_obs,
        true_reward=step.true_reward,
        learned_reward=learned,
        terminal=step.terminal,
        truncated=step.truncated,
        episode_step=step.episode_step,
    )
    if (buffer.qpos is None) != (step.qpos is None):
        raise ValueError("a buffer stores qpos exactly when its steps carry them (replay.init's qpos_size)")
    if buffer.qpos is not None:
        values["qpos"] = step.qpos
    if (buffer.scene is None) != (step.scene is None):
        raise ValueError("a buffer stores scenes exactly when its steps carry them (replay.init's scene_size)")
    if buffer.scene is not None:
        values["scene"] = step.scene

    def write(name: str, value: jax.Array) -> jax.Array:
        field = getattr(buffer, name)
        return jax.lax.dynamic_update_index_in_dim(field, value.astype(field.dtype), buffer.ptr, axis=0)

    written = {name: write(name, value) for name, value in values.items()}
    return buffer.replace(
        **written,
        ptr=(buffer.ptr + 1) % buffer.rows,
        size=jnp.minimum(buffer.size + 1, buffer.rows),
    )


def sample(buffer: Buffer, key: jax.Array, batch_size: int, learned_reward: bool | jax.Array) -> Transition:
    """Uniform sample, with replacement, over filled (row, env) pairs.

    Args:
        buffer: a buffer with ``size >= 1``.
        key: PRNG key.
        batch_size: transitions to draw.
        learned_reward: the batch's ``reward``: ``learned_reward`` (True) or ``true_reward`` (False); may be traced.

    Returns:
        A :class:`Transition` with ``discount = 1 - terminal``.
    """
    key_row, key_env = jax.random.split(key)
    row = jax.random.randint(key_row, (batch_size,), 0, buffer.size)
    env = jax.random.randint(key_env, (batch_size,), 0, buffer.num_envs)
    reward = jnp.where(learned_reward, buffer.learned_reward[row, env], buffer.true_reward[row, env])
    return Transition(
        obs=buffer.obs[row, env],
        action=buffer.action[row, env],
        reward=reward,
        next_obs=buffer.next_obs[row, env],
        discount=1.0 - buffer.terminal[row, env],
    )


def sample_recent(buffer: Buffer, key: jax.Array, batch_size: int, recent: jax.Array, window: jax.Array) -> Transition:
    """:func:`sample` with the learned reward, except that the batch positions where ``recent`` holds are drawn
    from the newest ``window`` rows (a hybrid batch, as QPA's: huxiao09/QPA@7e9e49e:agent/sac.py:274-285).

    Args:
        recent: (batch_size,) bool, the positions drawn from the newest rows.
        window: () int, how many of the newest rows (1 to ``size``).
    """
    key_row, key_back, key_env = jax.random.split(key, 3)
    back = jax.random.randint(key_back, (batch_size,), 0, window)
    row = jax.random.randint(key_row, (batch_size,), 0, buffer.size)
    row = jnp.where(recent, (buffer.ptr - 1 - back) % buffer.rows, row)
    env = jax.random.randint(key_env, (batch_size,), 0, buffer.num_envs)
    fields = (buffer.obs, buffer.action, buffer.learned_reward, buffer.next_obs, buffer.terminal)
    obs, action, reward, next_obs, terminal = (field[row, env] for field in fields)
    return Transition(obs, action, reward, next_obs, 1.0 - terminal)


def _chunked(x: jax.Array, chunk_rows: int) -> jax.Array:
    """(T, E, ...) -> (ceil(T / chunk_rows), chunk_rows * E, ...), padding T with zeros."""
    pad = -x.shape[0] % chunk_rows
    if pad:
        x = jnp.concatenate([x, jnp.zeros((pad, *x.shape[1:]), x.dtype)])
    return x.reshape(x.shape[0] // chunk_rows, chunk_rows * x.shape[1], *x.shape[2:])


def relabel(buffer: Buffer, reward_fn: Callable[[jax.Array, jax.Array], jax.Array], chunk_rows: int) -> Buffer:
    """Recompute ``learned_reward`` of every row with ``reward_fn``, ``chunk_rows`` rows at a time.

    Args:
        buffer: the buffer.
        reward_fn: maps (obs (N, obs_size), action (N, action_size)) to rewards (N,),
            called with N = chunk_rows * E under ``jax.lax.map``.
        chunk_rows: rows per call (bounds peak memory); need not divide T.

    Returns:
        The buffer with ``learned_reward`` replaced (rows beyond ``size`` included).
    """
    chunk_rows = max(1, min(chunk_rows, buffer.rows))
    obs, action = _chunked(buffer.obs, chunk_rows), _chunked(buffer.action, chunk_rows)
    rewards = jax.lax.map(lambda xs: reward_fn(*xs), (obs, action))
    rewards = rewards.reshape(-1, buffer.num_envs)[: buffer.rows]
    return buffer.replace(learned_reward=rewards.astype(buffer.learned_reward.dtype))
