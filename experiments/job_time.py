"""How long a run would take at another length, projected from a run's own round times.

Usage:
  python experiments/job_time.py RUN_DIR [RUN_DIR ...] --total-steps 250000 [--fit-steps 80000]

For planning device sessions (BENCHMARKS.md, "plan every GPU session"): a run directory's
``metrics.jsonl`` gives each round's seconds, its ``config.json`` the schedule. The projection keeps the
run's program (task, algorithm, columns, device) and changes only ``train.total_steps``:

- the first round (the compile and the first seed steps) as measured;
- every later seed-step round (no updates yet) at the run's median seed-step round;
- every plain round at the run's median plain round;
- every feedback session round (``train.session_due``) at the plain median plus a session cost
  ``a + b * labels``, fitted by least squares to the run's session rounds, ``labels`` being the pairs each
  column holds after that session (``labels_used``). Sessions train on every stored label (SURF's all 20
  passes; PEBBLE's until its accuracy stops them), so their cost grows with the labels.

A run with fewer than two sessions fits ``b = 0``. Sessions past the run's last label count extrapolate the
line. It does not change the number of columns or the device: run a job at the size it is planned for.
"""

from __future__ import annotations

import argparse
import dataclasses
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


def project(run_dir: str | pathlib.Path, total_steps: int, fit_steps: int | None = None) -> dict:
    """A run's measured costs and its projected seconds at ``total_steps`` agent steps (and at its own length,
    to set against what it took). ``fit_steps`` fits the costs on the rounds up to that step only: a check of
    the projection against the rest of the run."""
    run_dir = pathlib.Path(run_dir)
    cfg = read_config(run_dir / "config.json")
    rows = records(run_dir)
    costs = round_costs([r for r in rows if fit_steps is None or r["env_steps"] <= fit_steps], cfg)
    longer = dataclasses.replace(cfg, train=dataclasses.replace(cfg.train, total_steps=total_steps))
    return {
        "run": run_dir.name,
        "costs": costs._asdict(),
        "measured_steps": rows[-1]["env_steps"],
        "measured_s": sum(r["seconds"] for r in rows),
        "own_length_s": sum(round_seconds(costs, cfg)[: len(rows)]),
        "total_steps": total_steps,
        "projected_s": sum(round_seconds(costs, longer)),
    }


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", type=pathlib.Path, help="run directories (config.json, metrics.jsonl)")
    p.add_argument("--total-steps", type=int, required=True, help="agent steps of the projected run")
    p.add_argument("--fit-steps", type=int, default=None, help="fit on the rounds up to this step (default: all)")
    args = p.parse_args(argv)
    if args.total_steps < 1 or (args.fit_steps is not None and args.fit_steps < 1):
        p.error("--total-steps and --fit-steps must be positive agent steps")
    print("| run | plain s | session s: a + b x labels | measured: steps, s (fit at its length) | projected s |")
    print("|---|---:|---:|---:|---:|")
    for run in args.runs:
        try:
            out = project(run, args.total_steps, args.fit_steps)
        except (FileNotFoundError, ValueError) as err:
            sys.exit(f"error: {run}: {err}")
        c = out["costs"]
        print(
            f"| {out['run']} | {c['plain']:.2f} | {c['session_base']:.1f} + {c['session_per_label']:.3f} x labels "
            f"({c['sessions']} sessions) | {out['measured_steps']:,}, {out['measured_s']:,.0f} "
            f"({out['own_length_s']:,.0f}) | {out['projected_s']:,.0f} at {out['total_steps']:,} |"
        )


if __name__ == "__main__":
    main()
