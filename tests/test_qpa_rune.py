"""QPA and RUNE (``rebel_jax.methods.qpa``, ``.rune``) against NumPy and Python-loop references of their own rules:
QPA's recent-episode query pool, its hybrid SAC batch, its cropped Bradley-Terry term and its early-stopped
sessions; RUNE's bonus and its decay. Then their settings on the command line, and one short run of each. Then the
same on pixel tasks (the frame ring's query pool, the hybrid n-step batch, the bonus, a short run of each), and pixel
PEBBLE through the method hooks against the trainer's calls before them."""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import types
from typing import Any

import chex
import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_pixel_preference import MICRO as PIXEL_MICRO
from test_pixel_preference import _filled_buffer as _filled_pixel_buffer
from test_pixel_preference import _place_of

from rebel_jax import train
from rebel_jax.agents import frame_replay, replay
from rebel_jax.agents.drqv2 import DrQV2Config
from rebel_jax.config import Config, EnvConfig, FeedbackConfig, SACConfig
from rebel_jax.methods import REGISTRY
from rebel_jax.methods.base import Method
from rebel_jax.methods.qpa import QPAConfig
from rebel_jax.methods.rune import RUNEConfig, bonus_weight
from rebel_jax.preference import pixel_reward, reward_model, reward_train
from rebel_jax.preference.feedback import StateFeedback
from rebel_jax.preference.pixel_feedback import PixelFeedback
from rebel_jax.preference.pixel_reward import PixelRewardConfig
from rebel_jax.preference.reward_model import PrefBatch, RewardConfig, Steps
from rebel_jax.run import cli, loop
from rebel_jax.train import Trainer

# A replay of 2 environments with 20-step episodes, 150 rows written of 200: 7 complete episodes per environment
# (rows 0-139) and the running ones (rows 140-149). Each cell's observation is its (row, env).
EPISODE, ENVS, ROWS, WRITTEN = 20, 2, 200, 150


def _marked_buffer(terminal: bool = False) -> replay.Buffer:
    """The replay above; ``terminal`` marks every 7th row terminal (a pattern a batch's discount must follow)."""
    buffer = replay.init(ROWS * ENVS, ENVS, 2, 1)
    row, env = np.meshgrid(np.arange(ROWS), np.arange(ENVS), indexing="ij")
    step = row % EPISODE
    return buffer.replace(
        obs=jnp.asarray(np.stack([row, env], -1), jnp.float32),
        next_obs=jnp.asarray(np.stack([row + 0.5, env], -1), jnp.float32),
        learned_reward=jnp.asarray(10 * row + env, jnp.float32),
        terminal=jnp.asarray(terminal & (row % 7 == 0), jnp.float32),
        truncated=jnp.asarray(step == EPISODE - 1, jnp.float32),
        episode_step=jnp.asarray(step, jnp.int32),
        ptr=jnp.int32(WRITTEN),
        size=jnp.int32(WRITTEN),
    )


def _fake_trainer(feedback: type, cfg: Config, **sizes) -> types.SimpleNamespace:
    """The trainer's parts a method's hooks read, without building a trainer: its config, ``sizes`` and
    ``sample_pairs`` (that of the real ``feedback`` part, state or pixel)."""
    part = types.SimpleNamespace(cfg=cfg, trainer=types.SimpleNamespace(cfg=cfg, **sizes))
    return types.SimpleNamespace(cfg=cfg, sample_pairs=functools.partial(feedback.sample_pairs, part), **sizes)


def _qpa_config(**qpa) -> Config:
    return Config(
        algo="qpa",
        env=EnvConfig(task="probe_point", num_envs=ENVS, episode_length=EPISODE),
        sac=SACConfig(batch_size=64),
        feedback=FeedbackConfig(labels=40, per_session=64),
        qpa=QPAConfig(**qpa),
    )


def test_qpa_queries_come_only_from_the_last_complete_episodes():
    cfg, length = _qpa_config(recent_episodes=3), 5
    trainer = _fake_trainer(StateFeedback, cfg, stored_length=length, episode_length=EPISODE)
    ts = types.SimpleNamespace(buffer=_marked_buffer())
    seg_a, seg_b = jax.jit(lambda key: REGISTRY["qpa"].query_segments(trainer, ts, key, True))(jax.random.key(3))
    # Reference (B-Pref's FIFO of complete episodes, last transition at step L - 1): the episodes ordered by
    # (last row, env), the last three kept; a segment starts at an offset in [0, L - H) of one of them.
    ends = [(r, e) for r in range(WRITTEN) for e in range(ENVS) if r % EPISODE == EPISODE - 1]
    allowed = {(r - EPISODE + 1, e) for r, e in ends[-3:]}
    seen = set()
    for seg in (seg_a, seg_b):
        rows, envs = np.asarray(seg.row), np.asarray(seg.env)
        np.testing.assert_array_equal(np.asarray(seg.obs[..., 0]), rows)
        for row, env in zip(rows, envs, strict=True):
            first = row[0] - row[0] % EPISODE
            assert (first, env[0]) in allowed and np.all(env == env[0])
            np.testing.assert_array_equal(row, row[0] + np.arange(length))
            assert row[0] - first < EPISODE - length
            seen.add((first, env[0]))
    assert seen == allowed  # 128 segments: each of the three episodes is drawn


