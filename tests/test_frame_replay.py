"""The frame replay (each frame stored once) against a naive NumPy buffer that stores full stacks.

Environments are simulated in NumPy as the pixel tasks stack frames: a reset repeats the first
frame ``stack`` times, each step drops the oldest frame and appends the new one. Episodes are
short and the ring small, so the buffers wrap several times and windows meet episode starts.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.agents import frame_replay
from rebel_jax.agents.frame_replay import FrameStep
from rebel_jax.preference import pixel_reward

STACK, FRAME, ENVS, GAMMA = 3, (4, 4, 3), 2, 0.9


def _simulate(rng, num_steps: int, episode_length: int):
    """Vector steps of ENVS synchronised pixel environments: a list of dicts (NumPy)."""
    steps, stack = [], None
    for t in range(num_steps):
        k = t % episode_length
        if k == 0:
            reset = rng.integers(0, 256, (ENVS, *FRAME), dtype=np.uint8)
            stack = np.concatenate([reset] * STACK, axis=-1)
        new = rng.integers(0, 256, (ENVS, *FRAME), dtype=np.uint8)
        nxt = np.concatenate([stack[..., 3:], new], axis=-1)
        steps.append(
            dict(
                obs=stack,
                next_obs=nxt,
                action=rng.uniform(-1, 1, (ENVS, 2)).astype(np.float32),
                true_reward=rng.normal(size=ENVS).astype(np.float32),
                terminal=(rng.uniform(size=ENVS) < 0.15).astype(np.float32),  # exercises the n-step cut
                truncated=np.full(ENVS, float(k == episode_length - 1), np.float32),
                episode_step=np.int32(k),
                time=t,
                episode=t // episode_length,
            )
        )
        stack = nxt
    return steps


class NaiveBuffer:
    """A ring of T rows holding each transition's full ``obs`` and ``next_obs`` stacks."""

    def __init__(self, rows: int):
        self.rows, self.data, self.ptr, self.size = rows, [None] * rows, 0, 0

    def add(self, step: dict):
        self.data[self.ptr] = step
        self.ptr, self.size = (self.ptr + 1) % self.rows, min(self.size + 1, self.rows)

    def valid(self, row: int, nstep: int) -> bool:
        """Rows row..row+n-1 hold consecutive steps of one episode."""
        if row >= self.size:
            return False
        first = self.data[row]
        for i in range(nstep):
            d = self.data[(row + i) % self.rows]
            if d is None or d["time"] != first["time"] + i or d["episode"] != first["episode"]:
                return False
        return True

    def transition(self, row: int, env: int, nstep: int):
        """DrQ-v2's n-step sample (replay_buffer.py:150-160) from stored stacks."""
        reward, discount = 0.0, 1.0
        for i in range(nstep):
            d = self.data[(row + i) % self.rows]
            reward += discount * float(d["true_reward"][env])
            discount *= (1.0 - float(d["terminal"][env])) * GAMMA
        last = self.data[(row + nstep - 1) % self.rows]
        first = self.data[row]
        return first["obs"][env], first["action"][env], reward, discount, last["next_obs"][env]


@functools.cache
def _add():
    return jax.jit(frame_replay.add)


