"""How long a run would take at another length, projected from a run's own round times.

Usage:
  python experiments/job_time.py RUN_DIR [RUN_DIR ...] --total-steps 250000 [--fit-steps 80000]

For planning device sessions (BENCHMARKS.md, "plan every GPU session"): a run directory's
``metrics.jsonl`` gives each round's seconds, its ``config.json`` the schedule. The projection keeps the
run's program (task, algorithm, columns, device; the table names the device from ``meta.json``) and changes only
``train.total_steps``:

- the first round (the compile and the first seed steps) as measured;
- every later seed-step round (no updates yet) at the run's median seed-step round;
- every plain round at the run's median plain round;
- every feedback session round (``train.session_due``) at the plain median plus a session cost
  ``a + b * labels``, fitted by least squares to the run's session rounds, ``labels`` being the pairs each
  column holds after that session (``labels_used``). Sessions train on every stored label (SURF's all 20
  passes; PEBBLE's until its accuracy stops them), so their cost grows with the labels.

A run with fewer than two sessions fits ``b = 0``. Sessions past the run's last label count extrapolate the
line. It does not change the device.

``--columns N`` projects each pixel run at N columns (seeds x lambdas) instead of its own: the plain round
from a line ``alpha + beta x columns`` fitted to the plain rounds of all the runs given (one task, one device,
at least two column counts; each column's updates run one after another, ``drqv2.seed_loop``, beside the
physics they share), and the session costs scaled by N over the run's columns (a pixel session trains one
column at a time, ``pixel_reward.session_loop``). The first and the seed-step rounds are kept.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import statistics
import sys
from typing import NamedTuple

import numpy as np

from rebel_jax.config import Config, read_config
from rebel_jax.plots import per_seed, records
from rebel_jax.train import session_due


class RoundCosts(NamedTuple):
    """A run's measured round costs, in seconds."""

    first: float
    """Round 0: the compile, then the round."""
    seed_step: float
    """Median of the later rounds that end within the seed steps (no updates); NaN if there are none."""
    plain: float
    """Median of the rounds after the seed steps without a session."""
    session_base: float
    """``a`` of a session round's extra cost ``a + b * labels`` over a plain round."""
    session_per_label: float
    """``b``: seconds per label held by each column after the session."""
    sessions: int
    """Session rounds the fit used."""


def _is_session(record: dict) -> bool:
    return not all(np.isnan(per_seed(record.get("session_labels"))))


def round_costs(rows: list[dict], cfg: Config) -> RoundCosts:
    """The costs of :class:`RoundCosts` from a run's ``metrics.jsonl`` records (``plots.records``).

    Raises:
      ValueError: if the run has no plain round after its seed steps.
    """
    later = rows[1:]
    seed = [r["seconds"] for r in later if r["env_steps"] <= cfg.train.seed_steps and not _is_session(r)]
    plain = [r["seconds"] for r in later if r["env_steps"] > cfg.train.seed_steps and not _is_session(r)]
    if not plain:
        raise ValueError("the run has no plain round after its seed steps: run it longer")
    plain_s = statistics.median(plain)
    sessions = [r for r in later if _is_session(r)]
    extra = np.array([r["seconds"] - plain_s for r in sessions])
    labels = np.array([np.nanmax(per_seed(r["labels_used"])) for r in sessions])
    if len(sessions) >= 2 and np.ptp(labels) > 0:
        per_label, base = np.polyfit(labels, extra, 1)
    else:
        per_label, base = 0.0, float(extra.mean()) if len(extra) else 0.0
    return RoundCosts(
        first=rows[0]["seconds"],
        seed_step=statistics.median(seed) if seed else float("nan"),
        plain=plain_s,
        session_base=float(base),
        session_per_label=float(per_label),
        sessions=len(sessions),
    )


def round_seconds(costs: RoundCosts, cfg: Config) -> list[float]:
    """Each round's projected seconds for a run of ``cfg`` (its ``train.total_steps``)."""
    per_round = cfg.train.steps_per_round
    seconds, labels = [], 0
    for r in range(cfg.train.num_rounds):
        due = cfg.preference and bool(session_due(cfg, r)[0])
        if due:  # The oracle answers every pair; the last session asks for what is left (B-Pref).
            labels = min(labels + cfg.feedback.queries, cfg.feedback.labels)
        if r == 0:  # Measured whole: the compile, and a session if one is due.
            seconds.append(costs.first)
        elif due:
            seconds.append(costs.plain + costs.session_base + costs.session_per_label * labels)
        elif (r + 1) * per_round <= cfg.train.seed_steps:
            seconds.append(costs.seed_step)
        else:
            seconds.append(costs.plain)
    return seconds


def columns_of(run_dir: pathlib.Path) -> int:
    """The run's columns (seeds x lambdas x teachers), from its ``meta.json``."""
    return int(json.loads((run_dir / "meta.json").read_text())["columns"])


def devices_of(run_dir: pathlib.Path) -> str:
    """The devices the run ran on, from its ``meta.json`` (an H100's rounds are not an H200's)."""
    return ", ".join(json.loads((run_dir / "meta.json").read_text())["devices"])


