"""Pixel PEBBLE (``--algo pebble`` on ``probe_point_pixels``): the pixel reward ensemble's BT loss against
NumPy, the oracle's labels against NumPy segment returns of the stored true rewards, and a short run."""

from __future__ import annotations

import dataclasses
import functools
import re

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.flatten_util import ravel_pytree

from rebel_jax.agents import frame_replay
from rebel_jax.agents.drqv2 import DrQV2Config, task_config
from rebel_jax.config import Config, ConfigError, EnvConfig, FeedbackConfig, TrainConfig
from rebel_jax.methods import rebel as agent_preference
from rebel_jax.methods import surf
from rebel_jax.methods.rebel import AgentPreferenceConfig
from rebel_jax.methods.surf import SURFConfig
from rebel_jax.preference import pixel_reward, teachers
from rebel_jax.preference import reward_model as rm
from rebel_jax.preference import reward_train as rt
from rebel_jax.preference.pixel_reward import PixelRewardConfig, SegmentPlaces
from rebel_jax.preference.pretrain import PretrainConfig
from rebel_jax.preference.queries import QueryConfig
from rebel_jax.preference.teachers import TeacherConfig
from rebel_jax.run.cli import parse
from rebel_jax.train import Trainer, compiled, seed_keys

STACK, SIZE, ENVS, LENGTH, ACTIONS = 3, 16, 2, 6, 2
REWARD = PixelRewardConfig(hidden=8, batch_size=4, max_epochs=3, lr=1e-3, chunk=3)


def _filled_buffer(rng, steps: int, buffer=None, length: int = LENGTH):
    """A frame replay of ``steps`` vector steps of synchronised simulated pixel envs, and the naive stacks:
    ``buffer`` (empty; episodes of ``length`` agent steps) filled, or a new one of this module's sizes."""
    if buffer is None:
        buffer = frame_replay.init(steps * ENVS, ENVS, (SIZE, SIZE, 3), ACTIONS, length, STACK, learned_reward=True)
    envs, frame, actions_size, depth = buffer.num_envs, buffer.frames.shape[2:], buffer.action.shape[-1], buffer.stack
    stacks, actions, true = [], [], []
    stack = None
    for t in range(steps):
        if t % length == 0:
            reset = rng.integers(0, 256, (envs, *frame), dtype=np.uint8)
            stack = np.concatenate([reset] * depth, axis=-1)
        nxt = np.concatenate([stack[..., 3:], rng.integers(0, 256, (envs, *frame), dtype=np.uint8)], axis=-1)
        action = rng.uniform(-1, 1, (envs, actions_size)).astype(np.float32)
        reward = rng.uniform(0, 1, size=envs).astype(np.float32)  # non-negative, as the tasks' rewards
        step = frame_replay.FrameStep(
            obs=jnp.asarray(stack),
            action=jnp.asarray(action),
            next_obs=jnp.asarray(nxt),
            learned_reward=jnp.zeros(envs),
            terminal=jnp.zeros(envs),
            truncated=jnp.full(envs, float(t % length == length - 1)),
            episode_step=jnp.int32(t % length),
            true_reward=jnp.asarray(reward),
        )
        buffer = frame_replay.add(buffer, step)
        stacks.append(stack)
        actions.append(action)
        true.append(reward)
        stack = nxt
    return buffer, np.stack(stacks), np.stack(actions), np.stack(true)


def _frames(buffer, seg: SegmentPlaces, horizon: int) -> pixel_reward.SegmentFrames:
    """Segments at places of any leading shape, copied from the replay as the label store keeps them."""
    flat = jax.tree.map(lambda x: x.reshape(-1), seg)
    got = pixel_reward.gather_segments(buffer, flat, horizon)
    return jax.tree.map(lambda x: x.reshape(*seg.row.shape, *x.shape[1:]), got)


def _place_of(buffer, frames, action, length: int) -> tuple[int, int]:
    """The one (row, env) of the replay whose ``length`` actions are ``action`` (the actions are distinct
    floats), checking that the stored ``frames`` are the replay's there."""
    actions = np.asarray(buffer.action)
    found = [
        (row, env)
        for row in range(int(buffer.size) - length + 1)
        for env in range(buffer.num_envs)
        if np.array_equal(actions[row : row + length, env], action)
    ]
    assert len(found) == 1, found
    row, env = found[0]
    expected = frame_replay.segment_frames(buffer, jnp.asarray([row]), jnp.asarray([env]), length)[0]
    np.testing.assert_array_equal(frames, expected)
    return row, env


@pytest.mark.parametrize("crop", [0, pytest.param(1, marks=pytest.mark.heavy)])  # crop 1: make test-heavy
def test_bt_loss_matches_numpy_on_naive_stacks(crop):
    rng = np.random.default_rng(0)
    buffer, stacks, actions, _ = _filled_buffer(rng, 3 * LENGTH)
    horizon, batch = 4, 5
    state = pixel_reward.init(REWARD, jax.random.PRNGKey(1), (SIZE, SIZE, 3 * STACK), ACTIONS, 8, horizon)
    members = REWARD.ensemble_size
    # Starts inside one episode (episode b, offset <= L - H), per member its own pairs.
    episode = rng.integers(0, 3, (2, members, batch))
    rows = episode * LENGTH + rng.integers(0, LENGTH - horizon + 1, (2, members, batch))
    envs = rng.integers(0, ENVS, (2, members, batch))
    labels = rng.choice([0.0, 0.5, 1.0], (members, batch)).astype(np.float32)
    weight = (rng.uniform(size=(members, batch)) < 0.8).astype(np.float32)
    weight[:, 0] = 1.0
    seg_a = SegmentPlaces(jnp.asarray(rows[0], jnp.int32), jnp.asarray(envs[0], jnp.int32))
    seg_b = SegmentPlaces(jnp.asarray(rows[1], jnp.int32), jnp.asarray(envs[1], jnp.int32))
    key = jax.random.PRNGKey(7)
    seg_a, seg_b = _frames(buffer, seg_a, horizon), _frames(buffer, seg_b, horizon)
    pairs = rm.PrefBatch(seg_a, seg_b, jnp.asarray(labels), jnp.asarray(weight), members=jnp.arange(members))
    pairs = rm.with_rewards(REWARD, state.params, pairs)
    loss, metrics = rm.bt_loss(REWARD, crop, crop_accuracy=True)(state.params, pairs, key)
    masks = np.ones((2, members, batch, horizon), np.float32)
    if crop:  # SURF's crops, drawn from the same key: every member sums over its own masked steps
        masks = np.stack(rm.crop_masks(key, (members, batch), horizon, crop))
        assert np.all(masks.sum(-1)[0] == masks.sum(-1)[1]) and np.any(masks.sum(-1) != horizon)

    net = REWARD.network()
    expected = 0.0
    for m in range(members):
        member = jax.tree.map(lambda x, m=m: x[m], state.params)
        total, count = 0.0, 0.0
        for i in range(batch):
            returns = []
            for side in range(2):
                r, e = rows[side, m, i], envs[side, m, i]
                obs = stacks[r : r + horizon, e]  # the environment's own stacks, stored whole
                rewards = np.asarray(net.apply(member, obs, actions[r : r + horizon, e]))
                returns.append(float(np.sum(rewards * masks[side, m, i])))
            z = np.float64(returns[1] - returns[0])
            y = labels[m, i]
            ce = -(y * np.log(1 / (1 + np.exp(-z))) + (1 - y) * np.log(1 / (1 + np.exp(z))))
            total += weight[m, i] * ce
            count += weight[m, i]
        expected += total / count
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5, atol=1e-6)
    assert crop == 0 or metrics["accuracy_logits"].shape == (members, batch)


