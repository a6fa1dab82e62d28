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


def _metrics(cfg, columns: int = 2, rounds: list[float] | None = None) -> list[dict]:
    """``metrics.jsonl`` records of a run that cost exactly ``rounds`` (default :func:`_expected_rounds`)."""
    t, fb = cfg.train, cfg.feedback
    rows, held = [], 0
    for r, seconds in enumerate(_expected_rounds(cfg) if rounds is None else rounds):
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


def _write_run(run_dir: pathlib.Path, cfg, columns: int = 2, rounds=None, device: str = "NVIDIA H200") -> pathlib.Path:
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "config.json").write_text(json.dumps(dataclasses.asdict(cfg)))
    (run_dir / "meta.json").write_text(json.dumps({"columns": columns, "devices": [device]}))
    rows = _metrics(cfg, columns, rounds)
    (run_dir / "metrics.jsonl").write_text("".join(json.dumps(row) + "\n" for row in rows))
    return run_dir


def test_project_reads_a_run_directory(tmp_path):
    cfg = _config(40_000)
    _write_run(tmp_path, cfg)
    out = job_time.project(tmp_path, 300_000)
    assert out["measured_steps"] == 40_000 and out["device"] == "NVIDIA H200"  # as _write_run's meta.json
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


ALPHA, BETA = 1.1, 1.2  # plain round = ALPHA + BETA x columns; a session costs per column


def _rounds_at(cfg, columns: int) -> list[float]:
    """A round's seconds for ``columns`` columns: the plain rounds on the line, the sessions' extra cost per column."""
    plain = ALPHA + BETA * columns
    out = []
    for seconds in _expected_rounds(cfg):
        if seconds in (FIRST, SEED_ROUND):
            out.append(seconds)
        else:  # PLAIN, or PLAIN + a session's (BASE + PER_LABEL x labels), the latter for each column
            out.append(plain + (seconds - PLAIN) * columns)
    return out


def test_columns_carry_a_run_to_another_size_on_the_plain_rounds_line(tmp_path, capsys):
    short = _config(60_000)
    runs = [_write_run(tmp_path / f"c{c}", short, c, _rounds_at(short, c)) for c in (2, 4)]
    assert job_time.fit_line(runs) == pytest.approx((ALPHA, BETA))
    for columns in (1, 3):
        out = job_time.project(runs[1], 250_000, columns=columns, line=(ALPHA, BETA))
        assert out["columns"] == columns
        assert out["projected_s"] == pytest.approx(sum(_rounds_at(_config(250_000), columns)))
    job_time.main([*map(str, runs), "--total-steps", "250000", "--columns", "1"])
    assert "1.10 + 1.20 s per column" in capsys.readouterr().out


def test_columns_refuse_one_size_other_tasks_or_devices_and_state_runs(tmp_path):
    pixels = _config(60_000)
    two = _write_run(tmp_path / "two", pixels, 2, _rounds_at(pixels, 2))
    with pytest.raises(ValueError, match="two column counts"):
        job_time.fit_line([two, _write_run(tmp_path / "again", pixels, 2, _rounds_at(pixels, 2))])
    h100 = _write_run(tmp_path / "h100", pixels, 4, _rounds_at(pixels, 4), device="NVIDIA H100 80GB HBM3")
    with pytest.raises(ValueError, match="one task on one device"):
        job_time.fit_line([two, h100])
    state = dataclasses.replace(PRESETS["paper"], train=dataclasses.replace(PRESETS["paper"].train, total_steps=60_000))
    costs = job_time.round_costs(_metrics(pixels), pixels)
    with pytest.raises(ValueError, match="session_loop"):
        job_time.at_columns(costs, state, 2, 1, (ALPHA, BETA))
