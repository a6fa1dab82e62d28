"""The preference methods inside the jitted round: PEBBLE, REBEL and PEBBLE+SURF end to end on CPU."""

from __future__ import annotations

import dataclasses
import functools

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from rebel_jax.config import Config, EnvConfig, FeedbackConfig, SACConfig, TrainConfig
from rebel_jax.methods.rebel import AgentPreferenceConfig
from rebel_jax.methods.surf import SURFConfig
from rebel_jax.preference import pretrain, reward_model
from rebel_jax.preference.budget import offered_pairs, remaining_budget, within_budget
from rebel_jax.preference.feedback import SESSION_METRICS, saturated_fraction
from rebel_jax.preference.pretrain import PretrainConfig
from rebel_jax.preference.queries import QueryConfig
from rebel_jax.preference.reward_model import RewardConfig
from rebel_jax.preference.teachers import TeacherConfig
from rebel_jax.train import Trainer, compiled, seed_keys

# Episodes of 40 steps, rounds of 20 vector steps: 20 seed steps, 60 pre-training steps, then a
# feedback session at the start of rounds 2, 3 and 4 (env steps 80, 120, 160). On the probe task,
# which compiles in seconds (the trainer is the same for every task).
MICRO_PEBBLE = Config(
    algo="pebble",
    env=EnvConfig(task="probe_point", num_envs=2, episode_length=40),
    sac=SACConfig(hidden=16, batch_size=16, utd=0.5),
    train=TrainConfig(total_steps=200, seed_steps=20, steps_per_round=40, eval_every=40, eval_episodes=1),
    feedback=FeedbackConfig(labels=48, per_session=16, interval=40),
    reward=RewardConfig(hidden=32, depth=2, batch_size=16),
    query=QueryConfig(segment_length=8),
    pretrain=PretrainConfig(steps=60, chunk_size=64),
    surf=SURFConfig(pool_size=32, crop=2, ratio=2),
    rebel=AgentPreferenceConfig(num_segments=8, segment_length=8),
)
ROUNDS = MICRO_PEBBLE.train.num_rounds


def _run(cfg: Config, keys, lam=None):
    trainer = Trainer(cfg)
    chex.clear_trace_counter()
    trainer.round = chex.assert_max_traces(trainer.round, n=1)  # Every round of the run is one program.
    init, round_fn, _ = compiled(trainer)
    state = init(keys)
    if lam is not None:
        state = state.replace(lam=jnp.asarray(lam, jnp.float32))
    metrics = []
    for r in range(ROUNDS):
        state, m = round_fn(state, jnp.int32(r))
        metrics.append(jax.device_get(m))
    return trainer, state, metrics


# Four columns: two seeds twice. The vmapped batch size changes XLA's rounding, so runs that
# must agree bit for bit are compared at the same batch size.
KEYS = jnp.concatenate([seed_keys(0, 2), seed_keys(0, 2)])


@pytest.fixture(scope="module")
def rebel_runs():
    """REBEL on two seeds, each with lambda 0 and lambda -1: one compile, four runs vmapped."""
    cfg = dataclasses.replace(MICRO_PEBBLE, algo="rebel")
    return _run(cfg, KEYS, lam=[0.0, 0.0, -1.0, -1.0])


@pytest.fixture(scope="module")
def pebble_run():
    return _run(MICRO_PEBBLE, KEYS)


def test_schedule_sessions_and_budget(pebble_run):
    _, state, metrics = pebble_run  # Its rounds were traced once (``_run``).
    sessions = [int(np.all(m["session"] == 1.0)) for m in metrics]
    assert sessions == [0, 0, 1, 1, 1]  # at env steps 80, 120, 160
    assert all(np.all(np.isnan(m["reward_accuracy_all"])) for m, s in zip(metrics, sessions, strict=True) if not s)
    # Oracle teacher: nothing skipped, and the budget is spent exactly.
    np.testing.assert_array_equal(metrics[-1]["labels_used"], [48] * 4)
    np.testing.assert_array_equal(state.reward.data.count, [48] * 4)
    for key in SESSION_METRICS:
        assert np.all(np.isfinite(metrics[2][key])), key
    for m, s in zip(metrics, sessions, strict=True):  # the oracle agrees with itself; NaN without a session
        np.testing.assert_array_equal(m["session_oracle_agreement"], 1.0 if s else np.nan)