def test_relabel_and_row_stacks_match_naive_stacks():
    rng = np.random.default_rng(2)
    buffer, stacks, actions, _ = _filled_buffer(rng, 2 * LENGTH)
    np.testing.assert_array_equal(
        frame_replay.row_stacks(buffer, jnp.arange(2 * LENGTH)[:, None], jnp.arange(ENVS)[None]), stacks
    )
    state = pixel_reward.init(REWARD, jax.random.PRNGKey(3), (SIZE, SIZE, 3 * STACK), ACTIONS, 4, 2)
    expected = rm.mean_reward(REWARD, state.params, jnp.asarray(stacks), jnp.asarray(actions))
    for chunk_rows in (5, 10 * LENGTH):  # a ragged last chunk; a chunk larger than the replay
        relabelled = frame_replay.relabel(
            buffer, lambda o, a: rm.mean_reward(REWARD, state.params, o, a), chunk_rows=chunk_rows
        )
        np.testing.assert_allclose(relabelled.learned_reward, expected, rtol=1e-5, atol=1e-6)


# Episodes of 20 frames = 10 agent steps, rounds of one episode; sessions at the starts of rounds 1, 2, 3.
MICRO = Config(
    algo="pebble",
    env=EnvConfig(task="probe_point_pixels", num_envs=2, episode_length=20),
    drqv2=DrQV2Config(feature_dim=8, hidden=16, batch_size=16, nstep=3, std_steps=40),
    train=TrainConfig(total_steps=80, seed_steps=20, steps_per_round=20, eval_every=20, eval_episodes=1),
    feedback=FeedbackConfig(labels=12, per_session=4, interval=20),
    query=QueryConfig(segment_length=4, sampling="disagreement", candidate_factor=2),
    pixel_reward=REWARD,
    pretrain=PretrainConfig(reset_updates=2),
)
ROUNDS, SEEDS = 4, 2


@pytest.fixture(scope="module")
def run():
    trainer = Trainer(MICRO)
    init, round_fn, _ = compiled(trainer)
    state = init(seed_keys(0, SEEDS))
    start = jax.device_get(state)  # the round donates its input
    metrics = []
    for r in range(ROUNDS):
        state, m = round_fn(state, jnp.int32(r))
        metrics.append(jax.device_get(m))
    return trainer, start, state, metrics


@pytest.mark.heavy
def test_pixel_pebble_traces_once_uses_labels_and_moves_its_reward(run):
    trainer, start, state, metrics = run
    assert trainer.trace_count == 1
    used = [float(m["labels_used"][0]) for m in metrics]
    assert used == [0.0, 4.0, 8.0, 12.0]  # 4 pairs per session, none skipped by the oracle
    assert np.all(np.isnan(metrics[0]["session_oracle_agreement"]))  # no session in round 0
    for m in metrics[1:]:  # the oracle agrees with itself
        np.testing.assert_array_equal(m["session_oracle_agreement"], 1.0)
        np.testing.assert_array_equal(m["session_skipped"], 0.0)
        np.testing.assert_array_equal(m["session_equal"], 0.0)
    assert np.all(np.isnan(metrics[0]["reward_loss"]))  # no session before the seed steps are done
    for m in metrics[1:]:
        for key in ("reward_loss", "reward_accuracy_all", "reward_correlation_replay", "critic_loss"):
            assert np.all(np.isfinite(m[key])), key
        np.testing.assert_array_equal(m["diverged"], 0.0)
    # The reward learned from the oracle's labels follows the true one over the replay, in every seed (0.30 and
    # 0.46 after the third feedback session on this CPU; a flipped label convention would make it negative).
    assert np.all(metrics[-1]["reward_correlation_replay"] > 0.1), metrics[-1]["reward_correlation_replay"]
    before, after = jax.tree.leaves(start.reward.params), jax.tree.leaves(state.reward.params)
    assert all(not np.allclose(a, b) for a, b in zip(before, after, strict=True))
    # The replay's reward is the final ensemble's mean on every written row (relabelled, then stored at add).
    for seed in range(SEEDS):
        buffer = jax.tree.map(lambda x, s=seed: x[s], state.buffer)
        params = jax.tree.map(lambda x, s=seed: x[s], state.reward.params)
        rows = jnp.arange(int(buffer.size))[:, None]
        obs = frame_replay.row_stacks(buffer, rows, jnp.arange(buffer.num_envs)[None])
        expected = rm.mean_reward(MICRO.pixel_reward, params, obs, buffer.action[: int(buffer.size)])
        np.testing.assert_allclose(buffer.learned_reward[: int(buffer.size)], expected, rtol=1e-4, atol=1e-5)
        assert not np.allclose(buffer.learned_reward[: int(buffer.size)], buffer.true_reward[: int(buffer.size)])


@pytest.mark.heavy
def test_oracle_labels_are_numpy_segment_returns_of_the_stored_true_rewards(run):
    trainer, _, state, metrics = run
    horizon, length = MICRO.query.segment_length, trainer.episode_length
    true = np.asarray(state.buffer.true_reward)
    # The stored true reward is the environment's: each round ends one training episode, whose mean return
    # over the environments the round reports.
    for r, m in enumerate(metrics):
        episode = true[:, r * length : (r + 1) * length].sum(axis=1).mean(axis=-1)
        np.testing.assert_allclose(m["train_return"], episode, rtol=1e-5, atol=1e-5)
    data = jax.device_get(state.reward.data)
    for seed in range(SEEDS):
        count = int(data.count[seed])
        assert count == 12
        buffer = jax.tree.map(lambda x, s=seed: x[s], state.buffer)
        for i in range(count):
            returns = []
            for frames, action in ((data.a.frames, data.a.action), (data.b.frames, data.b.action)):
                # The stored copy is the replay's segment at the place the teacher saw.
                start, e = _place_of(buffer, frames[seed, i], action[seed, i], horizon)
                assert start % length <= length - horizon  # inside one episode
                returns.append(sum(float(true[seed, start + h, e]) for h in range(horizon)))
            assert data.labels[seed, i] == (1.0 if returns[0] < returns[1] else 0.0)


