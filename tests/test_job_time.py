"""experiments/job_time.py: a run's round costs read back from its log, and its projection to another length."""

from __future__ import annotations

import dataclasses
import json
import math
import pathlib
import sys

import pytest

sys.path.insert(0, str(pathlib.Path(__file__).parents[1] / "experiments"))

import job_time  # noqa: E402

from rebel_jax.config import PRESETS  # noqa: E402

FIRST, SEED_ROUND, PLAIN, BASE, PER_LABEL = 90.0, 0.8, 3.5, 2.0, 0.2


def _config(total_steps: int, budget: str = "asked"):
    cfg = PRESETS["surf_pixels_cheetah"]  # seed steps 2,000, rounds of 1,000, 25 labels every 10,000 steps
    return dataclasses.replace(
        cfg,
        train=dataclasses.replace(cfg.train, total_steps=total_steps),
        feedback=dataclasses.replace(cfg.feedback, budget=budget),
    )


def _is_session(cfg, step: int, held: int) -> bool:
    """A session at the seed steps' end, then every interval: under the ``asked`` budget until every label is
    asked, under ``answered`` on (the store stays full)."""
    t, fb = cfg.train, cfg.feedback
    on_time = step >= t.seed_steps and (step - t.seed_steps) % fb.interval == 0
    return on_time and (held < fb.labels or fb.budget == "answered")


def _expected_rounds(cfg) -> list[float]:
    """A round's seconds by the schedule written out; a session costs BASE + PER_LABEL * the labels held
    after it."""
    t, fb = cfg.train, cfg.feedback
    seconds, held = [], 0
    for r in range(math.ceil(t.total_steps / t.steps_per_round)):
        step = r * t.steps_per_round
        session = _is_session(cfg, step, held)
        held = min(held + fb.per_session, fb.labels) if session else held
        if r == 0:
            seconds.append(FIRST)
        elif session:
            seconds.append(PLAIN + BASE + PER_LABEL * held)
        elif step + t.steps_per_round <= t.seed_steps:
            seconds.append(SEED_ROUND)
        else:
            seconds.append(PLAIN)
    return seconds


def _metrics(cfg, columns: int = 2) -> list[dict]:
    """``metrics.jsonl`` records of a run that cost exactly :func:`_expected_rounds`."""
    t, fb = cfg.train, cfg.feedback
    rows, held = [], 0
    for r, seconds in enumerate(_expected_rounds(cfg)):
        step = r * t.steps_per_round
        session = _is_session(cfg, step, held)
        held = min(held + fb.per_session, fb.labels) if session else held
        rows.append(
            {
                "round": r,
                "env_steps": step + t.steps_per_round,
                "seconds": seconds,
                "labels_used": [float(held)] * columns,
                "session_labels": [float(fb.per_session) if session else None] * columns,
            }
        )
    return rows


def test_round_costs_read_back_the_costs_a_run_was_made_of():
    cfg = _config(150_000)
    costs = job_time.round_costs(_metrics(cfg), cfg)
    assert costs.first == FIRST and costs.seed_step == SEED_ROUND and costs.plain == PLAIN
    assert costs.session_base == pytest.approx(BASE) and costs.session_per_label == pytest.approx(PER_LABEL)
    assert costs.sessions == 15


@pytest.mark.parametrize("budget", ["asked", "answered"])
@pytest.mark.parametrize("longer", [150_000, 500_000, 1_000_000])
def test_a_projection_to_another_length_follows_the_label_schedule(longer, budget):
    # Fitted on 80k steps (8 sessions, 200 labels), projected to runs whose sessions go on to the budget of
    # 1,000 labels (40 sessions) and past it: none after the 40th (asked), or sessions on 1,000 labels (answered).
    short, long = _config(80_000, budget), _config(longer, budget)
    costs = job_time.round_costs(_metrics(short), short)
    assert job_time.round_seconds(costs, long) == pytest.approx(_expected_rounds(long))


def test_project_reads_a_run_directory(tmp_path):
    cfg = _config(40_000)
    (tmp_path / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    (tmp_path / "metrics.jsonl").write_text("".join(json.dumps(row) + "\n" for row in _metrics(cfg)))
    out = job_time.project(tmp_path, 300_000)
    assert out["measured_steps"] == 40_000
    assert out["measured_s"] == pytest.approx(sum(_expected_rounds(cfg)))
    assert out["own_length_s"] == pytest.approx(out["measured_s"])
    assert out["projected_s"] == pytest.approx(sum(_expected_rounds(_config(300_000))))
    # Fitted on its first 20k steps (2 sessions) only, the projection still holds: the costs are exact.
    assert job_time.project(tmp_path, 300_000, fit_steps=20_000)["projected_s"] == pytest.approx(out["projected_s"])
    with pytest.raises(ValueError, match="no plain round"):
        job_time.project(tmp_path, 300_000, fit_steps=2_000)


def test_a_run_without_a_plain_round_or_a_log_is_refused(tmp_path, capsys):
    cfg = _config(2_000)  # seed steps only
    with pytest.raises(ValueError, match="no plain round"):
        job_time.round_costs(_metrics(cfg), cfg)
    with pytest.raises(SystemExit, match="config.json"):
        job_time.main([str(tmp_path / "missing"), "--total-steps", "1000"])
    with pytest.raises(SystemExit):
        job_time.main([str(tmp_path), "--total-steps", "0"])
    assert "must be positive" in capsys.readouterr().err
