"""``benchmarks/pixel_session_parts.py``: the parts of a pixel preference session it times are the trainer's own,
on a state whose replay and label store are full, and its rows say what ran (CPU, 16x16 probe)."""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest


@pytest.fixture
def parts_module(benchmark_script):
    return benchmark_script("pixel_session_parts")


# make test-heavy (16 s of compiles of a benchmark): the session's parts are the trainer's, tested in
# test_pixel_preference.py.
@pytest.mark.heavy
def test_a_rebel_job_times_the_bt_epoch_the_rebel_epoch_and_the_relabel_on_a_full_state(tmp_path, parts_module):
    out = tmp_path / "parts.json"
    args = parts_module.parser().parse_args(["--tiny", "--jobs", "rebel_cheetah", "--labels", "8", "--precisions",
                                             "bf16", "--repeats", "1", "--out", str(out)])  # fmt: skip
    results = parts_module.Results(out, "test")
    parts_module.run_job("rebel_cheetah", "bf16", args, results)
    rows = json.loads(out.read_text())
    assert [r["what"] for r in rows] == ["epoch_bt", "relabel", "relabel_8", "epoch_bt_rebel"]
    for row in rows:
        assert (row["job"], row["precision"], row["labels"]) == ("rebel_cheetah", "bf16", 8)
        assert "--pixel-reward.precision bf16" in row["command"] and "--algo rebel" in row["command"]
    # The state the parts ran on: the label store holds --labels pairs and every replay row is written.
    trainer = parts_module.Trainer(parts_module.parse(parts_module.job_flags("rebel_cheetah", 1000, 0, True)).config)
    ts = parts_module.filled(jax.jit(trainer.init)(jax.random.PRNGKey(0)), 8, None)
    assert int(ts.reward.data.count) == 8 and int(ts.buffer.size) == ts.buffer.rows == rows[0]["rows"]
    assert set(parts_module.parts(trainer)) == {"epoch_bt", "relabel", "epoch_bt_rebel"}
    # The relabelling at another chunk is the same rewards in fewer steps.
    every = parts_module.parts(trainer, (5, trainer.cfg.pixel_reward.relabel_rows))
    assert set(every) == {"epoch_bt", "relabel", "relabel_5", "epoch_bt_rebel"}
    key = jax.random.PRNGKey(0)
    np.testing.assert_allclose(every["relabel_5"](ts, key), every["relabel"](ts, key), rtol=1e-4)  # batch-size rounding
    with pytest.raises(SystemExit, match="--labels 13"):
        parts_module.filled(ts, 13, None)  # more pairs than the tiny store's 12


def test_a_pebble_job_has_no_rebel_part(parts_module):
    flags = parts_module.job_flags("pebble_walker", 1000, 0, True)
    trainer = parts_module.Trainer(parts_module.parse(flags).config)
    assert set(parts_module.parts(trainer)) == {"epoch_bt", "relabel"}


@pytest.mark.heavy  # two more compiles of a 2-column session (~20 s each on 2 cores): make test-heavy
def test_whole_sessions_run_vmapped_over_the_columns_looped_and_batched(tmp_path, parts_module):
    out = tmp_path / "parts.json"
    args = parts_module.parser().parse_args(["--tiny", "--labels", "8", "--repeats", "1", "--columns", "2",
                                             "--out", str(out)])  # fmt: skip
    results = parts_module.Results(out, "test")
    for loop in (True, False):
        parts_module.time_sessions("pebble_walker", "tf32", loop, args, results)
    rows = json.loads(out.read_text())
    assert [(r["what"], r["session_loop"], r["columns"]) for r in rows] == [("session", True, 2), ("session", False, 2)]
    max_epochs = parts_module.parse(
        parts_module.job_flags("pebble_walker", 1000, 0, True)
    ).config.pixel_reward.max_epochs
    assert [r["epochs"] for r in rows] == [max_epochs] * 2  # tied labels never reach the stop accuracy
    assert "--pixel-reward.no-session-loop" in rows[1]["command"] and "--seeds 2" in rows[1]["command"]