def plain_line(points: list[tuple[int, float]]) -> tuple[float, float]:
    """``(alpha, beta)`` of the least-squares line ``plain = alpha + beta x columns`` through ``(columns, plain)``.

    Raises:
      ValueError: with fewer than two column counts.
    """
    columns = np.array([c for c, _ in points], float)
    if len(set(columns)) < 2:
        raise ValueError("--columns needs runs of at least two column counts to fit the plain rounds' line")
    beta, alpha = np.polyfit(columns, [p for _, p in points], 1)
    return float(alpha), float(beta)


def at_columns(costs: RoundCosts, cfg: Config, own: int, columns: int, line: tuple[float, float]) -> RoundCosts:
    """``costs`` of a run of ``own`` columns carried to ``columns`` (the module's ``--columns``).

    Raises:
      ValueError: for a run whose sessions are not looped over its columns (state tasks batch them).
    """
    if not (cfg.pixels and cfg.pixel_reward.session_loop):
        raise ValueError("--columns needs pixel runs with pixel_reward.session_loop (one column's session at a time)")
    alpha, beta = line
    scale = columns / own
    return costs._replace(
        plain=alpha + beta * columns,
        session_base=costs.session_base * scale,
        session_per_label=costs.session_per_label * scale,
    )


def project(
    run_dir: str | pathlib.Path,
    total_steps: int,
    fit_steps: int | None = None,
    columns: int | None = None,
    line: tuple[float, float] | None = None,
) -> dict:
    """A run's measured costs and its projected seconds at ``total_steps`` agent steps (and at its own length,
    to set against what it took). ``fit_steps`` fits the costs on the rounds up to that step only: a check of
    the projection against the rest of the run. ``columns`` (with the plain rounds' ``line``,
    :func:`plain_line`) projects it at that many columns (:func:`at_columns`)."""
    run_dir = pathlib.Path(run_dir)
    cfg = read_config(run_dir / "config.json")
    rows = records(run_dir)
    costs = round_costs([r for r in rows if fit_steps is None or r["env_steps"] <= fit_steps], cfg)
    longer = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, total_steps=total_steps))
    own = columns_of(run_dir)
    projected = costs if columns is None else at_columns(costs, cfg, own, columns, line)
    return {
        "run": run_dir.name,
        "device": devices_of(run_dir),
        "columns": own if columns is None else columns,
        "costs": costs._asdict(),
        "measured_steps": rows[-1]["env_steps"],
        "measured_s": sum(r["seconds"] for r in rows),
        "own_length_s": sum(round_seconds(costs, cfg)[: len(rows)]),
        "total_steps": total_steps,
        "projected_s": sum(round_seconds(projected, longer)),
    }


def fit_line(runs: list[pathlib.Path], fit_steps: int | None = None) -> tuple[float, float]:
    """:func:`plain_line` through the given runs' plain rounds.

    Raises:
      ValueError: if the runs differ in task or device, or have fewer than two column counts.
    """
    points, where = [], set()
    for run in runs:
        cfg = read_config(run / "config.json")
        rows = [r for r in records(run) if fit_steps is None or r["env_steps"] <= fit_steps]
        points.append((columns_of(run), round_costs(rows, cfg).plain))
        where.add((cfg.env.task, devices_of(run)))
    if len(where) > 1:
        raise ValueError(f"--columns needs runs of one task on one device; got {sorted(where)}")
    return plain_line(points)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=pathlib.Path, help="run directories (config.json, metrics.jsonl)")
    p.add_argument("--total-steps", type=int, required=True, help="agent steps of the projected run")
    p.add_argument("--fit-steps", type=int, default=None, help="fit on the rounds up to this step (default: all)")
    p.add_argument("--columns", type=int, default=None, help="project pixel runs at this many columns (see above)")
    args = p.parse_args(argv)
    if args.total_steps < 1 or (args.fit_steps is not None and args.fit_steps < 1):
        p.error("--total-steps and --fit-steps must be positive agent steps")
    if args.columns is not None and args.columns < 1:
        p.error("--columns must be >= 1")
    line = None
    if args.columns is not None:
        try:
            line = fit_line(args.runs, args.fit_steps)
        except (FileNotFoundError, KeyError, ValueError) as err:
            sys.exit(f"error: {err}")
        print(f"plain rounds: {line[0]:.2f} + {line[1]:.2f} s per column")
    print(
        "| run | device | plain s | session s: a + b x labels | measured: steps, s (fit at its length) | projected s |"
    )
    print("|---|---|---:|---:|---:|---:|")
    for run in args.runs:
        try:
            out = project(run, args.total_steps, args.fit_steps, args.columns, line)
        except (FileNotFoundError, ValueError) as err:
            sys.exit(f"error: {run}: {err}")
        c = out["costs"]
        print(
            f"| {out['run']} | {out['device']} | {c['plain']:.2f} "
            f"| {c['session_base']:.1f} + {c['session_per_label']:.3f} x labels "
            f"({c['sessions']} sessions) | {out['measured_steps']:,}, {out['measured_s']:,.0f} "
            f"({out['own_length_s']:,.0f}) | {out['projected_s']:,.0f} at {out['total_steps']:,}, "
            f"{out['columns']} columns |"
        )


if __name__ == "__main__":
    main()