def test_an_imperfect_teachers_answers_and_oracle_agreement_match_numpy_segment_returns():
    """A skipping, "equal" and mistaken teacher through the pixel ``teach``, on a replay of random frames and
    true rewards (four episodes): its mask, counts and labels, and the share of its kept answers that are the
    oracle's, against NumPy returns of the stored true rewards; over 16 teacher keys (the mistakes are drawn)."""
    trainer = Trainer(MICRO)
    ts = jax.jit(trainer.init)(jax.random.PRNGKey(0))
    buffer, _, _, _ = _filled_buffer(
        np.random.default_rng(4), 4 * trainer.episode_length, ts.buffer, trainer.episode_length
    )
    ts = ts.replace(buffer=buffer)
    seg_a, seg_b = jax.jit(trainer.select, static_argnums=2)(ts, jax.random.PRNGKey(5), False)
    true, horizon = np.asarray(ts.buffer.true_reward), MICRO.query.segment_length
    returns_a, returns_b = (
        np.array([true[r : r + horizon, e].sum() for r, e in zip(np.asarray(s.row), np.asarray(s.env), strict=True)])
        for s in (seg_a, seg_b)
    )
    margin = horizon * true[: int(ts.buffer.size)].mean()
    # Thresholds from the data: the pair with the lowest best return is skipped, the closest kept pair is equal.
    # (Each threshold lies halfway between two of the returns, clear of float32 rounding.)
    best, gap = np.maximum(returns_a, returns_b), np.abs(returns_a - returns_b)
    lowest = np.sort(best)
    skipped = best < lowest[:2].mean()
    closest = np.sort(gap[~skipped])
    teacher = TeacherConfig(eps_mistake=0.5, eps_skip=lowest[:2].mean() / margin, eps_equal=closest[:2].mean() / margin)
    assert margin > 0 and lowest[0] < lowest[1] and len(closest) >= 2 and closest[0] < closest[1]
    ts = ts.replace(teacher=teachers.knobs(teacher))
    keys = jax.random.split(jax.random.PRNGKey(6), 16)
    teach = jax.jit(jax.vmap(trainer.teach, in_axes=(None, 0, None, None, None)))
    labels, mask, info = jax.device_get(teach(ts, keys, seg_a, seg_b, jnp.int32(0)))
    equal, oracle = (gap < closest[:2].mean()) & ~skipped, (returns_a < returns_b).astype(np.float32)
    np.testing.assert_array_equal(mask, np.broadcast_to(~skipped, mask.shape).astype(np.float32))
    np.testing.assert_array_equal(info["num_skipped"], skipped.sum())
    np.testing.assert_array_equal(info["num_equal"], equal.sum())
    np.testing.assert_array_equal(labels[:, equal], 0.5)
    answered = ~skipped & ~equal
    assert np.all((labels[:, answered] == oracle[answered]) | (labels[:, answered] == 1 - oracle[answered]))
    expected = np.mean(labels[:, ~skipped] == oracle[~skipped], axis=1)
    np.testing.assert_allclose(info["oracle_agreement"], expected, rtol=1e-6)
    assert len(set(expected.tolist())) > 1  # the drawn mistakes move the agreement


# The paper's V (rebel.source onpolicy, the default): the evaluation episode's 10 agent steps, whole.
REBEL = dataclasses.replace(MICRO, algo="rebel", rebel=AgentPreferenceConfig())
LAMS = (0.0, -1.0)


@pytest.fixture(scope="module")
def rebel_run():
    trainer = Trainer(REBEL)
    init, round_fn, _ = compiled(trainer)
    state = init(jnp.tile(seed_keys(0, SEEDS), (len(LAMS), 1)))  # columns: lambda, then seed
    state = state.replace(lam=jnp.repeat(jnp.asarray(LAMS, jnp.float32), SEEDS))
    for r in range(ROUNDS):
        state, _ = round_fn(state, jnp.int32(r))
    return trainer, jax.device_get(state)


def test_value_term_on_pixels_matches_numpy_on_naive_stacks():
    rng = np.random.default_rng(4)
    buffer, stacks, _, _ = _filled_buffer(rng, 2 * LENGTH)
    state = pixel_reward.init(REWARD, jax.random.PRNGKey(5), (SIZE, SIZE, 3 * STACK), ACTIONS, 4, 2)
    horizon, n, gamma = 4, 3, 0.9
    rows = rng.integers(0, 2, n) * LENGTH + rng.integers(0, LENGTH - horizon + 1, n)
    envs = rng.integers(0, ENVS, n)
    actions = rng.uniform(-1, 1, (n, horizon, ACTIONS)).astype(np.float32)
    place = np.stack([rows[:, None] + np.arange(horizon), np.broadcast_to(envs[:, None], (n, horizon))], -1)

    def predict_fn(params, where, action):
        return pixel_reward.place_rewards(REWARD, params, buffer, where, action)

    term = agent_preference.agent_value_term(
        REWARD, -0.5, jnp.asarray(place), jnp.asarray(actions), gamma, "discounted", False, predict_fn
    )
    loss, metrics = term(state.params, None, jax.random.PRNGKey(0))
    net = REWARD.network()
    values = []
    for m in range(REWARD.ensemble_size):
        member = jax.tree.map(lambda x, m=m: x[m], state.params)
        total = 0.0
        for i in range(n):
            r = np.asarray(net.apply(member, stacks[rows[i] : rows[i] + horizon, envs[i]], actions[i]))
            total += sum(gamma**h * float(r[h]) for h in range(horizon))
        values.append(total / n)
    np.testing.assert_allclose(float(loss), -0.5 * sum(values), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(metrics["agent_value"]), np.mean(values), rtol=1e-5, atol=1e-6)


@pytest.mark.heavy
def test_pixel_rebel_with_lambda_zero_is_pixel_pebble(run, rebel_run):
    trainer, state = rebel_run
    _, _, pebble, _ = run
    assert trainer.trace_count == 1
    pebble = jax.device_get(pebble)
    np.testing.assert_array_equal(state.reward.data.count, 12)
    for path in ("reward.params", "buffer.learned_reward", "agent.actor_params"):
        get = lambda tree, path=path: functools.reduce(getattr, path.split("."), tree)  # noqa: E731
        moved = []
        for ours, theirs in zip(jax.tree.leaves(get(state)), jax.tree.leaves(get(pebble)), strict=True):
            # lambda 0 is PEBBLE up to float rounding: another program (4 columns, not 2) rounds differently.
            np.testing.assert_allclose(ours[:SEEDS], theirs, rtol=1e-4, atol=1e-6, err_msg=path)
            moved.append(not np.allclose(ours[SEEDS:], theirs, rtol=1e-2, atol=1e-4))
        assert any(moved), path  # lambda -1 changes the reward, the relabelled buffer and the policy


SURF_MICRO = dataclasses.replace(
    MICRO, algo="surf", surf=SURFConfig(crop=1, pool_size=6, reward_update=2, ratio=1, threshold=0.6)
)


