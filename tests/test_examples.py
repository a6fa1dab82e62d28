"""The worked extensions: examples/l2_reward.py, a new method in one file, trained on state and pixel tasks, and
examples/rebel_on_qpa.py, two methods composed.

The L2 penalty is checked against a NumPy loop; trained with a large weight, the learned reward it leaves is
smaller than PEBBLE's from the same keys (the only difference between the two runs is the method). REBEL on QPA
at lambda 0 is QPA bit for bit, through the command line, and not at lambda 1.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_cli_runs import _metrics
from test_pixel_preference import MICRO as PIXEL_MICRO
from test_preference_train import MICRO_PEBBLE
from test_qpa_rune import METHOD_FLAGS
from test_qpa_rune import MICRO_FLAGS as QPA_MICRO

from rebel_jax import api, config, methods, train
from rebel_jax.run import cli

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "examples"))
from l2_reward import L2Reward, l2_penalty  # noqa: E402
from rebel_on_qpa import REBELOnQPA  # noqa: E402


@pytest.fixture(scope="module")
def strong_l2():
    """The example registered as ``l2_reward`` with a weight that dominates the Bradley-Terry loss."""
    method = methods.register(L2Reward(weight=50.0))
    yield method
    del methods.REGISTRY[method.name]


def test_l2_penalty_is_the_weighted_mean_square_per_member_summed():
    rng = np.random.default_rng(0)
    rewards_a, rewards_b = rng.normal(size=(2, 3, 5, 4)).astype(np.float32)
    mask = np.array([[1, 1, 0, 1, 0], [1, 0, 0, 0, 0], [0, 0, 0, 0, 0]], np.float32)
    expected = 0.0
    for m in range(3):
        real = [b for b in range(5) if mask[m, b]]
        squares = [np.mean(np.concatenate([rewards_a[m, b], rewards_b[m, b]]) ** 2) for b in real]
        expected += np.mean(squares) if real else 0.0
    got = l2_penalty(0.3, jnp.asarray(rewards_a), jnp.asarray(rewards_b), jnp.asarray(mask))
    np.testing.assert_allclose(got, 0.3 * expected, rtol=1e-6)


def test_a_registered_name_is_refused():
    with pytest.raises(ValueError, match="exists already"):
        methods.register(methods.get("pebble"))


def _learned_square(cfg, rounds: int) -> float:
    trainer = api.make_trainer(cfg)
    init, round_fn, _ = train.compiled(trainer)
    state = init(train.seed_keys(0, 2))
    for r in range(rounds):
        state, metrics = round_fn(state, jnp.int32(r))
    assert np.isfinite(np.asarray(metrics["eval_return"])).all()
    buffer = jax.device_get(state.buffer)
    rows = int(np.max(buffer.size))
    reward = buffer.learned_reward  # the same name on the state and the frame replay
    return float(np.mean(np.asarray(reward)[:, :rows] ** 2))


def test_the_example_trains_on_a_state_task_and_shrinks_the_reward(strong_l2):
    rounds = 3  # two feedback sessions
    pebble = _learned_square(MICRO_PEBBLE, rounds)
    l2 = _learned_square(dataclasses.replace(MICRO_PEBBLE, algo=strong_l2.name), rounds)
    assert l2 < pebble / 2


def test_the_example_s_penalty_reaches_the_run_s_metrics(strong_l2, tmp_path):
    """A loss term's own metric is logged under the method's name, per seed and as their mean, at each session."""
    run_dir = tmp_path / "run"
    cli.main([strong_l2.name, *QPA_MICRO, "--run-dir", str(run_dir)])
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    sessions = [r for r in rows if r["session_mean"] == 1.0]
    assert sessions and all(r["l2_reward/l2_penalty_mean"] > 0 for r in sessions)
    for r in sessions:  # the mean over seeds of the per-seed values
        assert r["l2_reward/l2_penalty_mean"] == pytest.approx(np.mean(r["l2_reward/l2_penalty"]), rel=1e-6)
    assert all(r["l2_reward/l2_penalty"] == [None, None] for r in rows if r["session_mean"] is None)


@pytest.mark.heavy  # make test-heavy: the pixel agent's compile is about a minute on 2 cores
def test_the_example_trains_on_a_pixel_task_and_shrinks_the_reward(strong_l2):
    rounds = 3
    pebble = _learned_square(PIXEL_MICRO, rounds)
    l2 = _learned_square(dataclasses.replace(PIXEL_MICRO, algo=strong_l2.name), rounds)
    assert l2 < pebble / 2


@pytest.fixture(scope="module")
def rebel_on_qpa():
    """examples/rebel_on_qpa.py registered as ``rebel_qpa``."""
    method = methods.register(REBELOnQPA())
    yield method
    del methods.REGISTRY[method.name]


def _qpa_run(run_dir: pathlib.Path, *flags: str) -> tuple[list[dict], dict]:
    """The QPA micro run of tests/test_qpa_rune.py with ``flags`` last: its metrics rows (no timings) and final.json."""
    cli.main([*QPA_MICRO, *METHOD_FLAGS["qpa"].split(), *flags, "--run-dir", str(run_dir)])
    return _metrics(run_dir), json.loads((run_dir / "final.json").read_text())


@pytest.mark.heavy  # make test-heavy: three QPA micro runs through the command line, 1-4 minutes on 2 cores
def test_rebel_on_qpa_at_lambda_0_is_qpa_bit_for_bit(rebel_on_qpa, tmp_path):
    rebel = ("--algo", rebel_on_qpa.name, "--rebel.source", "replay", "--rebel.segment-length", "8")
    qpa_rows, qpa_final = _qpa_run(tmp_path / "qpa")
    zero_rows, zero_final = _qpa_run(tmp_path / "zero", *rebel, "--rebel.lam", "0")
    assert zero_final == qpa_final
    for qpa_row, zero_row in zip(qpa_rows, zero_rows, strict=True):
        assert {k: zero_row[k] for k in qpa_row} == qpa_row
    one_rows, _ = _qpa_run(tmp_path / "one", *rebel, "--rebel.lam", "1")  # the term weighs: another reward
    assert one_rows[-1]["reward_loss"] != qpa_rows[-1]["reward_loss"]


def test_a_composed_method_reads_both_sections_and_flags_of_either_are_its_own(rebel_on_qpa):
    composed = dataclasses.replace(config.PRESETS["qpa"], algo=rebel_on_qpa.name).unused_parts()
    assert "qpa" not in composed and "rebel" not in composed and composed["surf"] == "--algo surf"
    qpa_alone = dataclasses.replace(config.PRESETS["qpa"], algo="qpa").unused_parts()
    assert qpa_alone["rebel"] == "--algo rebel or --algo rebel_qpa"
    args = cli.parse(["rebel_qpa", "--preset", "qpa", "--task", "probe_point", "--qpa.her-ratio", "0.25"])
    assert (args.config.qpa.her_ratio, args.config.algo) == (0.25, "rebel_qpa")
