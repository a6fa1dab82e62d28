"""Scaling efficiency of a run over several devices against a run on one, from the two runs' logs.

Usage:
  python benchmarks/scaling.py MULTI_RUN_DIR ONE_RUN_DIR [--first-round 1]

Each run directory holds ``meta.json`` (devices, JAX version, command, start) and ``metrics.jsonl``
(``seconds`` per round). A run's rate is its columns (``meta.json``) over the median round time of the
rounds from ``--first-round`` on (round 0 holds the compile). Efficiency is the multi-device run's rate
over ``devices`` x the one-device run's rate: 1.0 when each device runs its columns as fast as one device
alone runs as many. Prints one markdown table.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import statistics


def run_rate(run_dir: pathlib.Path, first_round: int = 1) -> dict:
    """Columns, devices, round seconds (median and all, from ``first_round``; and round 0's, ``first``) and
    seed-rounds/s of one run."""
    meta = json.loads((run_dir / "meta.json").read_text())
    rounds = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
    seconds = [r["seconds"] for r in rounds if r["round"] >= first_round]
    if not seconds:
        raise SystemExit(f"error: {run_dir} has no round from round {first_round} on")
    median = statistics.median(seconds)
    return {
        "run": run_dir.name,
        "columns": meta["columns"],
        "devices": len(meta["devices"]),  # every process's devices
        "device": meta["devices"][0],
        "jax": meta["jax"],
        "commit": meta.get("git_commit"),
        "started": meta["started"],
        "command": meta["command"],
        "seconds": seconds,
        "first": rounds[0]["seconds"],
        "median": median,
        "rate": meta["columns"] / median,
    }


def efficiency(multi: dict, one: dict) -> float:
    """(seed-rounds/s of ``multi``) / (its devices x seed-rounds/s of ``one``)."""
    return multi["rate"] / (multi["devices"] * one["rate"])


def table(multi: dict, one: dict) -> str:
    """Both runs and the efficiency as markdown."""
    lines = ["| run | devices | columns | rounds (s) | median (s) | seed-rounds/s |", "|---|---:|---:|---|---:|---:|"]
    for r in (multi, one):
        rounds = ", ".join(f"{s:.2f}" for s in r["seconds"])
        lines.append(
            f"| {r['run']} | {r['devices']} x {r['device']} | {r['columns']} | {rounds} | {r['median']:.2f} | "
            f"{r['rate']:.3f} |"
        )
    lines.append("")
    lines.append(f"Scaling efficiency: **{efficiency(multi, one):.3f}** (JAX {multi['jax']}, code {multi['commit']}).")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("multi", type=pathlib.Path)
    parser.add_argument("one", type=pathlib.Path)
    parser.add_argument("--first-round", type=int, default=1, help="the first round counted (0 holds the compile)")
    args = parser.parse_args(argv)
    print(table(run_rate(args.multi, args.first_round), run_rate(args.one, args.first_round)))


if __name__ == "__main__":
    main()