@pytest.mark.heavy
def test_pixel_surf_labels_central_steps_grows_its_pool_and_traces_once():
    trainer = Trainer(SURF_MICRO)
    init, round_fn, _ = compiled(trainer)
    state = init(seed_keys(0, SEEDS))
    start = jax.device_get(state.reward.params)
    for r in range(ROUNDS):
        state, m = round_fn(state, jnp.int32(r))
    assert trainer.trace_count == 1
    state, m = jax.device_get((state, m))
    np.testing.assert_array_equal(m["diverged"], 0.0)
    np.testing.assert_array_equal(m["reward_epochs"], SURF_MICRO.surf.reward_update)  # no early stop
    np.testing.assert_array_equal(state.reward.pool.count, 3 * SURF_MICRO.surf.pool_size)  # 3 sessions
    true, crop, horizon = state.buffer.true_reward, SURF_MICRO.surf.crop, SURF_MICRO.query.segment_length
    data, stored = state.reward.data, horizon + 2 * crop
    assert data.a.frames.shape[2] == stored + STACK - 1 and state.reward.pool.a.action.shape[2] == stored
    for seed in range(SEEDS):
        assert int(data.count[seed]) == 12
        buffer = jax.tree.map(lambda x, s=seed: x[s], state.buffer)
        for i in range(12):
            places = [
                _place_of(buffer, frames[seed, i], action[seed, i], stored)
                for frames, action in ((data.a.frames, data.a.action), (data.b.frames, data.b.action))
            ]
            # the teacher sees the central H of the stored H + 2c steps
            returns = [sum(float(true[seed, row + crop + h, env]) for h in range(horizon)) for row, env in places]
            assert data.labels[seed, i] == (1.0 if returns[0] < returns[1] else 0.0)
    leaves = zip(jax.tree.leaves(start), jax.tree.leaves(state.reward.params), strict=True)
    moved = [not np.allclose(a, b) for a, b in leaves]
    assert all(moved)


def test_cli_takes_pixel_preference_algos_and_refuses_sac_there():
    flags = ["--algo", "pebble", "--task", "walker_walk_pixels", "--seed-steps", "2000", "--pixel-reward.lr", "1e-4"]
    args = parse(["--preset", "tiny", *flags])
    cfg = args.config
    assert cfg.preference and cfg.pixels and cfg.pixel_reward.lr == 1e-4
    assert cfg.pixel_reward.member_loop  # the default on pixels; the flag restores the members' vmap
    assert not parse(["--preset", "tiny", *flags, "--pixel-reward.no-member-loop"]).config.pixel_reward.member_loop
    assert not cfg.pixel_reward.per_member_adam  # the summed step of every pixel run so far; the flag is SURF's
    assert parse(["--preset", "tiny", *flags, "--pixel-reward.per-member-adam"]).config.pixel_reward.per_member_adam
    assert cfg.feedback_start == cfg.train.seed_steps  # no unsupervised phase on pixels
    for algo in ("sac",):
        with pytest.raises(ConfigError, match="drqv2 or a preference method"):
            Config(algo=algo, env=EnvConfig(task="probe_point_pixels")).validate()
    for rebel in (
        AgentPreferenceConfig(form="penalty", normalize=True),
        AgentPreferenceConfig(source="replay", segment_length=4),
    ):
        dataclasses.replace(REBEL, rebel=rebel).validate()
    with pytest.raises(ConfigError, match="rebel.episodes"):
        dataclasses.replace(REBEL, rebel=AgentPreferenceConfig(episodes=2)).validate()  # 1 evaluation env
    with pytest.raises(ValueError, match="rebel.horizon"):
        Trainer(dataclasses.replace(REBEL, rebel=AgentPreferenceConfig(horizon=11)))  # episodes of 10


@pytest.mark.parametrize("task", ["walker", "cheetah"])
def test_the_surf_pixel_presets_are_surfs_commands_for_every_pixel_algo(task):
    """``--preset surf_pixels_<task>``: SURF's pixel commands (alinlab/SURF branch pixel, README.md:22 walker and
    :32 cheetah, num_interact and num_seed_steps in frames, which are 2 agent steps here), DrQ-v2's per-task
    agent, and a valid run for each pixel algo."""
    frames_per_step = 2
    surf_commands = {  # max_feedback, reward_batch, num_interact (frames), segment crop, lambda_u (unlabel weight)
        "walker": dict(labels=200, per_session=10, interval_frames=30_000, crop=2, weight=0.1),
        "cheetah": dict(labels=1000, per_session=25, interval_frames=20_000, crop=5, weight=1.0),
    }[task]
    name = {"walker": "walker_walk", "cheetah": "cheetah_run"}[task]
    for algo in ("pebble", "surf", "rebel", "drqv2"):
        cfg = parse(["--preset", f"surf_pixels_{task}", "--algo", algo]).config
        assert cfg.env.task == f"{name}_pixels" and cfg.drqv2 == task_config(name)
        assert cfg.train.seed_steps * frames_per_step == 4_000  # DrQ-v2's num_seed_frames (cfgs/config.yaml:11)
        fb = cfg.feedback
        assert (fb.labels, fb.per_session) == (surf_commands["labels"], surf_commands["per_session"])
        assert fb.interval * frames_per_step == surf_commands["interval_frames"]
        assert (cfg.surf.crop, cfg.surf.weight, cfg.surf.threshold) == (
            surf_commands["crop"],
            surf_commands["weight"],
            0.99,
        )
        assert cfg.surf.pool_size == 5 * fb.per_session  # inv_label_ratio 5
        assert (cfg.query.sampling, cfg.query.recent_episodes) == ("uniform", 20)


# -- REBEL's on-policy V on pixels: the evaluation episode's kept frames -------------------------------

ONPOLICY = dataclasses.replace(
    REBEL,
    train=dataclasses.replace(MICRO.train, eval_episodes=2),
    rebel=AgentPreferenceConfig(lam=-0.5, gamma=0.9, episodes=1, horizon=6),
)


@pytest.fixture(scope="module")
def two_episodes():
    """A pixel REBEL seed stepped through two episodes (vector steps 0..19), the evaluation env's
    observations after every step of the second, and the policy it followed."""
    trainer = Trainer(ONPOLICY)
    ts = jax.jit(trainer.init)(jax.random.key(3))
    step, length, n = jax.jit(trainer.vector_step), trainer.episode_length, trainer.num_train
    after = []
    for t in range(2 * length):
        if t == length:
            frozen = trainer.agent.policy(ts.agent)  # the second episode's evaluation policy
        ts, _ = step(ts, jnp.int32(t))
        if t >= length:
            after.append(np.asarray(ts.env.obs[n]))
    return trainer, jax.device_get(ts), np.stack(after), frozen


