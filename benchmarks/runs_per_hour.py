"""Runs per GPU-hour of a sweep program, projected to a full job from a short run's logs.

Usage:
  python benchmarks/runs_per_hour.py RUN_DIR [RUN_DIR ...] [--total-steps 500000]

A run is one column (one seed of one setting). A job of ``--total-steps`` steps is its first round (the compile
included) and then ``total_steps / steps_per_round - 1`` rounds at the median of the run's later rounds
(``benchmarks/scaling.py``'s reading of ``metrics.jsonl``; ``steps_per_round`` from ``config.json``). Runs per
GPU-hour = columns x 3,600 s / (devices x the job's projected seconds). Prints one markdown table.
"""

from __future__ import annotations

import argparse
import json
import pathlib

from scaling import run_rate


def projection(run_dir: pathlib.Path, total_steps: int) -> dict:
    """The run's rate and first round (``scaling.run_rate``) and the projected job: seconds and runs/GPU-hour."""
    rate = run_rate(run_dir)
    per_round = json.loads((run_dir / "config.json").read_text())["train"]["steps_per_round"]
    rounds = -(-total_steps // per_round)
    job = rate["first"] + (rounds - 1) * rate["median"]
    per_hour = rate["columns"] * 3600 / (rate["devices"] * job)
    return {**rate, "rounds": rounds, "job": job, "per_hour": per_hour}


def table(rows: list[dict], total_steps: int) -> str:
    lines = [
        f"| run | devices | columns | first round (s) | median round (s) | {total_steps:,}-step job (s) "
        "| runs per GPU-hour |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['run']} | {r['devices']} x {r['device']} | {r['columns']} | {r['first']:.1f} | {r['median']:.2f} | "
            f"{r['job']:,.0f} | {r['per_hour']:.1f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", type=pathlib.Path, nargs="+")
    parser.add_argument("--total-steps", type=int, default=500_000, help="the full job's env steps per seed")
    args = parser.parse_args(argv)
    if args.total_steps < 1:
        raise SystemExit(f"error: --total-steps must be >= 1; got {args.total_steps}")
    print(table([projection(run, args.total_steps) for run in args.runs], args.total_steps))


if __name__ == "__main__":
    main()
