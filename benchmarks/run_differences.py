"""How far apart two runs of the same configuration are, round by round, from their logs.

Usage:
  python benchmarks/run_differences.py RUN_A RUN_B [--keys eval_return train_return critic_loss q]

For each round both runs logged and each key, prints the largest relative difference over the seeds,
``max_i |a_i - b_i| / max(|b_i|, 1e-6)``, as a markdown table. Two launches of one program (one process
against several, say) compare with two repeats of the same launch this way: on a GPU without
``--xla_gpu_deterministic_ops=true`` even the repeats differ (BENCHMARKS.md, "Is a GPU run reproducible?").
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np

KEYS = ("eval_return", "train_return", "critic_loss", "q")


def rounds(run_dir: pathlib.Path) -> dict[int, dict]:
    """A run's ``metrics.jsonl`` rows by round."""
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return {row["round"]: row for row in map(json.loads, filter(str.strip, lines))}


def largest_relative(a, b) -> float:
    """The largest of ``|a_i - b_i| / max(|b_i|, 1e-6)`` over the seeds."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    if a.shape != b.shape:
        raise SystemExit(f"error: the runs have different seed counts ({a.shape} against {b.shape})")
    return float(np.max(np.abs(a - b) / np.maximum(np.abs(b), 1e-6)))


def table(run_a: pathlib.Path, run_b: pathlib.Path, keys=KEYS) -> str:
    """One row per round both runs logged, one column per key."""
    a, b = rounds(run_a), rounds(run_b)
    lines = ["| round | " + " | ".join(keys) + " |", "|---:|" + "---:|" * len(keys)]
    for r in sorted(a.keys() & b.keys()):
        cells = [f"{largest_relative(a[r][k], b[r][k]):.3f}" if k in a[r] and k in b[r] else "-" for k in keys]
        lines.append(f"| {r} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_a", type=pathlib.Path)
    parser.add_argument("run_b", type=pathlib.Path)
    parser.add_argument("--keys", nargs="+", default=list(KEYS), help="per-seed metrics to compare")
    args = parser.parse_args(argv)
    print(f"Largest relative difference over the seeds, {args.run_a.name} against {args.run_b.name}:\n")
    print(table(args.run_a, args.run_b, args.keys))


if __name__ == "__main__":
    main()
