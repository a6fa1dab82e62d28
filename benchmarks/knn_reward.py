"""PEBBLE's pre-training reward (``pretrain.knn_reward``), seed-vmapped at B-Pref's walker shapes, by how each
chunk's smallest distances are found (``--select``: ``argmin``, ``rebel_jax.preference.pretrain.smallest``, or
``top_k``) and
by chunk size, at several fills of the pre-training buffer.

    python benchmarks/knn_reward.py                    # 5 seeds, batch 1024, 10,000 rows of 24 numbers
    python benchmarks/knn_reward.py --seeds 2 --batch-size 64 --rows 2000 --repeats 2   # a CPU check

Each row: the median milliseconds of one seed-vmapped reward (every seed's batch, drawn from its filled rows),
over ``--repeats`` calls of ``--per-call`` rewards in a ``lax.scan``; the ways' rewards are checked equal first.
The paper preset's pre-training reads 10,000 rows a seed (10 environments x 1,000 vector steps), filled from
1,000 to 10,000 as it runs. Rows merge into ``benchmarks/results/knn_reward.json``.
"""

from __future__ import annotations

import argparse
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
from timing import add_xla_flags_argument, median_seconds, merge_rows, provenance, use_xla_flags

from rebel_jax.preference.pretrain import knn_reward

RESULTS = pathlib.Path(__file__).parent / "results" / "knn_reward.json"


def reward_scan(args, filled: int, chunk_size: int, select: str):
    """``(total, key) -> total``: ``--per-call`` seed-vmapped rewards of batches drawn from the first ``filled``
    rows, and the buffer it reads."""
    buffer = jax.random.normal(jax.random.key(0), (args.seeds, args.rows, args.obs_size))
    valid = jnp.arange(args.rows) < filled

    def one(obs, key):
        batch = obs[jax.random.randint(key, (args.batch_size,), 0, filled)]
        return knn_reward(batch, obs, valid, args.k, chunk_size, select)

    def body(total, key):
        return total + jax.vmap(one)(buffer, jax.random.split(key, args.seeds)).sum(), None

    @jax.jit
    def run(total, key):
        return jax.lax.scan(body, total, jax.random.split(key, args.per_call))[0]

    return run


def rows(args):
    for filled in [int(f * args.rows) for f in args.fills]:
        runs = {(c, s): reward_scan(args, filled, c, s) for c in args.chunk_sizes for s in args.selects}
        totals = [np.asarray(run(jnp.zeros(()), jax.random.key(9))) for run in runs.values()]
        np.testing.assert_allclose(totals, totals[0], rtol=1e-5)
        for (chunk, select), run in runs.items():  # each compiled once, by the check above
            seconds = median_seconds(run, jnp.zeros(()), args.per_call, args.repeats)
            print(f"filled {filled:6d}  chunk {chunk:6d}  {select:7s}: {seconds * 1e3:8.3f} ms", flush=True)
            yield dict(
                provenance(),
                seeds=args.seeds,
                batch_size=args.batch_size,
                rows=args.rows,
                filled=filled,
                obs_size=args.obs_size,
                k=args.k,
                chunk_size=chunk,
                select=select,
                ms=seconds * 1e3,
            )


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--batch-size", type=int, default=1024)
    p.add_argument("--rows", type=int, default=10_000, help="buffer rows a seed (the pre-training buffer's)")
    p.add_argument("--obs-size", type=int, default=24, help="observation size (walker's 24)")
    p.add_argument("--k", type=int, default=5)
    p.add_argument("--fills", nargs="+", type=float, default=[0.1, 0.5, 1.0], help="filled share of the rows")
    p.add_argument("--chunk-sizes", nargs="+", type=int, default=[4096, 16384])
    p.add_argument("--selects", nargs="+", default=["argmin", "top_k"], choices=["argmin", "top_k"])
    p.add_argument("--per-call", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    add_xla_flags_argument(p)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    use_xla_flags(args.xla_flags)
    fields = ("device", "commit", "seeds", "batch_size", "rows", "filled", "chunk_size", "select", "xla_flags")
    merge_rows(args.out, rows(args), fields)


if __name__ == "__main__":
    main()
