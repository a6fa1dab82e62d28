"""Where the GPU time of the seed-vmapped DrQ-v2 update goes, kernel by kernel, from a JAX profiler trace.

    python benchmarks/drqv2_profile.py --precision bf16     # 84x84, 5 seeds looped, walker (batch 512, n-step 1)
    python benchmarks/drqv2_profile.py --size 16 --batch-size 8 --seeds 2 --repeats 2   # a CPU check

The program is ``drqv2_update.update_scan``'s (fixed random frame stacks, ``--updates-per-call`` updates per jitted
call). After a warm-up call, ``--repeats`` calls run under ``jax.profiler.trace``; the trace's events that carry an
``hlo_op`` of this program (on the GPU the kernels of the device plane's streams, on the CPU the host's thunks) are
summed per HLO instruction, and each instruction is put in a category read from the compiled HLO text
(:func:`categories`): the cuDNN convolutions by direction, matrix products, fusions by kind, and the rest by opcode.
The row (merged into ``benchmarks/results/drqv2_profile.json``) gives milliseconds per update of every seed, per
category and for the ``--top`` instructions, beside the wall time of the same calls: what the trace's kernels leave
of the wall time is launch gaps and the host. XLA's command buffers (CUDA graphs) are traced as one event each,
named ``command_buffer_<n>`` and counted as "not in the HLO"; ``--xla-flags=--xla_gpu_enable_command_buffer=``
turns them off, so that their kernels are traced one by one.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import pathlib
import re
import tempfile
import time

import jax
from drqv2_update import program_fields, update_scan
from timing import add_xla_flags_argument, merge_rows, provenance, use_xla_flags

from rebel_jax.drqv2 import DrQV2Config, task_config

RESULTS = pathlib.Path(__file__).parent / "results" / "drqv2_profile.json"
_INSTRUCTION = re.compile(r"^\s*(?:ROOT\s+)?%?([\w.\-]+)\s*=\s*(.*)$")
_OPCODE = re.compile(r"(?:^|\s)([a-z][a-z0-9\-]*)\(")
_TARGET = re.compile(r'custom_call_target="([^"]+)"')
_KIND = re.compile(r"kind=(k\w+)")
CONVOLUTIONS = {
    "convForward": "convolution forward",
    "convBiasActivationForward": "convolution forward",
    "convBackwardInput": "convolution input gradient",
    "convBackwardFilter": "convolution kernel gradient",
}


def category(rest: str) -> str:
    """The category of one HLO instruction from the text after its ``=`` (shape, opcode, operands, attributes)."""
    opcode = _OPCODE.search(rest)
    opcode = opcode.group(1) if opcode else "unknown"
    if opcode == "custom-call":
        target = _TARGET.search(rest)
        target = target.group(1) if target else ""
        for name, label in CONVOLUTIONS.items():
            if target.endswith(name):
                return label
        if "gemm" in target or "matmul" in target:
            return "matrix product"
        return f"custom-call {target}"
    if opcode == "convolution":
        return "convolution (XLA)"
    if opcode in ("dot", "cublas-gemm"):
        return "matrix product"
    if opcode == "fusion":
        if "triton_gemm" in rest:
            return "matrix product"
        kind = _KIND.search(rest)
        return f"fusion {kind.group(1) if kind else ''}".strip()
    return opcode


def categories(hlo: str) -> dict[str, str]:
    """HLO instruction name -> :func:`category`, for every instruction of every computation of ``hlo``'s text."""
    found = {}
    for line in hlo.splitlines():
        match = _INSTRUCTION.match(line)
        if match:
            found[match.group(1)] = category(match.group(2))
    return found


@dataclasses.dataclass(frozen=True)
class Event:
    """One traced event of a program's instruction: its ``hlo_op`` and duration."""

    op: str
    nanoseconds: float


def trace_events(path: pathlib.Path, module: str) -> tuple[list[Event], list[str]]:
    """The events of the ``.xplane.pb`` under ``path`` whose ``hlo_module`` stat names ``module``, with the lines
    they came from: the device planes' stream lines where a ``/device:`` plane exists, else every host line."""
    (xplane,) = path.rglob("*.xplane.pb")
    planes = list(jax.profiler.ProfileData.from_file(str(xplane)).planes)
    devices = [plane for plane in planes if plane.name.startswith("/device:")]
    events, lines = [], set()
    for plane in devices or planes:
        for line in plane.lines:
            if devices and not line.name.startswith("Stream"):
                continue  # derived lines (XLA Ops, XLA Modules) repeat the streams' kernels
            for event in line.events:
                stats = dict(event.stats)
                if "hlo_op" in stats and module in str(stats.get("hlo_module", "")):
                    events.append(Event(str(stats["hlo_op"]), float(event.duration_ns)))
                    lines.add(f"{plane.name} {line.name}")
    return events, sorted(lines)


def summarize(events: list[Event], kinds: dict[str, str], updates: int, top: int) -> dict:
    """Milliseconds per update (``updates`` traced): the whole, per category, and the ``top`` instructions."""
    per_op: dict[str, float] = collections.defaultdict(float)
    calls: dict[str, int] = collections.defaultdict(int)
    for event in events:
        per_op[event.op] += event.nanoseconds
        calls[event.op] += 1
    per_category: dict[str, float] = collections.defaultdict(float)
    for op, ns in per_op.items():
        per_category[kinds.get(op, "not in the HLO")] += ns
    ms = lambda ns: round(ns / 1e6 / updates, 4)
    ranked = sorted(per_op, key=per_op.get, reverse=True)[:top]
    return {
        "traced_ms_per_update": ms(sum(per_op.values())),
        "categories": {name: ms(ns) for name, ns in sorted(per_category.items(), key=lambda kv: -kv[1])},
        "top": [
            {"op": op, "category": kinds.get(op, "not in the HLO"), "ms": ms(per_op[op]), "calls": calls[op] / updates}
            for op in ranked
        ],
    }


def row(args) -> dict:
    base = task_config("walker_walk", DrQV2Config(precision=args.precision))
    cfg = dataclasses.replace(
        base, batch_size=args.batch_size or base.batch_size, seed_loop=args.seed_loop == "on", kernel_grad="xla"
    )
    run, state = update_scan(cfg, args.size, args.seeds, args.updates_per_call)
    compiled = run.lower(state, jax.random.PRNGKey(1)).compile()
    kinds = categories(compiled.as_text())
    state = jax.block_until_ready(compiled(state, jax.random.PRNGKey(2)))  # warm-up
    with tempfile.TemporaryDirectory() as folder:
        with jax.profiler.trace(folder):
            start = time.perf_counter()
            for i in range(args.repeats):
                state = compiled(state, jax.random.PRNGKey(10 + i))
            jax.block_until_ready(state)
            wall = time.perf_counter() - start
        events, lines = trace_events(pathlib.Path(folder), "many")
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
