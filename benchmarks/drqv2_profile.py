"""Where the GPU time of the seed-vmapped DrQ-v2 update goes, kernel by kernel, from a JAX profiler trace.

    python benchmarks/drqv2_profile.py --precision bf16     # 84x84, 5 seeds looped, walker (batch 512, n-step 1)
    python benchmarks/drqv2_profile.py --size 16 --batch-size 8 --seeds 2 --repeats 2   # a CPU check

The program is ``drqv2_update.update_scan``'s (fixed random frame stacks, ``--updates-per-call`` updates per jitted
call). After a warm-up call, ``--repeats`` calls run under ``jax.profiler.trace``; the trace's events that carry an
``hlo_op`` of this program (on the GPU the kernels of the device plane's streams, on the CPU the host's thunks) are
summed per HLO instruction, and each instruction is put in a category read from the compiled HLO text
(``kernel_profile.categories``): the cuDNN convolutions by direction, matrix products, fusions by kind, and the rest
by opcode.
The row (merged into ``benchmarks/results/drqv2_profile.json``) gives milliseconds per update of every seed, per
category and for the ``--top`` instructions, beside the wall time of the same calls: what the trace's kernels leave
of the wall time is launch gaps and the host. XLA's command buffers (CUDA graphs) are traced as one event each,
named ``command_buffer_<n>`` and counted as "not in the HLO"; ``--xla-flags=--xla_gpu_enable_command_buffer=``
turns them off, so that their kernels are traced one by one.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib

import jax
from drqv2_update import program_fields, update_scan
from kernel_profile import Event, categories, category, module_name, summarize, trace, trace_events
from timing import add_xla_flags_argument, merge_rows, provenance, use_xla_flags

from rebel_jax.agents.drqv2 import DrQV2Config, task_config

RESULTS = pathlib.Path(__file__).parent / "results" / "drqv2_profile.json"
__all__ = ["Event", "categories", "category", "main", "row", "summarize", "trace_events"]  # the tests' names


def row(args) -> dict:
    base = task_config("walker_walk", DrQV2Config(precision=args.precision))
    cfg = dataclasses.replace(
        base, batch_size=args.batch_size or base.batch_size, seed_loop=args.seed_loop == "on", kernel_grad="xla"
    )
    run, state = update_scan(cfg, args.size, args.seeds, args.updates_per_call)
    compiled = run.lower(state, jax.random.PRNGKey(1)).compile()
    kinds = categories(compiled.as_text())
    state = jax.block_until_ready(compiled(state, jax.random.PRNGKey(2)))  # warm-up
    run = lambda state, i: compiled(state, jax.random.PRNGKey(10 + i))
    events, lines, wall, _ = trace(run, state, args.repeats, module_name(compiled.as_text()))
    if not events:
        raise SystemExit("the trace holds no event of the update's program; nothing to report")
    updates = args.repeats * args.updates_per_call
    return {
        **provenance(),
        **program_fields(args, cfg),
        "updates": updates,
        "wall_ms_per_update": round(wall * 1e3 / updates, 4),
        "lines": lines,
        **summarize(events, kinds, updates, args.top),
    }


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--size", type=int, default=84, help="image height and width")
    p.add_argument("--batch-size", type=int, default=0, help="transitions per update (0: walker's 512)")
    p.add_argument("--precision", default="bf16", choices=["tf32", "highest", "bf16"])
    p.add_argument("--seed-loop", default="on", choices=["off", "on"])
    p.add_argument("--updates-per-call", type=int, default=10)
    p.add_argument("--repeats", type=int, default=5, help="traced calls")
    p.add_argument("--top", type=int, default=20, help="instructions listed by time")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    add_xla_flags_argument(p)
    return p


def main(argv=None):
    args = parser().parse_args(argv)
    if args.repeats < 1 or args.updates_per_call < 1:
        raise SystemExit("--repeats and --updates-per-call must be at least 1")
    use_xla_flags(args.xla_flags)
    result = row(args)
    print(json.dumps(result, indent=1), flush=True)
    key = ("device", "commit", "seeds", "size", "batch_size", "precision", "seed_loop", "xla_flags")
    merge_rows(args.out, [result], key)


if __name__ == "__main__":
    main()