def test_pixel_onpolicy_value_is_the_discounted_sum_over_the_kept_evaluation_episode(two_episodes):
    trainer, ts, after, frozen = two_episodes
    horizon, gamma, lam = 6, 0.9, -0.5
    assert trainer.trajectory_size == (1, horizon)
    frames, actions, predict_fn = trainer.method.value_trajectories(trainer, ts, jax.random.key(0), jnp.int32(0))
    assert frames.shape == (1, horizon, SIZE, SIZE, 3) and frames.dtype == jnp.uint8
    frames, actions = np.asarray(frames[0]), np.asarray(actions[0])
    # The environment's own stacks: the reset frame three times, then each step's observation after the last.
    naive = np.stack([np.tile(frames[0], (1, 1, 3)), *after[: horizon - 1]])
    np.testing.assert_array_equal(naive[1:, ..., -3:], frames[1:])  # the kept frames are the newest ones
    np.testing.assert_array_equal(frame_replay.episode_stacks(frames[None], STACK)[0], naive)  # rebuilt stacks
    # The actions are the mean actions of the policy frozen at the episode's start, on those stacks.
    expected = trainer.mean_action(frozen, jnp.asarray(naive))
    np.testing.assert_allclose(actions, np.asarray(expected), rtol=1e-5, atol=1e-6)
    # V: each member's own apply on each step, looped in Python, discounted over the horizon.
    (_, term) = trainer.method.reward_terms(trainer, ts, jax.random.key(1), jnp.int32(0))
    loss, metrics = term(ts.reward.params, None, jax.random.key(2))
    net = REWARD.network()
    values = []
    for m in range(REWARD.ensemble_size):
        member = jax.tree.map(lambda x, m=m: x[m], ts.reward.params)
        values.append(sum(gamma**h * float(net.apply(member, naive[h], actions[h])) for h in range(horizon)))
    np.testing.assert_allclose(float(loss), lam * sum(values), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(float(metrics["agent_value"]), np.mean(values), rtol=1e-5, atol=1e-6)
    # The same V from the frames through the shared agent_value.
    got = agent_preference.agent_value(
        REWARD, ts.reward.params, frames[None], actions[None], gamma, "discounted", predict_fn
    )
    np.testing.assert_allclose(np.asarray(got), values, rtol=1e-5, atol=1e-6)


@pytest.mark.heavy  # make test checks this for the state-based term (test_surf_rebel.py)
def test_pixel_onpolicy_value_gradients_reach_only_the_reward_parameters(two_episodes):
    trainer, ts, _, _ = two_episodes
    frames, actions, predict_fn = trainer.method.value_trajectories(trainer, ts, jax.random.key(0), jnp.int32(0))
    params = ts.reward.params

    def loss_of(p, frames, actions):
        term = agent_preference.agent_value_term(REWARD, -0.5, frames, actions, 0.9, predict_fn=predict_fn)
        return term(p, None, None)[0]

    grads = jax.grad(loss_of, argnums=(0, 1, 2))(params, frames.astype(jnp.float32), actions)
    assert all(np.any(np.asarray(g)) for g in jax.tree.leaves(grads[0]))  # every reward leaf moves
    assert not np.any(np.asarray(grads[1])) and not np.any(np.asarray(grads[2]))  # the episode stays fixed


@pytest.mark.heavy  # make test checks the variants' term on states against NumPy (test_surf_rebel.py)
def test_pixel_penalty_form_normalized_matches_a_python_reference(two_episodes):
    """``rebel.form penalty`` with ``rebel.normalize`` on pixels: ``lambda * sum_m (V*_m - V_m) / s_m``."""
    _, ts, after, _ = two_episodes
    ts = jax.tree.map(jnp.asarray, ts)
    cfg = dataclasses.replace(
        ONPOLICY, rebel=dataclasses.replace(ONPOLICY.rebel, form="penalty", normalize=True, best_segments=2)
    )
    trainer = Trainer(cfg)
    horizon, gamma, lam, h = 6, 0.9, -0.5, MICRO.query.segment_length
    rng = np.random.default_rng(8)
    pairs = 3
    starts = rng.integers(0, 2, (2, pairs)) * trainer.episode_length + rng.integers(0, 10 - h + 1, (2, pairs))
    envs = rng.integers(0, ENVS, (2, pairs))
    seg_a = SegmentPlaces(jnp.asarray(starts[0], jnp.int32), jnp.asarray(envs[0], jnp.int32))
    seg_b = SegmentPlaces(jnp.asarray(starts[1], jnp.int32), jnp.asarray(envs[1], jnp.int32))
    reward = pixel_reward.add_labels(ts.reward, ts.buffer, seg_a, seg_b, jnp.ones(pairs), jnp.ones(pairs))
    ts = ts.replace(reward=reward)
    params, buffer = ts.reward.params, ts.buffer
    members = REWARD.ensemble_size
    # A BT minibatch: every member on the three pairs; its per-step rewards give the spread.
    tile = lambda x: jnp.tile(x[None], (members, 1))  # noqa: E731
    seg_m = [SegmentPlaces(tile(s.row), tile(s.env)) for s in (seg_a, seg_b)]
    seg_m = [_frames(buffer, seg, h) for seg in seg_m]
    ones = jnp.ones((members, pairs))
    bt = rm.with_rewards(REWARD, params, rm.PrefBatch(*seg_m, ones, ones, members=jnp.arange(members)))
    (_, term) = trainer.method.reward_terms(trainer, ts, jax.random.key(1), jnp.int32(0))
    loss, metrics = term(params, bt, jax.random.key(2))

    net = REWARD.network()
    member = [jax.tree.map(lambda x, m=m: x[m], params) for m in range(members)]

    def step_rewards(m, row, env, length):
        obs = frame_replay.row_stacks(buffer, jnp.arange(row, row + length), jnp.int32(env))
        return np.asarray(net.apply(member[m], obs, buffer.action[row : row + length, env]))

    frames, actions, _ = trainer.method.value_trajectories(trainer, ts, jax.random.key(0), jnp.int32(0))
    frames, actions = np.asarray(frames[0]), np.asarray(actions[0])
    naive = np.stack([np.tile(frames[0], (1, 1, 3)), *after[: horizon - 1]])
    segments = [(int(starts[s, i]), int(envs[s, i])) for s in range(2) for i in range(pairs)]
    mean_return = [np.mean([step_rewards(m, r, e, h).sum() for m in range(members)]) for r, e in segments]
    best = [segments[i] for i in np.argsort(mean_return)[::-1][:2]]
    expected = 0.0
    for m in range(members):
        value = sum(gamma**t * float(net.apply(member[m], naive[t], actions[t])) for t in range(horizon))
        per_step = np.mean(np.concatenate([step_rewards(m, r, e, h) for r, e in best]))
        optimal = per_step * sum(gamma**t for t in range(horizon))
        labelled = np.concatenate([step_rewards(m, r, e, h) for r, e in segments])
        expected += (optimal - value) / np.std(labelled)
    np.testing.assert_allclose(float(loss), lam * expected, rtol=1e-4, atol=1e-6)
    assert np.isfinite(float(metrics["optimal_value"]))


# -- pixel_reward.member_loop: the members' gradients one at a time equal the vmapped ones -------------


def _stored_labels(rng, count: int, capacity: int, horizon: int):
    """A fresh ensemble holding ``count`` random pairs of ``horizon``-step segments, and its frame replay."""
    buffer, _, _, _ = _filled_buffer(rng, 3 * LENGTH)
    shape = (SIZE, SIZE, 3 * STACK)
    state = pixel_reward.init(REWARD, jax.random.PRNGKey(11), shape, ACTIONS, capacity, horizon)

    def places(n):
        rows = rng.integers(0, 3, n) * LENGTH + rng.integers(0, LENGTH - horizon + 1, n)
        return SegmentPlaces(jnp.asarray(rows, jnp.int32), jnp.asarray(rng.integers(0, ENVS, n), jnp.int32))

    labels = jnp.asarray(rng.choice([0.0, 0.5, 1.0], count), jnp.float32)
    state = pixel_reward.add_labels(state, buffer, places(count), places(count), labels, jnp.ones(count))
    pool = pixel_reward.empty_store(6, horizon, shape, ACTIONS)
    pool = pixel_reward.append_segments(pool, buffer, places(6), places(6), jnp.zeros(6), jnp.ones(6))
    return state.replace(pool=pool), buffer, places


def _epoch_terms(kind: str, cfg: PixelRewardConfig, state, buffer, seg: SegmentPlaces, horizon: int):
    """The loss terms of ``kind`` passed to ``train_epoch`` on pixels (REBEL: its V term on the replay
    segments ``seg``, normalised)."""
    if kind == "surf":
        surf_cfg = SURFConfig(crop=1, ratio=1, threshold=0.5, weight=0.7)
        return rm.bt_loss(cfg, 1, crop_accuracy=True), surf.pseudo_label_term(cfg, surf_cfg, state.pool)
    if kind == "rebel":
        length = 3
        rows = pixel_reward.segment_rows(seg.row, length)
        where = jnp.stack([rows, jnp.broadcast_to(seg.env[:, None], rows.shape)], axis=-1)

        def predict_fn(params, place, action):
            return pixel_reward.place_rewards(cfg, params, buffer, place, action)

        actions = buffer.action[rows, where[..., 1]]
        term = agent_preference.agent_value_term(cfg, -0.5, where, actions, 0.9, normalize=True, predict_fn=predict_fn)
        return rm.bt_loss(cfg), term
    return (rm.bt_loss(cfg),)


def _session_loop(config: Config, loop: bool) -> Config:
    return dataclasses.replace(config, pixel_reward=dataclasses.replace(config.pixel_reward, session_loop=loop))


@pytest.mark.heavy  # make test-heavy: a layout of the compiled session (its compile); make test runs the session
def test_session_loop_leaves_no_convolution_grouped_over_the_columns():
    """``pixel_reward.session_loop``: the seed-vmapped session (select, teach, train the ensemble, relabel, reset
    the critic), batched, groups the reward members' convolutions over the columns (``feature_group_count`` a
    multiple of them; DrQ-v2's were 6.8x slower so on one H100); looped, no convolution is grouped over them (the
    members' forward passes loop too, ``pixel_reward.member_loop``, so none is grouped at all). Lowered only:
    nothing runs."""
    counts = {}
    for loop in (False, True):
        trainer = Trainer(_session_loop(REBEL, loop))
        state = jax.eval_shape(jax.vmap(trainer.init), seed_keys(0, SEEDS))
        session = jax.vmap(trainer.feedback_session, in_axes=(0, None, None, None))
        text = jax.jit(session).lower(state, jnp.bool_(True), jnp.int32(20), jnp.int32(0)).as_text()
        counts[loop] = [int(n) for n in re.findall(r"(?:feature|batch)_group_count = (\d+)", text)]
    assert len(counts[False]) == len(counts[True]) > 0
    assert set(counts[False]) == {1, SEEDS} and set(counts[True]) == {1}


# make test-heavy (a 28 s compile of the pixel round): make test still checks the looped session's values
# (test_session_loop_leaves_no_convolution_grouped_over_the_columns and the sessions' NumPy references).
@pytest.mark.heavy
def test_looped_session_writes_the_columns_in_place_not_a_stacked_copy_of_the_state():
    """``pixel_reward.session_loop`` inside the seed-vmapped, donated round (``pixel_feedback.loop_in_place``): the
    compiled round's working memory holds about one column's copy of SURF's pool (half of it at 2 seeds, and the
    pool dominates the state here), never a stacked copy of the whole pool beside the donated state, which
    ``sequential_vmap``'s ``lax.map`` outputs were (1.7x the pool here; 73 GiB for surf_cheetah at 3 seeds,
    whose GPU run died allocating 72.6 GiB). Compiled only: nothing runs."""
    config = dataclasses.replace(SURF_MICRO, surf=dataclasses.replace(SURF_MICRO.surf, pool_size=600))
    assert config.pixel_reward.session_loop
    trainer = Trainer(config)
    state = jax.eval_shape(jax.vmap(trainer.init), seed_keys(0, SEEDS))
    round_fn = jax.jit(jax.vmap(trainer.round, in_axes=(0, None)), donate_argnums=0)
    memory = round_fn.lower(state, jnp.int32(0)).compile().memory_analysis()
    pool = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(state.reward.pool))
    assert pool > 0.9 * sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(state))
    assert memory.temp_size_in_bytes < pool, (memory.temp_size_in_bytes, pool)