def _fill(num_steps: int, episode_length: int, capacity: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    buffer = frame_replay.init(capacity, ENVS, FRAME, 2, episode_length, STACK)
    naive = NaiveBuffer(capacity // ENVS)
    for step in _simulate(rng, num_steps, episode_length):
        fields = {k: v for k, v in step.items() if k not in ("time", "episode")}
        buffer = _add()(buffer, FrameStep(**fields))
        naive.add(step)
    return buffer, naive


@pytest.mark.parametrize(
    "episode_length,num_steps,nstep",
    [(4, 31, 3), (4, 31, 1), (3, 20, 3), (10, 9, 3), (2, 25, 1), (5, 40, 2)],
    ids=["wrapped-n3", "wrapped-n1", "one-window-per-episode", "not-full", "episodes-shorter-than-stack", "n2"],
)
def test_stacks_and_nstep_equal_the_naive_buffer(episode_length, num_steps, nstep):
    capacity = 14  # 7 rows of 2 environments
    buffer, naive = _fill(num_steps, episode_length, capacity, seed=episode_length + nstep)
    valid = np.asarray(frame_replay.valid_rows(buffer, nstep))
    expected_valid = np.array([naive.valid(r, nstep) for r in range(naive.rows)])
    np.testing.assert_array_equal(valid, expected_valid)
    assert valid.any()
    rows = np.repeat(np.flatnonzero(valid), ENVS)
    envs = np.tile(np.arange(ENVS), valid.sum())
    gather = jax.jit(frame_replay.gather, static_argnums=(3, 4, 5))
    got = gather(buffer, jnp.asarray(rows), jnp.asarray(envs), nstep, GAMMA, False)  # DrQ-v2: the true reward
    for i, (row, env) in enumerate(zip(rows, envs, strict=True)):
        obs, action, reward, discount, next_obs = naive.transition(row, env, nstep)
        np.testing.assert_array_equal(got.obs[i], obs, err_msg=f"obs of row {row} env {env}")
        np.testing.assert_array_equal(got.next_obs[i], next_obs, err_msg=f"next_obs of row {row} env {env}")
        np.testing.assert_array_equal(got.action[i], action)
        np.testing.assert_allclose(got.reward[i], reward, rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(got.discount[i], discount, rtol=1e-5, atol=1e-7)


def test_sample_is_uniform_over_valid_transitions():
    buffer, naive = _fill(31, 4, 14, seed=3)
    nstep = 1  # a 1-step reward names its (row, env): the rewards are distinct floats
    sample = jax.jit(frame_replay.sample, static_argnums=(2, 3, 4, 5))
    batch = sample(buffer, jax.random.key(0), 4000, False, nstep, GAMMA)
    valid = {
        float(naive.data[r]["true_reward"][e]): (r, e)
        for r in range(naive.rows)
        if naive.valid(r, nstep)
        for e in range(ENVS)
    }
    drawn = [valid.get(float(r)) for r in np.asarray(batch.reward)]
    assert None not in drawn, "sampled a transition that is not valid"
    counts = np.array([drawn.count(v) for v in valid.values()])
    assert counts.min() > 0  # every valid transition is drawn
    expected = 4000 / len(valid)
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))  # uniform within 5 sigma


def test_each_frame_is_stored_once():
    """At the paper's size: 100k transitions of 84x84 frames, one env or ten."""
    for envs in (1, 10):
        shapes = jax.eval_shape(lambda envs=envs: frame_replay.init(100_000, envs, (84, 84, 3), 6, 500, 3))
        frames = shapes.frames.shape[0] * shapes.frames.shape[1]
        assert 100_000 <= frames <= 100_000 * (1 + 1 / 500) + envs * (3 + 2)  # + a reset frame per episode
        total = frame_replay.nbytes(shapes)
        stacked = 100_000 * 2 * 84 * 84 * 9  # obs and next_obs as full stacks
        assert total < stacked / 5.9


# -- segments: the label store's copies and the query pool on a ring that wraps --------------------------


def _segment_reference(naive: NaiveBuffer, row: int, env: int, length: int):
    """The environment's own stacks and actions of ``length`` rows from ``row`` (NumPy)."""
    data = [naive.data[(row + j) % naive.rows] for j in range(length)]
    return np.stack([d["obs"][env] for d in data]), np.stack([d["action"][env] for d in data])


@pytest.mark.parametrize("num_steps", [6, 31], ids=["not-full", "wrapped"])
def test_segment_frames_rebuild_the_naive_stacks(num_steps):
    length, episode_length = 3, 5
    buffer, naive = _fill(num_steps, episode_length, 14, seed=num_steps)
    places = [(r, e) for r in range(naive.rows) if naive.valid(r, length) for e in range(ENVS)]
    assert places
    rows, envs = (jnp.asarray(x, jnp.int32) for x in zip(*places, strict=True))
    frames = jax.jit(frame_replay.segment_frames, static_argnums=3)(buffer, rows, envs, length)
    assert frames.shape == (len(places), length + STACK - 1, *FRAME)  # each frame once
    stacks = frame_replay.segment_stacks(frames, STACK)
    for i, (row, env) in enumerate(places):
        expected, _ = _segment_reference(naive, row, env, length)
        np.testing.assert_array_equal(stacks[i], expected, err_msg=f"row {row} env {env}")


@pytest.mark.parametrize("recent", [3, 10])
def test_sample_segments_draws_the_last_complete_episodes_the_ring_holds(recent):
    """Rows 18..30 of a 13-row ring: episodes of 4 steps, 16-19 partly overwritten, 20-23 and 24-27
    complete, 28-30 running; the draws cover exactly the last ``recent`` complete (episode, env)."""
    length, episode_length = 2, 4
    buffer, naive = _fill(31, episode_length, 26, seed=5)
    draw = jax.jit(pixel_reward.sample_segments, static_argnums=(2, 3, 4))
    places = draw(jax.random.key(0), buffer, 2000, length, episode_length, recent)
    held = {}
    for d in naive.data:
        held[d["episode"]] = held.get(d["episode"], 0) + 1
    complete = sorted((ep, e) for ep, n in held.items() if n == episode_length for e in range(ENVS))
    assert [ep for ep, _ in complete] == [5, 5, 6, 6]
    eligible = set(complete[-recent:])
    drawn = set()
    for row, env in zip(np.asarray(places.row), np.asarray(places.env), strict=True):
        first = naive.data[row]
        assert naive.valid(int(row), length), f"row {row} does not start {length} steps of one episode"
        assert first["time"] % episode_length <= episode_length - length
        drawn.add((first["episode"], int(env)))
    assert drawn == eligible


def test_label_store_keeps_its_frames_after_the_replay_wraps():
    """Labelled segments are copied: after the ring has overwritten every row, the store still holds the
    stacks and actions the teacher saw, where the replay's rows (the old place-based store) no longer do."""
    length, episode_length, pairs = 3, 5, 4
    rng = np.random.default_rng(7)
    steps = _simulate(rng, 40, episode_length)
    buffer = frame_replay.init(14, ENVS, FRAME, 2, episode_length, STACK)
    naive = NaiveBuffer(7)

    def add(buffer, step):
        naive.add(step)
        return _add()(buffer, FrameStep(**{k: v for k, v in step.items() if k not in ("time", "episode")}))

    for step in steps[:20]:  # the ring has wrapped twice: rows hold steps 13..19, episode 15..19 complete
        buffer = add(buffer, step)
    draw = jax.jit(pixel_reward.sample_segments, static_argnums=(2, 3, 4))
    places = draw(jax.random.key(1), buffer, 2 * pairs, length, episode_length, 10)
    seg_a, seg_b = (jax.tree.map(lambda x, s=s: x[s], places) for s in (slice(0, pairs), slice(pairs, None)))
    starts = zip(places.row, places.env, strict=True)
    references = [_segment_reference(naive, int(r), int(e), length) for r, e in starts]
    mask = jnp.asarray([1.0, 0.0, 1.0, 1.0])  # the second pair skipped by the teacher
    store = pixel_reward.empty_store(3, length, (*FRAME[:2], 3 * STACK), 2)
    store = store.replace(ptr=jnp.int32(2), count=jnp.int32(2))  # two older labels: the kept pairs wrap
    store = jax.jit(pixel_reward.append_segments)(store, buffer, seg_a, seg_b, jnp.arange(pairs) / 4.0, mask)
    slots = {0: 2, 2: 0, 3: 1}  # pair -> slot
    assert int(store.ptr) == 2 and int(store.count) == 3

    def check(store):
        for pair, slot in slots.items():
            for side, frames, action in ((0, store.a.frames, store.a.action), (1, store.b.frames, store.b.action)):
                stacks, actions = references[side * pairs + pair]
                got = pixel_reward.SegmentFrames(frames[slot], action[slot])
                np.testing.assert_array_equal(got.stacks(), stacks, err_msg=f"pair {pair} side {side}")
                np.testing.assert_array_equal(got.action, actions)
            assert float(store.labels[slot]) == pair / 4.0

    check(store)
    for step in steps[20:]:  # 20 more steps: every row and frame of the ring is overwritten
        buffer = add(buffer, step)
    check(store)
    gathered = pixel_reward.gather_segments(buffer, seg_a, length)
    for pair in slots:
        stale = pixel_reward.SegmentFrames(gathered.frames[pair], gathered.action[pair])
        assert not np.array_equal(stale.stacks(), references[pair][0])  # the replay's rows moved on