def test_pebble_learns_a_reward_that_agrees_with_the_teacher(pebble_run):
    _, state, metrics = pebble_run
    last = metrics[-1]
    assert np.all(last["reward_accuracy_all"] >= 0.9)
    assert np.all(last["reward_correlation"] > 0.2)
    # The buffer holds the ensemble's rewards: relabelled after the session, new rows as collected.
    assert np.all(np.std(state.buffer.learned_reward, axis=(1, 2)) > 0)


def test_pebble_relabel_matches_the_reward_model(pebble_run):
    trainer, state, _ = pebble_run
    seed = jax.tree.map(lambda x: x[0], state)
    expected = jax.jit(reward_model.mean_reward, static_argnums=0)(
        trainer.reward_cfg, seed.reward.params, seed.buffer.obs, seed.buffer.action
    )
    np.testing.assert_allclose(seed.buffer.learned_reward, expected, rtol=1e-5, atol=1e-6)


def _numpy_member(params, x):
    """One reward member in NumPy, B-Pref's ``gen_net``: LeakyReLU(0.01) hidden layers, tanh output."""
    layers = [params["params"][f"Dense_{i}"] for i in range(len(params["params"]))]
    for layer in layers[:-1]:
        x = x @ np.asarray(layer["kernel"], np.float64) + np.asarray(layer["bias"], np.float64)
        x = np.where(x > 0, x, 0.01 * x)
    last = layers[-1]
    return np.tanh(x @ np.asarray(last["kernel"], np.float64) + np.asarray(last["bias"], np.float64))[..., 0]


def test_stored_pairs_labels_and_loss_equal_a_numpy_bpref_on_the_same_buffer(pebble_run):
    """The path from stored transitions to the reward model's inputs, the teacher's labels and the
    loss, end to end through the trainer's sessions, against plain NumPy on the run's own buffer:
    B-Pref's ``get_queries`` (H consecutive steps of one env's episode), ``get_label`` (oracle:
    ``1 * (sum r_1 < sum r_2)``) and ``train_reward``'s loss (cross-entropy over the logits
    ``[sum r_hat_1, sum r_hat_2]``), rl-research/BPref reward_model.py."""
    trainer, state, _ = pebble_run
    cfg, horizon = trainer.reward_cfg, MICRO_PEBBLE.query.segment_length
    for column in range(KEYS.shape[0]):
        seed = jax.device_get(jax.tree.map(lambda x, c=column: x[c], state))
        buffer, data = seed.buffer, seed.reward.data
        obs, action, reward = np.asarray(buffer.obs), np.asarray(buffer.action), np.asarray(buffer.true_reward)
        steps, count = np.asarray(buffer.episode_step), int(data.count)
        assert count == MICRO_PEBBLE.feedback.labels
        returns = {}
        for side in ("a", "b"):
            seg_obs, seg_act = np.asarray(getattr(data, side).obs), np.asarray(getattr(data, side).action)
            sums = []
            for i in range(count):
                # Where the segment's first step is in the buffer, then the H steps from there.
                rows, envs = np.nonzero(np.all(obs == seg_obs[i, 0], axis=-1))
                matches = [
                    (t, e)
                    for t, e in zip(rows, envs, strict=True)
                    if t + horizon <= obs.shape[0]
                    and np.array_equal(obs[t : t + horizon, e], seg_obs[i])
                    and np.array_equal(action[t : t + horizon, e], seg_act[i])
                ]
                assert len(matches) == 1, f"pair {i} side {side}: {len(matches)} places in the buffer"
                t, e = matches[0]
                one_episode = steps[t, e] + np.arange(horizon)
                np.testing.assert_array_equal(steps[t : t + horizon, e], one_episode)
                sums.append(reward[t : t + horizon, e].astype(np.float64).sum())
            returns[side] = np.array(sums)
        expected_labels = (returns["a"] < returns["b"]).astype(np.float32)  # B-Pref: 1 means segment 2.
        np.testing.assert_array_equal(np.asarray(data.labels[:count]), expected_labels)

        # The BT loss of every member on the stored pairs: ours against NumPy's cross-entropy.
        members = jax.tree.leaves(seed.reward.params)[0].shape[0]
        logits = []
        for m in range(members):
            params = jax.tree.map(lambda x, m=m: np.asarray(x[m]), seed.reward.params)
            r_a = _numpy_member(params, np.concatenate([data.a.obs[:count], data.a.action[:count]], -1)).sum(-1)
            r_b = _numpy_member(params, np.concatenate([data.b.obs[:count], data.b.action[:count]], -1)).sum(-1)
            logits.append(np.stack([r_a, r_b], -1))
        logits = np.stack(logits)  # (M, N, 2)
        log_softmax = logits - np.log(np.exp(logits).sum(-1, keepdims=True))
        target = expected_labels.astype(int)
        numpy_loss = -np.take_along_axis(log_softmax, target[None, :, None], -1)[..., 0].mean(-1).sum()

        def every_member(x, count=count, members=members):
            return jnp.broadcast_to(x[:count], (members, *x[:count].shape))

        batch = reward_model.PrefBatch(
            a=jax.tree.map(every_member, data.a),
            b=jax.tree.map(every_member, data.b),
            labels=every_member(data.labels),
            weight=jnp.ones((members, count)),
            members=jnp.arange(members),
        )
        batch = reward_model.with_rewards(cfg, seed.reward.params, batch)
        loss, _ = reward_model.bt_loss(cfg)(seed.reward.params, batch, None)
        np.testing.assert_allclose(float(loss), numpy_loss, rtol=1e-4)