def test_members_forward_one_at_a_time_is_the_member_vmap():
    """``reward_model.over_members`` (``member_loop``): the looped members' rewards and segment returns are the
    vmapped ones, and each row is that member's own network."""
    rng = np.random.default_rng(21)
    state = pixel_reward.init(REWARD, jax.random.PRNGKey(3), (SIZE, SIZE, 3 * STACK), ACTIONS, 4, 2)
    obs = jnp.asarray(rng.integers(0, 256, (5, SIZE, SIZE, 3 * STACK)), jnp.uint8)
    action = jnp.asarray(rng.uniform(-1, 1, (5, ACTIONS)), jnp.float32)
    looped = rm.predict(REWARD, state.params, obs, action)
    vmapped = rm.predict(dataclasses.replace(REWARD, member_loop=False), state.params, obs, action)
    np.testing.assert_allclose(looped, vmapped, rtol=1e-5, atol=1e-6)
    net = REWARD.network()
    for m in range(REWARD.ensemble_size):
        member = jax.tree.map(lambda x, m=m: x[m], state.params)
        np.testing.assert_allclose(looped[m], net.apply(member, obs, action), rtol=1e-5, atol=1e-6)
    assert not np.allclose(looped[0], looped[1])


def test_bf16_members_are_the_float32_members_up_to_bfloat16_rounding():
    """``--pixel-reward.precision bf16`` (a speed setting) runs the members' convolutions and matmuls in bfloat16
    on the same float32 parameters: their rewards and their gradients are the float32 ones up to bf16's 8
    mantissa bits, and the parameters and Adam state stay float32."""
    rng = np.random.default_rng(22)
    exact, half = (dataclasses.replace(REWARD, precision=p) for p in ("highest", "bf16"))
    state = pixel_reward.init(half, jax.random.PRNGKey(4), (SIZE, SIZE, 3 * STACK), ACTIONS, 4, 2)
    assert {x.dtype for x in jax.tree.leaves((state.params, state.opt_state)) if x.ndim} == {jnp.dtype("float32")}
    obs = jnp.asarray(rng.integers(0, 256, (64, SIZE, SIZE, 3 * STACK)), jnp.uint8)
    action = jnp.asarray(rng.uniform(-1, 1, (64, ACTIONS)), jnp.float32)
    weights = jnp.asarray(rng.normal(size=64), jnp.float32)

    def objective(cfg, params):
        return jnp.sum(rm.predict(cfg, params, obs, action) * weights)

    rewards = {cfg.precision: rm.predict(cfg, state.params, obs, action) for cfg in (exact, half)}
    assert rewards["bf16"].dtype == jnp.float32 and float(jnp.std(rewards["highest"])) > 1e-3
    np.testing.assert_allclose(rewards["bf16"], rewards["highest"], atol=2e-2)
    assert not np.array_equal(rewards["bf16"], rewards["highest"])  # bf16 did round
    grads = [ravel_pytree(jax.grad(objective, 1)(cfg, state.params))[0] for cfg in (exact, half)]
    cosine = jnp.dot(grads[0], grads[1]) / (jnp.linalg.norm(grads[0]) * jnp.linalg.norm(grads[1]))
    assert float(cosine) > 0.99, float(cosine)