@pytest.mark.parametrize("count,hybrid", [(0, False), (20, True), (40, False)], ids=["before", "during", "after"])
def test_qpa_hybrid_batch_draws_its_last_quarter_from_the_recent_rows_while_the_budget_lasts(count, hybrid):
    cfg = _qpa_config(recent_episodes=3, her_ratio=0.25)
    trainer = types.SimpleNamespace(cfg=cfg, episode_length=EPISODE)
    ts = types.SimpleNamespace(reward=types.SimpleNamespace(data=types.SimpleNamespace(count=jnp.int32(count))))
    buffer = _marked_buffer(terminal=True)
    keys = jax.random.split(jax.random.key(0), 300)
    batch = jax.jit(jax.vmap(lambda k: REGISTRY["qpa"].sample_batch(trainer, ts, buffer, k)))(keys)
    rows, envs = np.asarray(batch.obs[..., 0]).astype(int), np.asarray(batch.obs[..., 1]).astype(int)
    np.testing.assert_array_equal(np.asarray(batch.reward), 10 * rows + envs)
    np.testing.assert_array_equal(np.asarray(batch.next_obs[..., 0]), rows + 0.5)
    np.testing.assert_array_equal(np.asarray(batch.discount), 1.0 - (rows % 7 == 0))
    assert rows.min() >= 0 and rows.max() < WRITTEN and set(envs.ravel()) == {0, 1}
    # Reference: QPA's last 3 x 20 transitions are ceil(60 / 2) = 30 rows of the 2 environments; int(0.25 x 64) = 16.
    window = min(math.ceil(3 * EPISODE / ENVS), WRITTEN)
    recent = int(0.25 * 64)
    inside = rows >= WRITTEN - window
    share = window / WRITTEN  # of uniform rows inside the window
    tolerance = 4 * math.sqrt(share * (1 - share) / rows[:, :-recent].size)
    assert abs(inside[:, :-recent].mean() - share) < tolerance
    if hybrid:
        assert inside[:, -recent:].all()
        assert abs(inside.mean() - (recent + (64 - recent) * share) / 64) < tolerance
    else:
        assert abs(inside[:, -recent:].mean() - share) < 4 * math.sqrt(share * (1 - share) / rows[:, -recent:].size)


def _np_log_sigmoid(z):
    return -np.logaddexp(0.0, -z)


def _init_params(rcfg: RewardConfig, seed: int, obs_size: int, act_size: int):
    return jax.jit(lambda key: reward_model.init(rcfg, key, obs_size, act_size, 1).params)(jax.random.key(seed))


@functools.partial(jax.jit, static_argnums=0)
def _member_rewards(rcfg: RewardConfig, params, obs, action):
    """Each member's rewards of its own (obs, action) (leading member axis on all three): (M, ...)."""
    return jax.vmap(rcfg.network().apply)(params, obs, action)


def _qpa_terms(rcfg: RewardConfig, qpa: QPAConfig):
    """QPA's reward terms on a state task."""
    cfg = dataclasses.replace(_qpa_config(), qpa=qpa)
    return REGISTRY["qpa"].reward_terms(types.SimpleNamespace(cfg=cfg, reward_cfg=rcfg), None, None, None)


def test_augmented_bt_loss_is_the_mean_cross_entropy_over_every_crop_of_every_pair():
    rcfg, qpa = RewardConfig(ensemble_size=2, hidden=16, depth=2), QPAConfig(data_aug_ratio=3, crop=2)
    members, pairs, length = 2, 5, 12
    params, rng = _init_params(rcfg, 1, 3, 2), np.random.default_rng(2)
    obs_a, obs_b = (jnp.asarray(rng.normal(size=(members, pairs, length, 3)), jnp.float32) for _ in "ab")
    act_a, act_b = (jnp.asarray(rng.normal(size=(members, pairs, length, 2)), jnp.float32) for _ in "ab")
    batch = PrefBatch(
        a=Steps(obs_a, act_a),
        b=Steps(obs_b, act_b),
        labels=jnp.array([[1.0, 0.0, 0.5, 1.0, 0.0], [0.0, 0.0, 1.0, 1.0, 0.5]]),
        weight=jnp.array([[1.0, 1.0, 1.0, 1.0, 0.0], [1.0] * 5]),  # one padded pair
        members=jnp.arange(members),
    )
    batch = jax.jit(reward_model.with_rewards, static_argnums=0)(rcfg, params, batch)
    key = jax.random.key(4)
    (term,) = _qpa_terms(rcfg, qpa)
    loss, metrics = jax.jit(term)(params, batch, key)
    masks = jax.jit(lambda key: reward_model.crop_masks(key, (members, 3, pairs), length, qpa.crop))(key)
    mask_a, mask_b = (np.asarray(m) for m in masks)
    rewards_a = np.asarray(_member_rewards(rcfg, params, obs_a, act_a), np.float64)
    rewards_b = np.asarray(_member_rewards(rcfg, params, obs_b, act_b), np.float64)
    expected, correct, counted = 0.0, 0.0, 0.0
    for m in range(members):
        reward_a, reward_b = rewards_a[m], rewards_b[m]
        labels, weight = np.asarray(batch.labels[m]), np.asarray(batch.weight[m])
        total = 0.0
        for r in range(3):
            for b in range(pairs):
                z = np.sum(reward_b[b] * mask_b[m, r, b]) - np.sum(reward_a[b] * mask_a[m, r, b])
                y = labels[b]
                total += weight[b] * -(y * _np_log_sigmoid(z) + (1 - y) * _np_log_sigmoid(-z))
                if y != 0.5:
                    correct += weight[b] * ((z > 0) == (y > 0.5))
                    counted += weight[b]
        expected += total / (3 * weight.sum())
    np.testing.assert_allclose(float(loss), expected, rtol=1e-5)
    np.testing.assert_allclose(float(metrics["bt_accuracy"]), correct / counted, rtol=1e-6)
    plain = jax.jit(reward_model.bt_loss(rcfg))(params, batch, key)[0]
    (uncropped,) = _qpa_terms(rcfg, dataclasses.replace(qpa, data_aug_ratio=0))
    once = jax.jit(uncropped)(params, batch, key)[0]
    assert float(once) == float(plain)


