"""DrQ-v2's random shift, three ways: the per-image window (``drqv2.shift_images``, a gather once vmapped), the same
with its shifts behind ``jax.lax.optimization_barrier`` (``drqv2.random_shift``'s form: the draws are not fused into
the window), and separable selects over the ``2 pad + 1`` row and column offsets (:func:`shift_by_selects`).

    python benchmarks/shift_bench.py                  # walker's batch 512, 84x84, 9 channels, pad 4
    python benchmarks/shift_bench.py --batch-size 8 --size 16 --repeats 2   # a CPU check

Each row: the median milliseconds of one shift of a uint8 batch (``u8``), and of the shift followed by the
encoder's scaling to float32 and bf16 (``scaled``: ``x / 255 - 0.5``, networks.py), over ``--repeats`` calls of
``--per-call`` shifts in a ``lax.scan`` that returns every output; the two ways' outputs are checked equal first.
``--hlo FILE`` also writes the optimised HLO of the 5-seed looped DrQ-v2 update of ``drqv2_update.update_scan``
(walker, bf16) to FILE.
Rows merge into ``benchmarks/results/shift_bench.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import statistics
import time

import jax
import jax.numpy as jnp
from drqv2_update import update_scan
from timing import merge_rows, provenance

from rebel_jax.agents.drqv2 import DrQV2Config, draw_shifts, shift_images, task_config

RESULTS = pathlib.Path(__file__).parent / "results" / "shift_bench.json"


def shift_by_selects(obs: jax.Array, shifts: jax.Array, pad: int) -> jax.Array:
    """:func:`drqv2.shift_images` without a gather: the rows at each image's y offset, then the columns at its
    x offset, each picked by a select among the ``2 pad + 1`` static slices of the edge-padded batch."""
    _, height, width, _ = obs.shape
    padded = jnp.pad(obs, ((0, 0), (pad, pad), (pad, pad), (0, 0)), mode="edge")
    pick = lambda offset, n: shifts[:, offset, None, None, None] == n
    rows = padded[:, :height]
    for n in range(1, 2 * pad + 1):
        rows = jnp.where(pick(1, n), padded[:, n : n + height], rows)
    out = rows[:, :, :width]
    for n in range(1, 2 * pad + 1):
        out = jnp.where(pick(0, n), rows[:, :, n : n + width], out)
    return out


WAYS = {
    "gather": shift_images,
    "selects": shift_by_selects,
    # The shifts drawn once, kept out of the window's fusion (as drqv2.random_shift does).
    "gather_barrier": lambda obs, shifts, pad: shift_images(obs, jax.lax.optimization_barrier(shifts), pad),
}


def scaled(images: jax.Array) -> jax.Array:
    """The encoder's input scaling (networks.py, ``Encoder``), cast to bf16 as its convolutions take it."""
    return (images.astype(jnp.float32) / 255.0 - 0.5).astype(jnp.bfloat16)


def timed(fn, obs, pad, per_call, repeats) -> float:
    """Median seconds per shift of ``fn`` (images, shifts, pad) on ``obs``, each shift with new offsets."""

    @jax.jit
    def run(key):
        def body(carry, key):  # every output is returned (the scan's ys), so none of the work can be dropped
            return carry, fn(obs, draw_shifts(key, obs.shape[0], pad), pad)

        return jax.lax.scan(body, None, jax.random.split(key, per_call))[1]

    jax.block_until_ready(run(jax.random.PRNGKey(0)))
    times = []
    for i in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(run(jax.random.PRNGKey(1 + i)))
        times.append((time.perf_counter() - start) / per_call)
    return statistics.median(times)


def rows(args):
    obs = jax.random.randint(jax.random.PRNGKey(0), (args.batch_size, args.size, args.size, 9), 0, 256).astype(
        jnp.uint8
    )
    shifts = draw_shifts(jax.random.PRNGKey(1), args.batch_size, args.pad)
    reference = jax.jit(shift_images, static_argnums=2)(obs, shifts, args.pad)
    for name, fn in WAYS.items():
        if not bool(jnp.array_equal(jax.jit(fn, static_argnums=2)(obs, shifts, args.pad), reference)):
            raise SystemExit(f"{name} differs from drqv2.shift_images")
        for output, wrapped in (("u8", fn), ("scaled", lambda o, s, p, fn=fn: scaled(fn(o, s, p)))):
            sec = timed(wrapped, obs, args.pad, args.per_call, args.repeats)
            row = {
                **provenance(),
                "way": name,
                "output": output,
                "batch_size": args.batch_size,
                "size": args.size,
                "pad": args.pad,
                "ms": round(sec * 1e3, 4),
            }
            print(json.dumps(row), flush=True)
            yield row


def write_hlo(path: pathlib.Path) -> None:
    cfg = dataclasses.replace(task_config("walker_walk", DrQV2Config(precision="bf16")), seed_loop=True)
    run, state = update_scan(cfg, 84, 5, 2)
    path.write_text(run.lower(state, jax.random.PRNGKey(1)).compile().as_text())


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--batch-size", type=int, default=512)
    p.add_argument("--size", type=int, default=84)
    p.add_argument("--pad", type=int, default=4)
    p.add_argument("--per-call", type=int, default=20)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--hlo", type=pathlib.Path, default=None, help="write the DrQ-v2 update's optimised HLO here")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    merge_rows(args.out, rows(args), ("device", "commit", "way", "output", "batch_size", "size", "pad"))
    if args.hlo:
        write_hlo(args.hlo)


if __name__ == "__main__":
    main()