def test_session_loop_is_a_validated_setting():
    with pytest.raises(ConfigError, match="pixel_reward.session_loop"):
        PixelRewardConfig(session_loop=1).validate()
    with pytest.raises(ConfigError, match="pixel_reward.per_member_adam"):
        PixelRewardConfig(per_member_adam="yes").validate()
    assert PixelRewardConfig().session_loop and PixelRewardConfig().member_loop


@pytest.mark.heavy  # a second compile of the micro run (make test-heavy); make test checks the looped program's HLO
def test_session_loop_rounds_equal_the_batched_rounds(run):
    """The looped sessions (on in ``run``) inside the seed-vmapped round (cond, scan, donation) give the batched
    sessions' run up to float rounding: labels, ensemble, relabelled replay and policy."""
    trainer, _, looped, looped_metrics = run
    assert MICRO.pixel_reward.session_loop
    batched = Trainer(_session_loop(MICRO, False))
    init, round_fn, _ = compiled(batched)
    state = init(seed_keys(0, SEEDS))
    for r in range(ROUNDS):
        state, metrics = round_fn(state, jnp.int32(r))
    assert batched.trace_count == 1
    state = jax.device_get(state)
    np.testing.assert_array_equal(state.reward.data.labels, looped.reward.data.labels)
    close = functools.partial(np.testing.assert_allclose, rtol=1e-4, atol=1e-5)
    jax.tree.map(close, (state.reward.params, state.buffer.learned_reward, state.agent.actor_params),
                 (looped.reward.params, looped.buffer.learned_reward, looped.agent.actor_params))  # fmt: skip
    close(metrics["reward_correlation_replay"], looped_metrics[-1]["reward_correlation_replay"])


@pytest.mark.heavy  # three more compiles of the pixel reward's epoch (~20 s each on 2 cores): make test-heavy
@pytest.mark.parametrize("kind", ["pebble", "surf", "rebel"])
def test_member_loop_trains_the_ensemble_as_the_member_vmap(kind):
    horizon = 4
    state, buffer, places = _stored_labels(np.random.default_rng(9), 10, 12, horizon)  # 3 minibatches of 4
    value_segments = places(3)
    out = {}
    for loop in (False, True):
        cfg = dataclasses.replace(REWARD, member_loop=loop)
        terms = _epoch_terms(kind, cfg, state, buffer, value_segments, horizon)
        epoch = jax.jit(lambda st, key, cfg=cfg, terms=terms: rt.train_epoch(cfg, st, key, terms))
        out[loop] = jax.device_get(epoch(state, jax.random.PRNGKey(12)))
    (vmapped, metrics_vmap), (looped, metrics_loop) = out[False], out[True]
    for name in ("accuracy", "loss"):
        np.testing.assert_allclose(metrics_loop[name], metrics_vmap[name], rtol=1e-6, atol=1e-7, err_msg=name)
    pairs = zip(jax.tree.leaves(looped.params), jax.tree.leaves(vmapped.params), strict=True)
    for ours, theirs in pairs:
        np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-6)
    for ours, theirs in zip(jax.tree.leaves(looped.opt_state), jax.tree.leaves(vmapped.opt_state), strict=True):
        # Adam's moments: rounding near their zeros is relative to the leaf's scale, not the entry's.
        np.testing.assert_allclose(ours, theirs, rtol=1e-5, atol=1e-5 * np.max(np.abs(theirs)))
    moved = zip(jax.tree.leaves(state.params), jax.tree.leaves(looped.params), strict=True)
    assert all(not np.allclose(before, after) for before, after in moved)


def _torch_adam_after_each_backward(params, calls, lr, b1=0.9, b2=0.999, eps=1e-8):
    """NumPy reference of SURF's reward training steps under torch 1.9.0: one ``torch.optim.Adam`` over all
    members' parameters (``params``: (M, D)), and per call ``(member, gradient)``: ``opt.zero_grad()`` (zeros,
    not None, in torch 1.9), that member's backward, ``opt.step()`` (torch/optim/_functional.py ``adam``, which
    skips parameters whose gradient is None: members without a backward yet)."""
    p = np.array(params, np.float64)
    grad = [None] * len(p)
    step, m, v = np.zeros(len(p)), np.zeros_like(p), np.zeros_like(p)
    for member, g in calls:
        grad = [None if x is None else np.zeros_like(x) for x in grad]
        grad[member] = np.asarray(g, np.float64)
        for j, gj in enumerate(grad):
            if gj is None:
                continue
            step[j] += 1
            m[j] = b1 * m[j] + (1 - b1) * gj
            v[j] = b2 * v[j] + (1 - b2) * gj * gj
            denom = np.sqrt(v[j]) / np.sqrt(1 - b2 ** step[j]) + eps
            p[j] = p[j] - lr / (1 - b1 ** step[j]) * m[j] / denom
    return p, step


def _per_member(tree) -> np.ndarray:
    """(M, D): each member's leaves of ``tree`` (leading member axis) flattened side by side."""
    return np.concatenate([np.reshape(x, (np.shape(x)[0], -1)) for x in jax.tree.leaves(tree)], axis=1)


def test_member_adam_steps_as_torch_1_9_adam_after_each_members_backward():
    rng = np.random.default_rng(21)
    members, lr = 3, 1e-2
    params = {"w": jnp.asarray(rng.normal(size=(members, 3, 2)), jnp.float32), "b": jnp.zeros((members, 2))}
    calls = [
        (m, {"w": jnp.asarray(rng.normal(size=(3, 2)), jnp.float32), "b": jnp.asarray(rng.normal(size=2), jnp.float32)})
        for _ in range(4)
        for m in range(members)
    ]
    state, ours = rm.member_adam_init(params), params
    for m, g in calls:
        ours, state = rt.member_adam_step(lr, state, ours, g, jnp.int32(m))
    reference = [(m, _per_member(jax.tree.map(lambda x: x[None], g))[0]) for m, g in calls]
    expected, steps = _torch_adam_after_each_backward(_per_member(params), reference, lr)
    np.testing.assert_allclose(_per_member(ours), expected, rtol=1e-5, atol=1e-6)
    # 4 rounds of 3 members: 12, 11 and 10 steps (a member's first step is its own backward's).
    np.testing.assert_array_equal(state.count, steps)
    np.testing.assert_array_equal(state.count, [12, 11, 10])
    # One member alone is plain Adam (optax's).
    one = jax.tree.map(lambda x: x[:1], params)
    adam = optax.adam(lr)
    opt, mine, mine_state = adam.init(one), one, rm.member_adam_init(one)
    for _, g in calls[:3]:
        updates, opt = adam.update(jax.tree.map(lambda x: x[None], g), opt, one)
        one = optax.apply_updates(one, updates)
        mine, mine_state = rt.member_adam_step(lr, mine_state, mine, g, jnp.int32(0))
    jax.tree.map(functools.partial(np.testing.assert_allclose, rtol=1e-6, atol=1e-7), mine, one)