def test_qpa_crops_are_qpa_s_35_to_45_of_50_steps_one_length_per_pair():
    # QPA's get_cropping_mask: length = randint(S - 15, S - 5 + 1), each segment's start randint(0, S + 1 - length).
    masks = jax.jit(lambda key: reward_model.crop_masks(key, (3000,), 50, QPAConfig().crop))(jax.random.key(5))
    mask_a, mask_b = (np.asarray(m) for m in masks)
    lengths = mask_a.sum(-1)
    np.testing.assert_array_equal(lengths, mask_b.sum(-1))
    assert set(lengths.astype(int)) == set(range(35, 46))
    for mask in (mask_a, mask_b):
        starts = mask.argmax(-1)
        inside = (np.arange(50) >= starts[:, None]) & (np.arange(50) < (starts + lengths)[:, None])
        np.testing.assert_array_equal(mask, inside)  # one run from the start
        assert starts.min() == 0 and np.all(starts <= 50 - lengths)


@flax.struct.dataclass
class _State:
    reward: Any
    method: Any = None


@functools.partial(jax.jit, static_argnums=(0, 1, 2))
def _labelled_state(rcfg: RewardConfig, count: int, length: int) -> reward_model.RewardState:
    """A fresh model with ``count`` stored pairs of random segments, labelled by a teacher it can learn."""
    state = reward_model.init(rcfg, jax.random.key(6), 3, 1, length)
    k = jax.random.split(jax.random.key(7), 4)
    obs_a, obs_b = (jax.random.normal(k[i], (count, length, 3)) for i in (0, 1))
    seg_a, seg_b = (
        types.SimpleNamespace(obs=o, action=jax.random.normal(k[i], (count, length, 1)))
        for o, i in ((obs_a, 2), (obs_b, 3))
    )
    labels = (obs_b[..., 0].sum(-1) > obs_a[..., 0].sum(-1)).astype(jnp.float32)
    return reward_model.add_labels(state, seg_a, seg_b, labels, jnp.ones(count))