def test_rebel_with_lambda_zero_is_pebble_bit_for_bit(pebble_run, rebel_runs):
    _, pebble, _ = pebble_run
    _, rebel, _ = rebel_runs
    first_two = functools.partial(jax.tree.map, lambda x: np.asarray(x)[:2])
    for name in ("agent", "reward", "buffer"):
        chex.assert_trees_all_equal(first_two(getattr(pebble, name)), first_two(getattr(rebel, name)))


def test_rebel_lambda_is_traced_and_changes_the_learned_reward(rebel_runs):
    _, state, metrics = rebel_runs  # lambda 0 and -1 ran in one program, traced once (``_run``).
    differs = [not np.array_equal(x[:2], x[2:]) for x in jax.tree.leaves(jax.device_get(state.reward.params))]
    assert all(differs)
    assert np.all(np.isfinite(metrics[-1]["reward_loss"])) and np.all(np.isfinite(metrics[-1]["critic_loss"]))


@pytest.mark.heavy  # one more round compile (~26 s on 2 cores); the penalty term itself is checked in make test
def test_rebel_penalty_form_with_lambda_zero_is_pebble_and_otherwise_trains_another_reward(pebble_run):
    """``rebel.form penalty`` (eq. "bilevel_rlhf_fo") through the round: lambda 0 adds exactly nothing. The term
    against a NumPy reference: ``test_surf_rebel.py`` and ``test_pixel_preference.py``."""
    rebel = dataclasses.replace(MICRO_PEBBLE.rebel, form="penalty", best_segments=4)
    cfg = dataclasses.replace(MICRO_PEBBLE, algo="rebel", rebel=rebel)
    _, state, metrics = _run(cfg, KEYS, lam=[0.0, 0.0, 1.0, 1.0])
    _, pebble, _ = pebble_run
    first_two = functools.partial(jax.tree.map, lambda x: np.asarray(x)[:2])
    chex.assert_trees_all_equal(first_two(pebble.reward), first_two(state.reward))
    differs = [not np.array_equal(x[:2], x[2:]) for x in jax.tree.leaves(jax.device_get(state.reward.params))]
    assert all(differs)
    assert np.all(np.isfinite(metrics[-1]["reward_loss"])) and np.all(np.isfinite(metrics[-1]["critic_loss"]))


