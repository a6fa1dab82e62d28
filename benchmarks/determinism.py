"""Does one program, run twice from the same seed keys, give the same state bit for bit? And what do XLA's
deterministic GPU ops cost?

Why (RESULTS.md, question 4): three H100 teacher programs with one round program and the
same seed keys already differed in their PEBBLE columns' round-0 returns, before any label. If a repeat of one
program differs too, the GPU runs are not reproducible, and seed-paired comparisons pair initial states only.

In one process: build the run's trainer from CLI flags (``cli.parse``), then twice ``init`` from the same keys and
``--rounds`` rounds; compare the two final states leaf by leaf and the rounds' metrics. Run it once without and
once with ``--xla-flags=--xla_gpu_deterministic_ops=true`` (a flag is read when the backend starts, so one process
per setting). One row per run in ``benchmarks/results/determinism.json``: identical or not, how many state leaves
differ and by how much, and the seconds of each round of both repeats (the first includes the compile).

    python benchmarks/determinism.py --rounds 2 -- pebble --preset paper --task walker_walk --feedback.labels 100 \\
        --seeds 5 --sac.precision bf16 [--xla-flags=--xla_gpu_deterministic_ops=true]
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
from timing import add_xla_flags_argument, merge_rows, provenance, use_xla_flags

RESULTS = pathlib.Path(__file__).parent / "results" / "determinism.json"


def run_twice(flags: list[str], rounds: int) -> tuple[list, list[list[float]], list[list[dict]]]:
    """Two runs of ``rounds`` rounds of the configuration ``flags`` from the same seed keys, in one process (the
    second reuses the first's compiled programs). Returns both final states (on the host), the seconds of each
    round and the rounds' metrics."""
    from rebel_jax.run.cli import column_keys, initial_state, parse
    from rebel_jax.train import Trainer, compiled

    args = parse(flags)
    if args.config.pixels or args.host_teacher:
        raise SystemExit("error: a state-based run with a scripted teacher is needed")
    init, round_fn, _ = compiled(Trainer(args.config))
    states, seconds, metrics = [], [], []
    for _ in range(2):
        state, times, logged = initial_state(args, init, column_keys(args)), [], []
        for r in range(rounds):
            start = time.perf_counter()
            state, m = round_fn(state, jnp.int32(r))
            logged.append(jax.device_get(m))
            times.append(time.perf_counter() - start)
        states.append(jax.device_get(state))
        seconds.append(times)
        metrics.append(logged)
    return states, seconds, metrics


def compare(a, b) -> dict:
    """How two states differ: leaves compared, leaves not bit for bit equal, and their largest absolute
    difference (over the floating leaves; NaNs in the same places count as equal)."""
    leaves_a, leaves_b = jax.tree.leaves(a), jax.tree.leaves(b)
    differ, largest = 0, 0.0
    for x, y in zip(leaves_a, leaves_b, strict=True):
        if hasattr(x, "dtype") and jax.dtypes.issubdtype(x.dtype, jax.dtypes.prng_key):  # typed keys: their raw data
            x, y = jax.random.key_data(x), jax.random.key_data(y)
        x, y = np.asarray(x), np.asarray(y)
        if not np.array_equal(x, y, equal_nan=np.issubdtype(x.dtype, np.inexact)):
            differ += 1
            if np.issubdtype(x.dtype, np.inexact):
                largest = max(largest, float(np.nanmax(np.abs(x.astype(np.float64) - y.astype(np.float64)))))
    return {"leaves": len(leaves_a), "differing_leaves": differ, "max_abs_difference": largest}


def metrics_equal(a: list[dict], b: list[dict]) -> bool:
    """Whether two runs logged the same metrics in every round (NaN where the other has NaN)."""
    return all(
        np.array_equal(np.asarray(x[k]), np.asarray(y[k]), equal_nan=True) for x, y in zip(a, b, strict=True) for k in x
    )


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flags", nargs="*", help="the training CLI's flags (after --)")
    p.add_argument("--rounds", type=int, default=2, help="rounds per run (the first compiles)")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    add_xla_flags_argument(p)
    return p


def main() -> None:
    args = parser().parse_args()
    if args.rounds < 1:
        raise SystemExit("error: --rounds must be >= 1")
    use_xla_flags(args.xla_flags)
    states, seconds, metrics = run_twice(args.flags, args.rounds)
    row = {
        **provenance(),
        "flags": " ".join(args.flags),
        "rounds": args.rounds,
        **compare(*states),
        "metrics_equal": metrics_equal(*metrics),
        "round_seconds": [[round(t, 2) for t in times] for times in seconds],
    }
    row["identical"] = row["differing_leaves"] == 0 and row["metrics_equal"]
    merge_rows(args.out, [row], ("device", "commit", "flags", "rounds", "xla_flags"))
    print(
        f"identical: {row['identical']} ({row['differing_leaves']} of {row['leaves']} state leaves differ, largest "
        f"absolute difference {row['max_abs_difference']:.3g}); round seconds {row['round_seconds']}"
    )


if __name__ == "__main__":
    main()