@pytest.mark.parametrize("stop,kept", [(0.81, 12), (2.0, 12), (0.81, 0)], ids=["stops", "never-stops", "no-labels"])
def test_qpa_session_runs_one_step_at_a_time_until_the_running_accuracy_reaches_the_stop(stop, kept):
    rcfg = RewardConfig(ensemble_size=1, hidden=16, depth=2, batch_size=8, lr=1e-2)
    qpa = QPAConfig(reward_update=20, stop_accuracy=stop, data_aug_ratio=2, crop=1)
    cfg = dataclasses.replace(_qpa_config(), qpa=qpa)
    stored = _labelled_state(rcfg, 12, 8)
    trainer = types.SimpleNamespace(cfg=cfg, reward_cfg=rcfg, reward_optimizer=None)
    keys = {"terms": jax.random.key(8), "train": jax.random.key(9)}
    method = REGISTRY["qpa"]
    session = jax.jit(lambda s: method.train_reward(trainer, _State(None), s, keys, jnp.int32(kept), None, True))
    state, method_state, metrics = session(stored)
    assert method_state is None  # QPA has no state of its own
    # Reference: QPA's loop (train_QPA.py:143, reward_model.py:707-762) with this project's one-step training.
    most = math.ceil(20 * 12 / 8) if kept else 0
    terms = _qpa_terms(rcfg, qpa)
    one_step = jax.jit(lambda s, key: reward_train.train_iterations(rcfg, s, key, terms, jnp.ones((), jnp.int32)))
    expected, accuracy, steps = stored, 0.0, 0
    for step in range(most):
        expected, m = one_step(expected, jax.random.fold_in(keys["train"], step))
        accuracy, steps = accuracy + float(m["train_accuracy"]), step + 1
        if accuracy / steps >= stop:
            break
    assert int(metrics["epochs"]) == steps and (steps < most) == (stop < 1 and kept > 0)
    chex.assert_trees_all_close(state.params, expected.params, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(float(metrics["train_accuracy"]), accuracy / max(steps, 1), rtol=1e-5)


def test_qpa_s_meta_world_session_is_pebble_s_epochs_over_whole_segments():
    """``reward_session='epochs'`` (QPA's Meta-World branch, train_QPA.py:136-141: ``train_reward``, no crops) trains
    as the base method's session does, with the crop settings ignored."""
    rcfg = RewardConfig(ensemble_size=1, hidden=16, depth=2, batch_size=8, lr=1e-2, max_epochs=6, stop_accuracy=0.9)
    qpa = QPAConfig(reward_session="epochs", data_aug_ratio=4, crop=1)
    cfg = dataclasses.replace(_qpa_config(), qpa=qpa)
    stored = _labelled_state(rcfg, 12, 8)
    trainer = types.SimpleNamespace(cfg=cfg, reward_cfg=rcfg, reward_optimizer=None)
    keys = {"terms": jax.random.key(8), "train": jax.random.key(9)}

    def session(method):
        return jax.jit(lambda s: method.train_reward(trainer, _State(None), s, keys, jnp.int32(12), None, True))

    ours, _, metrics = session(REGISTRY["qpa"])(stored)
    pebble, _, expected = session(Method())(stored)
    chex.assert_trees_all_close(ours.params, pebble.params)
    assert int(metrics["epochs"]) == int(expected["epochs"]) >= 1
    assert [type(t) for t in REGISTRY["qpa"].reward_terms(trainer, _State(None), keys["terms"], None)] == [
        type(t) for t in Method().reward_terms(trainer, _State(None), keys["terms"], None)
    ]


def test_rune_adds_the_members_spread_weighted_by_a_decaying_beta():
    rcfg, rune = RewardConfig(ensemble_size=3, hidden=16, depth=2), RUNEConfig(beta_0=0.3, rho=1e-3)
    cfg = dataclasses.replace(_qpa_config(), algo="rune", rune=rune)
    params, rng = _init_params(rcfg, 10, 2, 1), np.random.default_rng(11)
    trainer = types.SimpleNamespace(cfg=cfg, reward_members=functools.partial(reward_model.predict, rcfg))
    ts = types.SimpleNamespace(reward=types.SimpleNamespace(params=params))
    obs, action, reward = (jnp.asarray(rng.normal(size=shape), jnp.float32) for shape in ((32, 2), (32, 1), (32,)))
    batch = replay.Transition(obs, action, reward, jnp.zeros((32, 2)), jnp.ones(32))
    members = np.asarray(_member_rewards(rcfg, params, *(jnp.broadcast_to(x, (3, *x.shape)) for x in (obs, action))))
    members = members.astype(np.float64)
    spread = np.sqrt(np.mean((members - members.mean(0)) ** 2, axis=0))  # NumPy's std, ddof 0, as RUNE's np.std
    batch_reward = jax.jit(lambda t: REGISTRY["rune"].batch_reward(trainer, ts, batch, t).reward)
    for t in (0, 7, 250):
        beta = 0.3 * (1 - 1e-3) ** (t * ENVS)  # RUNE's beta(step), step = environment steps
        np.testing.assert_allclose(
            np.asarray(batch_reward(jnp.int32(t * ENVS))), np.asarray(reward) + beta * spread, rtol=1e-5, atol=1e-7
        )
    # The weight far into a run, where (1 - rho) rounded to float32 would be off by a few percent.
    steps = np.array([0, 1, 12_345, 1_000_000])
    weights = jax.jit(jax.vmap(lambda step: bonus_weight(RUNEConfig(), step)))(jnp.asarray(steps, jnp.int32))
    np.testing.assert_allclose(np.asarray(weights), 0.05 * (1 - 1e-5) ** steps.astype(np.float64), rtol=1e-5)


TINY = ["--preset", "tiny", "--task", "probe_point", "--no-progress", "--no-tensorboard"]
BAD = {
    "rune-one-member": (["--algo", "rune", "--reward.ensemble-size", "1"], ["reward.ensemble_size=1", ">= 2"]),
    "rune-one-pixel-member": (
        ["--algo", "rune", "--task", "probe_point_pixels", "--pixel-reward.ensemble-size", "1"],
        ["pixel_reward.ensemble_size=1", ">= 2"],
    ),
    "qpa-with-pebble": (["--algo", "pebble", "--qpa.her-ratio", "0.3"], ["qpa settings", "qpa only with --algo qpa"]),
    "rune-with-qpa": (["--algo", "qpa", "--rune.rho", "0.1"], ["rune settings", "rune only with --algo rune"]),
    "qpa-crop": (["--algo", "qpa", "--qpa.crop", "9"], ["qpa.crop=9", "3 crop < 25"]),
    "qpa-her-ratio": (["--algo", "qpa", "--qpa.her-ratio", "1.5"], ["qpa.her_ratio=1.5", "[0, 1]"]),
    "rune-rho": (["--algo", "rune", "--rune.rho", "1"], ["rune.rho=1.0", "[0, 1)"]),
}


@pytest.mark.parametrize("argv,expected", BAD.values(), ids=BAD.keys())
def test_bad_or_unused_qpa_and_rune_settings_are_one_line(tmp_path, monkeypatch, capsys, argv, expected):
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exit_info:
        cli.main([*TINY, *argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert exit_info.value.code == 2 and len(err) == 1 and err[0].startswith("error: "), err
    assert all(part in err[0] for part in expected), err[0]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    "method,flags",
    [
        ("qpa", ("--qpa.recent-episodes", "--qpa.her-ratio", "--qpa.data-aug-ratio")),
        ("rune", ("--rune.beta-0", "--rune.rho")),
    ],
)
def test_each_method_s_help_lists_its_settings_and_not_the_other_s(capsys, method, flags):
    with pytest.raises(SystemExit) as exit_info:
        cli.main([method, "--help"])
    out = capsys.readouterr().out
    assert exit_info.value.code == 0
    assert "qpa, rune" in out  # the methods
    for flag in flags:
        assert flag in out
    other = "--rune." if method == "qpa" else "--qpa."
    assert other not in out


def test_the_qpa_preset_is_qpa_s_walker_walk_command():
    # huxiao09/QPA@7e9e49e, run_QPA.sh:5 and config/train_QPA.yaml, config/agent/sac.yaml.
    cfg = cli.parse(["--preset", "qpa"]).config.validate()
    assert (cfg.algo, cfg.env.task, cfg.train.total_steps, cfg.train.seed_steps, cfg.pretrain.steps) == (
        "qpa",
        "walker_walk",
        500_000,
        1_000,
        9_000,
    )
    assert (cfg.feedback.labels, cfg.feedback.queries, cfg.feedback.interval, cfg.feedback.budget) == (
        100,
        10,
        20_000,
        "asked",
    )
    assert (cfg.reward.ensemble_size, cfg.reward.lr, cfg.reward.batch_size, cfg.reward.output) == (1, 3e-4, 128, "tanh")
    assert (cfg.query.segment_length, cfg.pretrain.k, cfg.pretrain.reset_updates) == (50, 5, 100)
    assert (cfg.sac.actor_lr, cfg.sac.critic_lr, cfg.sac.batch_size, cfg.sac.utd) == (5e-4, 5e-4, 1024, 1.0)
    assert cfg.qpa == QPAConfig(recent_episodes=10, her_ratio=0.5, data_aug_ratio=20, reward_update=2000)


def test_the_qpa_metaworld_preset_is_qpa_s_drawer_open_command():
    # huxiao09/QPA@7e9e49e, run_QPA.sh:35 (drawer-open), config/train_QPA.yaml, config/agent/sac.yaml.
    cfg = cli.parse(["--preset", "qpa_metaworld"]).config.validate()
    assert (cfg.algo, cfg.env.task, cfg.env.episode_length, cfg.train.total_steps, cfg.pretrain.steps) == (
        "qpa",
        "metaworld_drawer-open",
        500,
        1_000_000,
        9_000,
    )
    assert (cfg.feedback.labels, cfg.feedback.queries, cfg.feedback.interval, cfg.feedback.budget) == (
        3_000,
        30,
        5_000,
        "asked",
    )
    assert (cfg.reward.ensemble_size, cfg.reward.max_epochs, cfg.reward.stop_accuracy, cfg.reward.batch_size) == (
        1,
        200,
        0.97,
        128,
    )
    assert (cfg.query.segment_length, cfg.query.sampling, cfg.train.eval_episodes) == (50, "uniform", 100)
    assert (cfg.sac.actor_lr, cfg.sac.critic_lr, cfg.sac.hidden, cfg.sac.depth, cfg.sac.batch_size) == (
        1e-4,
        1e-4,
        1024,
        2,
        1024,
    )
    assert (cfg.qpa.recent_episodes, cfg.qpa.her_ratio, cfg.qpa.reward_session) == (30, 0.5, "epochs")


# Rounds of 20 vector steps on the probe task: 20 seed steps, 60 of pre-training, sessions at env steps 80, 120 and
# 160 (4 pairs each), 200 steps in all.
MICRO_FLAGS = (
    "--preset tiny --task probe_point --num-envs 2 --episode-length 40 --sac.hidden 16 --sac.batch-size 16"
    " --sac.utd 0.5 --total-steps 200 --seed-steps 20 --steps-per-round 40 --eval-every 40 --eval-episodes 1"
    " --feedback.labels 12 --feedback.per-session 4 --feedback.interval 40 --reward.hidden 32 --reward.batch-size 16"
    " --query.segment-length 8"
    " --pretrain.steps 60 --pretrain.chunk-size 64 --seeds 2 --no-tensorboard --no-progress"
).split()
METHOD_FLAGS = {
    "qpa": "--algo qpa --qpa.recent-episodes 2 --qpa.reward-update 20 --qpa.data-aug-ratio 4 --qpa.crop 1",
    "rune": "--algo rune --rune.beta-0 0.5 --rune.rho 1e-3",
}


@pytest.mark.parametrize("method", METHOD_FLAGS)
def test_a_short_run_through_the_cli_traces_its_round_once_and_uses_the_budget(method, tmp_path, monkeypatch):
    def traced_once(trainer, sharding=None):
        chex.clear_trace_counter()
        trainer.round = chex.assert_max_traces(trainer.round, n=1)
        return train.compiled(trainer, sharding)

    monkeypatch.setattr(loop, "compiled", traced_once)
    cli.main([*MICRO_FLAGS, *METHOD_FLAGS[method].split(), "--run-dir", str(tmp_path / "run")])
    rows = [json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()]
    assert len(rows) == 5 and all(row["status"] == "ok" for row in rows)
    assert rows[-1]["labels_used"] == [12.0, 12.0]


# -- pixel tasks ---------------------------------------------------------------------------------------------------
# A frame ring of 40 rows of 2 environments with 6-step episodes, written for 57 vector steps: it holds writes 17-56,
# so the wrap cuts episode 2 (writes 12-17), episodes 3-8 are complete and episode 9 runs (writes 54-56). Each write's
# action is (write, env), its learned reward 10 write + env.
PIX_LENGTH, PIX_ENVS, PIX_ROWS, PIX_WRITES, PIX_SIZE, NSTEP, GAMMA = 6, 2, 40, 57, 4, 3, 0.9


@functools.cache
def _marked_ring() -> tuple[frame_replay.FrameBuffer, np.ndarray, np.ndarray]:
    """The ring above, and the stacks the environments showed before and after each write: (write, env, H, W, 9)."""
    rng = np.random.default_rng(12)
    buffer = frame_replay.init(PIX_ROWS * PIX_ENVS, PIX_ENVS, (PIX_SIZE, PIX_SIZE, 3), 2, PIX_LENGTH, 3, True)
    add, envs = jax.jit(frame_replay.add), np.arange(PIX_ENVS)
    obs, next_obs = [], []
    for t in range(PIX_WRITES):
        step = t % PIX_LENGTH
        if step == 0:
            stack = np.concatenate([rng.integers(0, 256, (PIX_ENVS, PIX_SIZE, PIX_SIZE, 3), np.uint8)] * 3, -1)
        new = rng.integers(0, 256, (PIX_ENVS, PIX_SIZE, PIX_SIZE, 3), np.uint8)
        nxt = np.concatenate([stack[..., 3:], new], -1)
        row = frame_replay.FrameStep(
            obs=jnp.asarray(stack),
            action=jnp.asarray(np.stack([np.full(PIX_ENVS, t), envs], -1), jnp.float32),
            next_obs=jnp.asarray(nxt),
            learned_reward=jnp.asarray(10.0 * t + envs, jnp.float32),
            terminal=jnp.zeros(PIX_ENVS),
            truncated=jnp.full(PIX_ENVS, float(step == PIX_LENGTH - 1)),
            episode_step=jnp.int32(step),
            true_reward=jnp.zeros(PIX_ENVS),
        )
        buffer = add(buffer, row)
        obs.append(stack)
        next_obs.append(nxt)
        stack = nxt
    return buffer, np.stack(obs), np.stack(next_obs)


def _pixel_config(algo: str, **parts) -> Config:
    return Config(
        algo=algo,
        env=EnvConfig(task="probe_point_pixels", num_envs=PIX_ENVS, episode_length=2 * PIX_LENGTH),
        drqv2=DrQV2Config(batch_size=64, nstep=NSTEP, gamma=GAMMA),
        feedback=FeedbackConfig(labels=40, per_session=64),
        **parts,
    )


@pytest.mark.parametrize("first", [True, False], ids=["first-session", "later-session"])
def test_qpa_pixel_queries_come_only_from_the_last_complete_episodes_of_the_ring(first):
    cfg, horizon = _pixel_config("qpa", qpa=QPAConfig(recent_episodes=3)), 4
    trainer = _fake_trainer(PixelFeedback, cfg, stored_length=horizon, episode_length=PIX_LENGTH)
    buffer, _, _ = _marked_ring()
    ts = types.SimpleNamespace(buffer=buffer)
    query_segments = jax.jit(lambda key: REGISTRY["qpa"].query_segments(trainer, ts, key, first))
    seg_a, seg_b = query_segments(jax.random.key(13))
    # Reference (B-Pref's FIFO of complete episodes): the episodes all of whose writes the ring holds, ordered by
    # (episode, env), the last three; a segment is H consecutive writes of one of them.
    held = range(PIX_WRITES - PIX_ROWS, PIX_WRITES)
    episodes = [(b, e) for b in range(PIX_WRITES // PIX_LENGTH + 1) for e in range(PIX_ENVS)]
    complete = [(b, e) for b, e in episodes if all(b * PIX_LENGTH + h in held for h in range(PIX_LENGTH))]
    allowed, actions = set(complete[-3:]), np.asarray(buffer.action)
    seen, offsets = set(), set()
    for seg in (seg_a, seg_b):
        assert seg.row.shape == (64,)
        for row, env in zip(np.asarray(seg.row), np.asarray(seg.env), strict=True):
            writes = actions[(row + np.arange(horizon)) % PIX_ROWS, env, 0].astype(int)  # the segment's writes
            np.testing.assert_array_equal(writes, writes[0] + np.arange(horizon))
            episode = writes[0] // PIX_LENGTH
            assert (episode, env) in allowed and writes[-1] // PIX_LENGTH == episode
            seen.add((episode, env))
            offsets.add(writes[0] % PIX_LENGTH)
    assert seen == allowed and offsets == set(range(PIX_LENGTH - horizon + 1))  # every episode, every start


@pytest.mark.parametrize("count,hybrid", [(0, False), (20, True), (40, False)], ids=["before", "during", "after"])
def test_qpa_pixel_batch_draws_its_last_quarter_from_the_recent_valid_rows_while_the_budget_lasts(count, hybrid):
    cfg = _pixel_config("qpa", qpa=QPAConfig(recent_episodes=3, her_ratio=0.25))
    trainer = types.SimpleNamespace(cfg=cfg, episode_length=PIX_LENGTH)
    ts = types.SimpleNamespace(reward=types.SimpleNamespace(data=types.SimpleNamespace(count=jnp.int32(count))))
    buffer, obs, next_obs = _marked_ring()
    keys = jax.random.split(jax.random.key(14), 200)
    batch = jax.jit(jax.vmap(lambda k: REGISTRY["qpa"].sample_batch(trainer, ts, buffer, k)))(keys)
    writes, envs = (np.asarray(batch.action[..., i]).astype(int) for i in (0, 1))
    # Reference (DrQ-v2's n-step windows; QPA's last 3 x 6 transitions are ceil(18 / 2) = 9 rows of 2 environments):
    # a start is valid when its 3 steps are held writes of one episode; the recent ones are among the last 9 writes.
    held = range(PIX_WRITES - PIX_ROWS, PIX_WRITES)
    valid = {t for t in held if t + NSTEP - 1 in held and t % PIX_LENGTH + NSTEP - 1 < PIX_LENGTH}
    recent = {t for t in valid if t >= PIX_WRITES - math.ceil(3 * PIX_LENGTH / PIX_ENVS)}
    rewards = 10.0 * np.arange(PIX_WRITES)[:, None] + np.arange(PIX_ENVS)
    returns = sum(GAMMA**i * rewards[writes + i, envs] for i in range(NSTEP))
    np.testing.assert_allclose(np.asarray(batch.reward), returns, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(batch.discount), GAMMA**NSTEP, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(batch.obs), obs[writes, envs])
    np.testing.assert_array_equal(np.asarray(batch.next_obs), next_obs[writes + NSTEP - 1, envs])
    assert set(writes.ravel()) <= valid and set(envs.ravel()) == {0, 1}
    last = int(0.25 * 64)
    inside, share = np.isin(writes, list(recent)), len(recent) / len(valid)  # share: of uniform starts
    tolerance = 4 * math.sqrt(share * (1 - share) / writes[:, :-last].size)
    assert abs(inside[:, :-last].mean() - share) < tolerance
    if hybrid:
        assert inside[:, -last:].all() and set(writes[:, -last:].ravel()) == recent
    else:
        assert abs(inside[:, -last:].mean() - share) < 4 * math.sqrt(share * (1 - share) / writes[:, -last:].size)


def test_rune_pixel_bonus_is_the_members_spread_at_the_first_step_of_each_n_step_transition():
    rcfg = PixelRewardConfig(ensemble_size=3, hidden=8)
    cfg = _pixel_config("rune", rune=RUNEConfig(beta_0=0.3, rho=1e-3), pixel_reward=rcfg)
    buffer, _, _ = _marked_ring()
    init = jax.jit(lambda key: pixel_reward.init(rcfg, key, (PIX_SIZE, PIX_SIZE, 9), 2, 4, 4).params)
    params, rng = init(jax.random.key(15)), np.random.default_rng(16)
    batch = jax.jit(lambda key: frame_replay.sample(buffer, key, 32, True, NSTEP, GAMMA))(jax.random.key(17))
    batch = batch.replace(reward=jnp.asarray(rng.normal(size=32), jnp.float32))  # the n-step learned returns
    trainer = types.SimpleNamespace(cfg=cfg, reward_members=functools.partial(reward_model.predict, rcfg))
    ts = types.SimpleNamespace(reward=types.SimpleNamespace(params=params))
    apply = jax.jit(rcfg.network().apply)
    members = [np.asarray(apply(jax.tree.map(lambda x, m=m: x[m], params), batch.obs, batch.action)) for m in range(3)]
    members = np.stack(members).astype(np.float64)  # (M, B): each member's reward of (s_t, a_t)
    spread = np.sqrt(np.mean((members - members.mean(0)) ** 2, axis=0))  # NumPy's std, ddof 0, as RUNE's
    assert spread.min() > 0
    batch_reward = jax.jit(lambda step: REGISTRY["rune"].batch_reward(trainer, ts, batch, step))
    for step in (0, 14, 3000):
        got = batch_reward(jnp.int32(step))
        beta = 0.3 * (1 - 1e-3) ** step  # RUNE's beta(step), step = the seed's agent steps so far
        np.testing.assert_allclose(
            np.asarray(got.reward), np.asarray(batch.reward) + beta * spread, rtol=1e-5, atol=1e-7
        )
        chex.assert_trees_all_equal(got.replace(reward=batch.reward), batch)  # only the reward changes


def _select_directly(trainer: Trainer, ts, key: jax.Array, first):
    """The pixel trainer's call for its queries before the method hooks."""
    cfg = trainer.cfg
    return pixel_reward.select(
        cfg.pixel_reward,
        key,
        ts.reward.params,
        ts.buffer,
        cfg.feedback.queries,
        trainer.stored_length,
        trainer.episode_length,
        cfg.query.recent_episodes,
        cfg.query.sampling,
        cfg.query.candidate_factor,
        first,
    )


def test_the_default_pixel_hooks_are_the_trainers_calls():
    """PEBBLE's pixel hooks against the calls the trainer made before them, bit for bit: ``pixel_reward.select``
    with the trainer's arguments, ``frame_replay.sample`` with DrQ-v2's sizes, the batch unchanged."""
    trainer = Trainer(PIXEL_MICRO)
    ts = jax.jit(trainer.init)(jax.random.key(18))
    filled, _, _, _ = _filled_pixel_buffer(np.random.default_rng(19), 4 * trainer.episode_length, ts.buffer)
    ts, method, cfg = ts.replace(buffer=filled), Method(), PIXEL_MICRO
    for first in (True, False):
        hooked = jax.jit(lambda key, first=first: method.query_segments(trainer, ts, key, first))
        direct = jax.jit(lambda key, first=first: _select_directly(trainer, ts, key, first))
        chex.assert_trees_all_equal(hooked(jax.random.key(20)), direct(jax.random.key(20)))
    sample = jax.jit(lambda key: method.sample_batch(trainer, ts, ts.buffer, key))
    d = cfg.drqv2
    expected = jax.jit(lambda key: frame_replay.sample(ts.buffer, key, d.batch_size, True, d.nstep, d.gamma))
    batch = sample(jax.random.key(21))
    chex.assert_trees_all_equal(batch, expected(jax.random.key(21)))
    assert method.batch_reward(trainer, ts, batch, jnp.int32(40)) is batch


class _Spy(Method):
    """PEBBLE, counting where the pixel trainer's round calls its pixel hooks (at trace time)."""

    name = "pebble"

    def __init__(self):
        self.calls = []

    def query_segments(self, trainer, ts, key, first):
        self.calls.append("query")
        return super().query_segments(trainer, ts, key, first)

    def sample_batch(self, trainer, ts, buffer, key):
        self.calls.append("sample")
        return super().sample_batch(trainer, ts, buffer, key)

    def batch_reward(self, trainer, ts, batch, agent_step):
        self.calls.append("reward")
        return super().batch_reward(trainer, ts, batch, agent_step)


def test_the_pixel_round_calls_the_hooks_in_the_session_the_updates_and_the_reset_updates():
    trainer = Trainer(PIXEL_MICRO)
    trainer.method = spy = _Spy()
    ts = jax.eval_shape(trainer.init, jax.random.key(0))
    jax.eval_shape(trainer.round, ts, jnp.int32(1))
    # The session's queries; its critic reset's updates (uniform batches, the method's reward); a step's updates. The
    # session is traced once (the round without one takes its metrics' shapes from that trace).
    assert spy.calls[:2] == ["query", "reward"]
    assert sorted(spy.calls[2:]) == ["reward", "sample"]


class _DirectQueries(Method):
    """PEBBLE whose queries are the trainer's call before the hooks; its batches are :class:`_DirectCalls`'s."""

    name = "pebble"

    def query_segments(self, trainer, ts, key, first):
        return _select_directly(trainer, ts, key, first)

    def sample_batch(self, trainer, ts, buffer, key):
        raise AssertionError("the direct trainer samples by itself")

    def batch_reward(self, trainer, ts, batch, agent_step):
        raise AssertionError("the direct trainer's batches keep the learned reward")


class _DirectCalls(Trainer):
    """The pixel trainer's DrQ-v2 updates as written before the method hooks: ``frame_replay.sample`` and the
    learned reward in the updates of every step and in those after the critic's reset."""

    def __init__(self, cfg: Config):
        super().__init__(cfg)
        self.method = _DirectQueries()
        self.feedback._reset_critic = self._direct_reset_critic

    def _updates(self, ts, buffer, key, t, pretraining=False):
        cfg, agent_step = self.cfg.drqv2, t * self.num_train

        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            batch = frame_replay.sample(buffer, key_sample, cfg.batch_size, True, cfg.nstep, cfg.gamma)
            return self.agent.update(state, batch, key_update, agent_step)

        agent, metrics = jax.lax.scan(one, ts.agent, jax.random.split(key, self.updates_per_step))
        return (agent, ts.entropy_stats), jax.tree.map(jnp.mean, metrics)

    def _direct_reset_critic(self, ts, key, agent_step):
        cfg = self.cfg.drqv2
        key_reset, key_updates = jax.random.split(key)
        agent = self.agent.reset_critic(ts.agent, key_reset)

        def one(state, key):
            key_sample, key_update = jax.random.split(key)
            batch = frame_replay.sample(ts.buffer, key_sample, cfg.batch_size, True, cfg.nstep, cfg.gamma)
            return self.agent.update(state, batch, key_update, agent_step)[0], None

        return jax.lax.scan(one, agent, jax.random.split(key_updates, self.cfg.pretrain.reset_updates))[0]


PIXEL_SEEDS = 2


def _pixel_run(trainer: Trainer, rounds: int) -> tuple[Trainer, list, list]:
    """``rounds`` rounds of two seeds; the state after each (on the host) and each round's metrics."""
    init, round_fn, _ = train.compiled(trainer)
    state = init(train.seed_keys(0, PIXEL_SEEDS))
    states, metrics = [], []
    for r in range(rounds):
        state, m = round_fn(state, jnp.int32(r))
        states.append(jax.device_get(state.replace(key=jax.random.key_data(state.key))))
        metrics.append(jax.device_get(m))
    return trainer, states, metrics


@pytest.fixture(scope="module")
def pixel_pebble():
    """PEBBLE's micro pixel run through the hooks: round 0 seeds, round 1 the first feedback session and its critic
    reset, round 2 a later session."""
    return _pixel_run(Trainer(PIXEL_MICRO), 3)


@pytest.mark.heavy  # two compiles of the pixel round; make test checks the hooks against the calls one by one
def test_pixel_pebble_through_the_hooks_is_the_trainers_direct_calls_bit_for_bit(pixel_pebble):
    _, states, metrics = pixel_pebble
    _, direct_states, direct_metrics = _pixel_run(_DirectCalls(PIXEL_MICRO), 3)
    for r in range(3):
        chex.assert_trees_all_equal(states[r], direct_states[r])
        chex.assert_trees_all_equal(metrics[r], direct_metrics[r])
    assert metrics[-1]["labels_used"].tolist() == [8.0, 8.0]  # two sessions ran


@pytest.mark.heavy  # a compile of the pixel round (~1 min on 2 cores)
def test_pixel_rune_learns_pebbles_reward_and_moves_the_agent_with_its_bonus(pixel_pebble):
    cfg = dataclasses.replace(PIXEL_MICRO, algo="rune", rune=RUNEConfig(beta_0=0.5, rho=1e-3))
    trainer, states, metrics = _pixel_run(Trainer(cfg), 2)
    _, pebble, _ = pixel_pebble
    assert trainer.trace_count == 1
    # Until the first feedback session's critic reset the runs are PEBBLE's: the same labels, the same learned reward
    # (up to float rounding: another program); the bonus then enters the reset's updates and every later update.
    ours, theirs = states[1], pebble[1]
    np.testing.assert_array_equal(ours.reward.data.labels, theirs.reward.data.labels)
    chex.assert_trees_all_close(ours.reward.params, theirs.reward.params, rtol=1e-4, atol=1e-6)
    critic = [jax.tree.leaves(state.agent.critic_params) for state in (ours, theirs)]
    change = max(float(np.max(np.abs(a - b))) for a, b in zip(*critic, strict=True))
    print(f"critic after round 1: largest change {change:.2e} from PEBBLE's")
    assert change > 1e-4  # far above float rounding
    for m in metrics[1:]:
        np.testing.assert_array_equal(m["diverged"], 0.0)
        assert all(np.all(np.isfinite(m[k])) for k in ("critic_loss", "reward_loss", "reward_accuracy_all"))


@pytest.mark.heavy  # a compile of the pixel round (~1 min on 2 cores) and four rounds
def test_pixel_qpa_labels_segments_of_the_last_complete_episodes_at_each_session():
    cfg = dataclasses.replace(PIXEL_MICRO, algo="qpa", qpa=QPAConfig(recent_episodes=2, crop=1, her_ratio=0.5))
    trainer, states, metrics = _pixel_run(Trainer(cfg), 4)
    assert trainer.trace_count == 1
    assert [float(m["labels_used"][0]) for m in metrics] == [0.0, 4.0, 8.0, 12.0]
    for m in metrics[1:]:
        np.testing.assert_array_equal(m["diverged"], 0.0)
        assert np.all(m["reward_epochs"] <= PIXEL_MICRO.pixel_reward.max_epochs)
        assert all(np.all(np.isfinite(m[k])) for k in ("critic_loss", "reward_loss", "reward_accuracy_all"))
    # Reference: the 2 envs' episodes of L = 10 agent steps start together, one per round, and the ring never wraps
    # (40 rows); session s (at round s) finds s complete episodes per env, and the last 2 of them by (age, env) are
    # episode s - 1 of both envs: rows 10 (s - 1) .. 10 s - 1. Its 4 pairs are stored 4 (s - 1) .. 4 s - 1.
    final, length, horizon = states[-1], trainer.episode_length, cfg.query.segment_length
    for seed in range(PIXEL_SEEDS):
        buffer = jax.tree.map(lambda x, s=seed: x[s], final.buffer)
        data = jax.tree.map(lambda x, s=seed: x[s], final.reward.data)
        for pair in range(12):
            session = pair // 4 + 1
            for frames, action in ((data.a.frames, data.a.action), (data.b.frames, data.b.action)):
                row, _ = _place_of(buffer, frames[pair], action[pair], horizon)
                assert row // length == session - 1 and (row + horizon - 1) // length == session - 1