def test_surf_with_disagreement_queries_a_skipping_teacher_and_the_asked_budget():
    """SURF end to end, with the non-default query scheme and teacher, under ``budget asked`` (the ``paper``
    preset's, B-Pref's accounting): 32 labels of 16 per session is 2 sessions though the schedule has 3, and
    the labels used are the answered pairs of those 2 sessions (a skipped pair is spent, not stored)."""
    cfg = dataclasses.replace(
        MICRO_PEBBLE,
        algo="surf",
        feedback=FeedbackConfig(labels=32, per_session=16, interval=40, budget="asked"),
        query=dataclasses.replace(MICRO_PEBBLE.query, sampling="disagreement"),
        teacher=TeacherConfig(eps_skip=0.5, eps_equal=0.1),
    )
    trainer, state, metrics = _run(cfg, seed_keys(4, 2))
    assert trainer.stored_length == cfg.query.segment_length + 2 * cfg.surf.crop
    assert state.reward.data.a.obs.shape[2] == trainer.stored_length
    sessions = [m for m in metrics if np.all(m["session"] == 1.0)]
    assert len(sessions) == 2 and sum(bool(trainer.session_due(r)[0]) for r in range(ROUNDS)) == 2
    skipped = sum(m["session_skipped"] for m in sessions)
    assert np.all(skipped > 0)  # half the margin skips some pairs of a near-random policy
    np.testing.assert_array_equal(metrics[-1]["labels_used"], 32 - skipped)
    np.testing.assert_array_equal(state.reward.data.count, 32 - skipped)
    # Skips and equal answers are this teacher's only departures from the oracle: the agreement is over the kept
    # answers (every session skipped some, so counting them would lower it), the "equal" ones disagreeing; NaN for a
    # session that kept none.
    for m in sessions:
        kept = 16 - m["session_skipped"]
        expected = np.where(kept > 0, (kept - m["session_equal"]) / np.maximum(kept, 1), np.nan)
        np.testing.assert_allclose(m["session_oracle_agreement"], expected, rtol=1e-6)
    # A session whose answers were all skipped trains nothing and logs NaN; the last trained model fits.
    accuracy = np.array([m["reward_accuracy_all"] for m in sessions])  # (sessions, seeds)
    kept = np.array([m["session_labels"] for m in sessions])
    np.testing.assert_array_equal(np.isnan(accuracy), kept == 0)
    assert np.all(kept.sum(axis=0) > 0)
    for seed in range(accuracy.shape[1]):
        assert accuracy[kept[:, seed] > 0, seed][-1] >= 0.7, accuracy
    assert np.all(np.isfinite(metrics[-1]["critic_loss"]))