@pytest.mark.heavy  # two compiles of the pixel reward's epoch (~20 s each on 2 cores): make test-heavy
def test_per_member_adam_epoch_steps_each_member_after_its_own_backward():
    """``per_member_adam`` in ``train_epoch``, one minibatch of a fresh ensemble: member m's gradient is taken
    before any step has moved it (the members after m are not yet seen), so it is the summed-loss epoch's
    gradient, which that epoch's first Adam moment holds (``mu = (1 - b1) g``); from those the NumPy reference
    of torch's Adam gives every member's parameters (member 0 three steps, member 2 one)."""
    state, _, _ = _stored_labels(np.random.default_rng(22), REWARD.batch_size, REWARD.batch_size, 4)
    per_member = dataclasses.replace(REWARD, per_member_adam=True)
    fresh = state.replace(opt_state=rm.member_adam_init(state.params))
    key = jax.random.PRNGKey(23)
    summed, _ = jax.jit(lambda st: rt.train_epoch(REWARD, st, key))(state)
    ours, metrics = jax.jit(lambda st: rt.train_epoch(per_member, st, key))(fresh)
    np.testing.assert_array_equal(ours.opt_state.count, [3, 2, 1])
    grads = _per_member(summed.opt_state[0].mu) / 0.1
    calls = [(m, grads[m]) for m in range(REWARD.ensemble_size)]
    expected, _ = _torch_adam_after_each_backward(_per_member(state.params), calls, REWARD.lr)
    np.testing.assert_allclose(_per_member(ours.params), expected, rtol=1e-4, atol=1e-6)
    assert np.isfinite(metrics["loss"]) and 0.0 <= float(metrics["accuracy"]) <= 1.0


@pytest.mark.heavy  # with the member-loop test above; make test trains through the vmapped ensemble
def test_one_member_sees_its_own_rows_of_the_ensembles_draws():
    """What a member computes alone (``members=[m]``, the loop's view) is row m of the whole ensemble's
    BT term and pseudo-label term: the same pairs, crops and pool draws, not another member's."""
    horizon, members = 4, REWARD.ensemble_size
    state, buffer, places = _stored_labels(np.random.default_rng(10), 8, 8, horizon)
    seg_a, seg_b = (
        SegmentPlaces(*(jnp.reshape(x, (members, 4)) for x in (p.row, p.env))) for p in (places(12), places(12))
    )
    seg_a, seg_b = _frames(buffer, seg_a, horizon), _frames(buffer, seg_b, horizon)
    labels, weight = jnp.ones((members, 4)), jnp.ones((members, 4))
    key = jax.random.PRNGKey(13)
    pseudo = surf.pseudo_label_term(REWARD, SURFConfig(crop=1, threshold=0.5), state.pool)

    def losses(params, seg_a, seg_b, labels, weight, chosen):
        batch = rm.with_rewards(REWARD, params, rm.PrefBatch(seg_a, seg_b, labels, weight, members=chosen))
        loss, bt = rm.bt_loss(REWARD, 1, crop_accuracy=True)(params, batch, key)
        return loss, bt["accuracy_logits"], pseudo(params, batch, key)[0]

    whole, whole_logits, whole_pseudo = losses(state.params, seg_a, seg_b, labels, weight, jnp.arange(members))
    alone = []
    for m in range(members):
        row = lambda x, m=m: x[m : m + 1]  # noqa: E731
        args = jax.tree.map(row, (state.params, seg_a, seg_b, labels, weight))
        alone.append(losses(*args, jnp.asarray([m])))
        np.testing.assert_allclose(alone[m][1][0], whole_logits[m], rtol=1e-5, atol=1e-6)
        # Member 0's draws would give another member other logits: the check above can tell them apart.
        other = losses(*args, jnp.asarray([(m + 1) % members]))
        assert not np.allclose(other[1][0], whole_logits[m], rtol=1e-3, atol=1e-4)
        assert not np.isclose(float(other[2]), float(alone[m][2]), rtol=1e-3, atol=1e-5)
    np.testing.assert_allclose(sum(float(a[0]) for a in alone), float(whole), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(sum(float(a[2]) for a in alone), float(whole_pseudo), rtol=1e-5, atol=1e-6)


@pytest.mark.heavy  # about 90 s on 2 cores; make test checks the same term on a state pool (test_surf_rebel.py)
def test_pseudo_label_term_on_frames_matches_numpy_with_the_same_draws():
    """SURF's one pseudo-label term on a pool of frame segments (the state pool's check: test_surf_rebel.py): each
    member labels its drawn pool pairs from its own sums over the central steps and is trained on their crops."""
    state, _, _ = _stored_labels(np.random.default_rng(14), 4, 4, 4)
    pool, members, pairs = state.pool, REWARD.ensemble_size, 3
    surf_cfg = SURFConfig(crop=1, ratio=2, threshold=0.52, weight=0.7)
    zeros = jnp.zeros((members, pairs))
    batch = rm.PrefBatch(None, None, zeros, zeros + 1, jnp.arange(members))
    key = jax.random.PRNGKey(15)
    loss, metrics = jax.jit(surf.pseudo_label_term(REWARD, surf_cfg, pool))(state.params, batch, key)
    key_index, key_crop = jax.random.split(key)
    index = np.asarray(jax.random.randint(key_index, (members, 2 * pairs), 0, int(pool.count)))
    masks = np.stack(rm.crop_masks(key_crop, (members, 2 * pairs), 4, 1))
    net, expected, confident_count = REWARD.network(), 0.0, 0
    for m in range(members):
        member = jax.tree.map(lambda x, m=m: x[m], state.params)
        ce, confident = [], []
        for j, i in enumerate(index[m]):
            rewards = [
                np.asarray(net.apply(member, *pixel_reward.SegmentFrames(side.frames[i], side.action[i]).inputs()))
                for side in (pool.a, pool.b)
            ]
            central = rewards[1][1:3].sum() - rewards[0][1:3].sum()
            prob = 1 / (1 + np.exp(-np.float64(central)))
            assert abs(max(prob, 1 - prob) - surf_cfg.threshold) > 1e-5  # no float32 borderline case
            label, sure = float(prob > 0.5), float(max(prob, 1 - prob) >= surf_cfg.threshold)
            z = np.float64((rewards[1] * masks[1, m, j]).sum() - (rewards[0] * masks[0, m, j]).sum())
            ce.append(label * np.log1p(np.exp(-z)) + (1 - label) * np.log1p(np.exp(z)))
            confident.append(sure)
        expected += surf_cfg.weight * np.mean(np.array(ce) * np.array(confident))
        confident_count += sum(confident)
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(float(metrics["pseudo_fraction"]), confident_count / (members * 2 * pairs), rtol=1e-6)


def test_a_session_trains_the_traced_number_of_epochs():
    """``pixel_train`` passes ``max_epochs`` 0 for a session without new labels (SURF and B-Pref hold none once
    the budget is spent): no epoch runs and the members stay; a traced 2 runs exactly 2."""
    state, _, _ = _stored_labels(np.random.default_rng(5), 8, 12, 4)
    train = jax.jit(lambda st, most: rt.train(REWARD, st, jax.random.PRNGKey(3), None, most, float("inf")))
    for most in (0, 2):
        trained, metrics = train(state, jnp.int32(most))
        assert int(metrics["epochs"]) == most
        pairs = zip(jax.tree.leaves(state.params), jax.tree.leaves(trained.params), strict=True)
        moved = [not np.array_equal(a, b) for a, b in pairs]
        assert all(moved) if most else not any(moved)
