"""Do two runs of one protocol learn alike? Their seeds' mean return side by side, step by step, from their logs.

Usage:
  python benchmarks/learning_check.py RUN_A RUN_B [--every 50000] [--key eval_return]

For every ``--every``-th env step both runs logged, prints each run's mean of ``--key`` over its seeds (and the
seeds' standard deviation), the difference of the means (B minus A) and its standard error,
``sqrt(std_a^2 / n_a + std_b^2 / n_b)`` with the seeds' sample standard deviations: a difference within about two
standard errors is within the seeds' noise. Steps one run has not reached are left out, so a run stopped early
compares over what it reached. A change that should not alter learning (another physics backend, a faster
kernel) is checked this way against the same command on the same seeds.
"""

from __future__ import annotations

import argparse
import pathlib

import numpy as np

from rebel_jax.run.rundir import log_records


def returns(run_dir: pathlib.Path, key: str = "eval_return") -> dict[int, np.ndarray]:
    """A run's per-seed ``key`` by env step, for the rows that logged it (a last line cut mid-write left out)."""
    rows = [record for _, record in log_records(run_dir / "metrics.jsonl")[0]]
    return {r["env_steps"]: np.asarray(r[key], np.float64) for r in rows if r.get(key) is not None}


def row(a: np.ndarray, b: np.ndarray) -> tuple[float, float, float, float, float, float]:
    """Means and sample standard deviations of both runs' seeds, the difference of the means (b - a), its error."""
    if a.size < 2 or b.size < 2:
        raise SystemExit("error: a standard error needs at least 2 seeds in each run")
    sa, sb = float(np.std(a, ddof=1)), float(np.std(b, ddof=1))
    return a.mean(), sa, b.mean(), sb, b.mean() - a.mean(), float(np.sqrt(sa**2 / a.size + sb**2 / b.size))


def table(run_a: pathlib.Path, run_b: pathlib.Path, every: int = 50_000, key: str = "eval_return") -> str:
    """One row per ``every``-th step both runs logged."""
    a, b = returns(run_a, key), returns(run_b, key)
    steps = sorted(s for s in a.keys() & b.keys() if s % every == 0)
    if not steps:
        raise SystemExit(f"error: {run_a.name} and {run_b.name} share no logged step that is a multiple of {every}")
    lines = [
        f"| env steps | {run_a.name} | {run_b.name} | difference (B - A) | standard error |",
        "|---:|---:|---:|---:|---:|",
    ]
    for s in steps:
        ma, sa, mb, sb, diff, err = row(a[s], b[s])
        lines.append(f"| {s:,} | {ma:.1f} +- {sa:.1f} | {mb:.1f} +- {sb:.1f} | {diff:+.1f} | {err:.1f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run_a", type=pathlib.Path)
    parser.add_argument("run_b", type=pathlib.Path)
    parser.add_argument("--every", type=int, default=50_000, help="compare at multiples of this many env steps")
    parser.add_argument("--key", default="eval_return", help="the per-seed metric to compare")
    args = parser.parse_args(argv)
    if args.every < 1:
        parser.error(f"--every must be at least 1, got {args.every}")
    names = f"{args.run_a.name} (A) and {args.run_b.name} (B)"
    print(f"Mean {args.key} of the seeds (+- their standard deviation), {names}:\n")
    print(table(args.run_a, args.run_b, args.every, args.key))


if __name__ == "__main__":
    main()