def test_session_correlations_are_those_of_the_learned_reward_on_the_sessions_segments(pebble_run):
    trainer, state, _ = pebble_run
    ts = jax.tree.map(lambda x: x[0], state)
    key, key_select = jax.random.key(31), jax.random.key(32)
    seg_a, seg_b = jax.jit(trainer.select, static_argnums=2)(ts, key_select, False)
    labels = (seg_b.true_reward.sum(-1) > seg_a.true_reward.sum(-1)).astype(jnp.float32)
    mask = jnp.zeros_like(labels)  # Nothing kept: the reward model stays as it is.
    new, metrics = jax.jit(trainer.learn, static_argnums=6)(ts, key, seg_a, seg_b, labels, mask, False)
    # The fresh segments are drawn with learn's own key split, as documented in Trainer.learn.
    key_fresh = jax.random.split(key, 5)[2]
    fresh = trainer.sample_segments(new.buffer, key_fresh, 64, trainer.horizon)
    learned = np.asarray(reward_model.mean_reward(trainer.reward_cfg, ts.reward.params, fresh.obs, fresh.action))
    true = np.asarray(fresh.true_reward)
    np.testing.assert_allclose(
        metrics["reward_correlation"], np.corrcoef(learned.ravel(), true.ravel())[0, 1], rtol=1e-4
    )
    np.testing.assert_allclose(
        metrics["reward_correlation_return"], np.corrcoef(learned.sum(-1), true.sum(-1))[0, 1], rtol=1e-4
    )
    np.testing.assert_allclose(metrics["reward_learned_mean"], learned.mean(), rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(metrics["reward_saturated"], np.mean(np.abs(learned) > 0.9))
    both_obs = np.concatenate([seg_a.obs, seg_b.obs])
    both_action = np.concatenate([seg_a.action, seg_b.action])
    queried = np.asarray(reward_model.mean_reward(trainer.reward_cfg, ts.reward.params, both_obs, both_action))
    true_queried = np.concatenate([seg_a.true_reward, seg_b.true_reward])
    np.testing.assert_allclose(
        metrics["reward_correlation_queries"], np.corrcoef(queried.ravel(), true_queried.ravel())[0, 1], rtol=1e-4
    )


def test_round_reward_metrics_describe_the_rounds_own_transitions(pebble_run):
    trainer, state, metrics = pebble_run
    rows = trainer.steps_per_round
    for seed in range(state.buffer.true_reward.shape[0]):
        ptr, capacity = int(state.buffer.ptr[seed]), state.buffer.true_reward.shape[1]
        index = [(ptr - rows + k) % capacity for k in range(rows)]  # The last round's rows.
        learned = np.asarray(state.buffer.learned_reward[seed])[index].ravel()
        true = np.asarray(state.buffer.true_reward[seed])[index].ravel()
        np.testing.assert_allclose(metrics[-1]["round_learned_mean"][seed], learned.mean(), rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(metrics[-1]["round_learned_saturated"][seed], np.mean(np.abs(learned) > 0.9))
        np.testing.assert_allclose(
            metrics[-1]["round_reward_correlation"][seed], np.corrcoef(learned, true)[0, 1], rtol=1e-4, atol=1e-6
        )


@pytest.mark.parametrize(
    "output, reward, low, high",
    [("tanh", [-0.95, -0.5, 0.0, 0.89, 0.91, 0.99], -1.0, 1.0), ("sigmoid", [0.01, 0.04, 0.06, 0.5, 0.94, 0.96], 0, 1)],
)
def test_saturated_fraction_counts_rewards_near_the_outputs_bounds(output, reward, low, high):
    reward = np.asarray(reward, np.float32)
    margin = 0.05 * (high - low)
    want = np.mean([r < low + margin or r > high - margin for r in reward])
    assert want == 0.5  # three of six near a bound
    np.testing.assert_allclose(saturated_fraction(jnp.asarray(reward), output), want)


def _bpref_asked_masks(labels: int, queries: int, kept: list[np.ndarray]) -> list[np.ndarray]:
    """B-Pref's accounting (train_PEBBLE.py ``learn_reward`` / ``run``), as a plain loop: a session asks
    ``min(mb_size, max_feedback - total_feedback)`` pairs (``set_batch``), the teacher keeps some, and
    ``total_feedback += mb_size``; no session once ``total_feedback >= max_feedback``."""
    total, out = 0, []
    for answered in kept:
        if total >= labels:
            break
        size = min(queries, labels - total)
        out.append(np.where(np.arange(queries) < size, answered, 0.0))
        total += queries
    return out


def _answered_masks(labels: int, kept: list[np.ndarray]) -> list[np.ndarray]:
    """The ``answered`` rule as a loop: answered pairs count until ``labels`` are stored."""
    stored, out = 0, []
    for answered in kept:
        mask = np.zeros_like(answered)
        for i, k in enumerate(answered):
            if k and stored < labels:
                mask[i], stored = 1.0, stored + 1
        out.append(mask)
    return out


@pytest.mark.parametrize("budget", ["asked", "answered"])
def test_within_budget_is_bprefs_accounting_or_the_answered_rule(budget):
    feedback = FeedbackConfig(labels=25, per_session=10, budget=budget)
    rng = np.random.default_rng(3)
    kept = [(rng.random(10) < 0.6).astype(np.float32) for _ in range(6)]
    if budget == "asked":
        want = _bpref_asked_masks(25, 10, kept)
    else:
        want = _answered_masks(25, kept)
    got, stored = [], 0
    for index, answered in enumerate(kept):
        if feedback.sessions is not None and index >= feedback.sessions:
            break
        mask = np.asarray(within_budget(feedback, jnp.asarray(answered), jnp.int32(stored), jnp.int32(index)))
        got.append(mask)
        stored += int(mask.sum())
    assert len(got) == len(want)
    for ours, theirs in zip(got, want, strict=True):
        np.testing.assert_array_equal(ours, theirs)
    assert feedback.sessions == (3 if budget == "asked" else None)


@pytest.mark.parametrize("labels, queries", [(100, 10), (25, 10), (7, 3)])
def test_offered_pairs_follow_bprefs_shrunken_last_session(labels, queries):
    """Under ``asked`` a person sees B-Pref's batch sizes, and every pair shown counts."""
    feedback = FeedbackConfig(labels=labels, per_session=queries, budget="asked")
    sizes, total = [], 0
    while total < labels:  # train_PEBBLE.py: mb_size, cut to max_feedback - total_feedback.
        size = queries if total + queries <= labels else labels - total
        sizes.append(size)
        total += size
    ours = [offered_pairs(feedback, int(remaining_budget(feedback, 0, i)), queries) for i in range(feedback.sessions)]
    assert ours == sizes
    for index, size in enumerate(ours):  # A skip is a shown pair too: the first `size` pairs are the counted ones.
        kept = within_budget(feedback, jnp.ones(queries), jnp.int32(0), jnp.int32(index))
        np.testing.assert_array_equal(kept, np.arange(queries) < size)
    answered = dataclasses.replace(feedback, budget="answered")
    assert offered_pairs(answered, 1, queries) == queries  # A skipped pair leaves its place to the next.


def _updates_one_by_one(trainer, ts, key, t, pretraining):
    """A vector step's updates as the trainer once ran them: draw, reward and update one minibatch at a time."""
    state, stats, metrics, agent_step = ts.agent, ts.entropy_stats, [], t * trainer.num_train
    for update_key in jax.random.split(key, trainer.updates_per_step):
        key_sample, key_update = jax.random.split(update_key)
        batch = trainer.method.sample_batch(trainer, ts, ts.buffer, key_sample)
        if pretraining:  # the kNN over the rows written before the replay wraps, as B-Pref's (pretrain.py)
            early = ts.buffer.replace(obs=ts.buffer.obs[: trainer.pretrain_steps])
            reward, stats = pretrain.intrinsic_reward(trainer.cfg.pretrain, stats, batch.obs, early)
            batch = batch.replace(reward=reward)
        else:
            batch = trainer.method.batch_reward(trainer, ts, batch, agent_step)
        state, step_metrics = trainer.agent.update(state, batch, key_update, agent_step)
        metrics.append(step_metrics)
    return (state, stats), jax.tree.map(lambda *m: jnp.mean(jnp.stack(m)), *metrics)


@pytest.mark.parametrize(
    ("algo", "pretraining", "unroll"),
    [("pebble", True, False), ("pebble", False, False), ("rune", False, False), ("pebble", False, True)],
)
def test_a_vector_steps_updates_equal_drawing_rewarding_and_updating_one_minibatch_at_a_time(algo, pretraining, unroll):
    """Looped (``train.unroll_updates`` off) or unrolled, the same updates as the one-at-a-time reference."""
    cfg = dataclasses.replace(
        MICRO_PEBBLE,
        algo=algo,
        sac=dataclasses.replace(MICRO_PEBBLE.sac, utd=1.5),
        train=dataclasses.replace(MICRO_PEBBLE.train, unroll_updates=unroll),
    )
    trainer = Trainer(cfg)
    assert trainer.updates_per_step == 3 and trainer.pretrain_steps > 0  # several minibatches; a pre-training phase
    ts = trainer.init(jax.random.key(0))
    step = jax.jit(trainer.vector_step)
    for t in range(30):  # past the seed steps: replay rows, learned rewards, the running statistics moved
        ts, _ = step(ts, jnp.int32(t))
    key, t = jax.random.key(5), jnp.int32(30)
    drawn_first = jax.jit(lambda ts: trainer._updates(ts, ts.buffer, key, t, pretraining=pretraining))(ts)
    one_by_one = jax.jit(lambda ts: _updates_one_by_one(trainer, ts, key, t, pretraining))(ts)
    chex.assert_trees_all_close(drawn_first, one_by_one, rtol=1e-5, atol=1e-6)
    before, after = jax.tree.leaves(ts.agent.critic_params), jax.tree.leaves(drawn_first[0][0].critic_params)
    assert not all(np.array_equal(a, b) for a, b in zip(before, after, strict=True))  # the updates moved the critic
