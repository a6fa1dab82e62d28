"""SAC training throughput at ``paper`` sizes.

Usage:
  python benchmarks/train_throughput.py update [--seeds 5 1 10] [--precisions tf32 bf16] [--unrolls 1 10]
      [--budget-s 100]
  python benchmarks/train_throughput.py hlo [--seeds 5] [--precisions tf32 bf16]
  python benchmarks/train_throughput.py runs RUN_DIR [RUN_DIR ...]

``update`` times the jitted, seed-vmapped SAC update alone (median of repeated scans
of 20 updates after a warm-up; one ahead-of-time compile per row) and reports updates/s,
achieved TFLOP/s against the card's bf16 matmul ceiling and the number of kernel launches in
the compiled scan; ``--unrolls`` gives the updates per iteration of the scan's loop (10: a vector step's, as the
trainer compiles them with ``train.unroll_updates``). ``hlo`` compiles one update from shapes only (no run, works on
CPU) and reports its op counts and XLA's ``cost_analysis`` bytes. ``runs`` turns finished training runs (``python -m
rebel_jax.train``) into rows of whole-round throughput: seed-env-steps/s over the
rounds after the first (which includes compilation) and the projected wall time of
500k steps. Both merge rows into ``benchmarks/results/train_throughput.json``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import pathlib
import re
import statistics
import time

import jax
import jax.numpy as jnp
from timing import add_xla_flags_argument, device_name, median_seconds, merge_rows, provenance, use_xla_flags

from rebel_jax.agents import replay
from rebel_jax.agents.sac import SAC, update_flops
from rebel_jax.config import PRESETS

RESULTS = pathlib.Path(__file__).parent / "results" / "train_throughput.json"
BF16_CEILING_TFLOPS = {"NVIDIA H100 80GB HBM3": 798.0, "NVIDIA H200": 788.0}  # measured, see BENCHMARKS.md
UPDATES_PER_CALL = 20


def _row(**kw) -> dict:
    return {**provenance(), **kw}


def _update_scan(num_seeds: int, precision: str, unroll: int = 1):
    """(jitted ``(state, key) -> state`` doing UPDATES_PER_CALL seed-vmapped ``paper`` updates, state); ``unroll``
    updates per iteration of the compiled loop."""
    cfg = PRESETS["paper"]
    sac_cfg = cfg.sac.__class__(**{**vars(cfg.sac), "precision": precision})
    sac = SAC(sac_cfg, 24, 6)
    keys = jax.random.split(jax.random.PRNGKey(0), num_seeds)
    state = jax.jit(jax.vmap(sac.init))(keys)
    batch = replay.Transition(
        obs=jax.random.normal(keys[0], (num_seeds, sac_cfg.batch_size, 24)),
        action=jax.random.uniform(keys[0], (num_seeds, sac_cfg.batch_size, 6), minval=-1, maxval=1),
        reward=jax.random.uniform(keys[0], (num_seeds, sac_cfg.batch_size)),
        next_obs=jax.random.normal(keys[-1], (num_seeds, sac_cfg.batch_size, 24)),
        discount=jnp.ones((num_seeds, sac_cfg.batch_size)),
    )

    def many(state, key):
        body = lambda s, k: (jax.vmap(sac.update)(s, batch, jax.random.split(k, num_seeds))[0], None)
        return jax.lax.scan(body, state, jax.random.split(key, UPDATES_PER_CALL), unroll=unroll)[0]

    return jax.jit(many, donate_argnums=0), state


def time_update(num_seeds: int, precision: str, repeats: int = 5, unroll: int = 1) -> tuple[float, dict]:
    """(median seconds of one seed-vmapped SAC update at ``paper`` sizes, :func:`hlo_counts` of its scan).

    The scan is compiled once, ahead of time, and that executable is both timed and counted.
    """
    run, state = _update_scan(num_seeds, precision, unroll)
    compiled = run.lower(state, jax.random.PRNGKey(1)).compile()
    return median_seconds(compiled, state, UPDATES_PER_CALL, repeats), hlo_counts(compiled)


FREE_OPS = {"parameter", "tuple", "get-tuple-element", "bitcast", "constant", "after-all", "opt-barrier"}
GEMM_TARGETS = ("gemm", "matmul")  # __cublas$gemm, __cublas$lt$matmul, __onednn$matmul ...


def _computations(text: str) -> tuple[dict[str, list[str]], str]:
    """{computation name: its instruction lines} of an HLO module's text, and the entry's name."""
    comps, entry, name = {}, None, None
    for line in text.splitlines():
        header = re.match(r"^(ENTRY )?%?([\w.-]+) .*\{$", line)
        if header and not line.startswith(" "):
            name = header.group(2)
            comps[name] = []
            entry = name if header.group(1) else entry
        elif line.startswith("}"):
            name = None
        elif name is not None and " = " in line:
            comps[name].append(line)
    return comps, entry


def _opcode(line: str) -> str:
    """The opcode of one HLO instruction line (``%x = f32[2]{0} add(%a, %b), ...``)."""
    rhs = line.split(" = ", 1)[1]
    rhs = re.sub(r"^\([^=]*?\)\s", "", rhs)  # a tuple-shaped result
    match = re.search(r"([a-z][a-z0-9-]*)\(", rhs)
    return match.group(1) if match else "?"


def hlo_counts(compiled) -> dict:
    """Op counts of a compiled program (no timing).

    ``launches`` counts the instructions that run as kernels or library calls: every
    instruction of the entry computation and of the loop bodies and branches it runs, except
    parameters, tuples, bitcasts and constants (each fusion counts once, its insides not; a
    loop's body counts once, not once per trip).
    ``dots`` counts matmuls anywhere (fused dots and library gemm calls); ``bytes`` and
    ``flops`` are XLA's ``cost_analysis`` (a loop body counted once).
    """
    comps, entry = _computations(compiled.as_text())
    launched, todo, seen = [], [entry], set()
    while todo:
        name = todo.pop()
        if name in seen or name not in comps:
            continue
        seen.add(name)
        for line in comps[name]:
            op = _opcode(line)
            if op not in FREE_OPS:
                launched.append(op)
            if op in ("while", "conditional", "call"):
                callees = re.findall(
                    r"(?:body|condition|to_apply|true_computation|false_computation)=%?([\w.-]+)", line
                )
                branches = re.search(r"branch_computations=\{([^}]*)\}", line)
                todo += callees + ([b.strip(" %") for b in branches.group(1).split(",")] if branches else [])
    every = [(_opcode(line), line) for lines in comps.values() for line in lines]
    target = lambda line: line.split("custom_call_target=")[-1][:40]
    gemm = lambda op, line: op == "custom-call" and any(t in target(line) for t in GEMM_TARGETS)
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return {
        "launches": len(launched),
        "fusions": launched.count("fusion"),
        "custom_calls": launched.count("custom-call"),
        "copies": launched.count("copy"),
        "dots": sum(op == "dot" or gemm(op, line) for op, line in every),
        "while": sum(op == "while" for op, _ in every),
        "conditional": sum(op == "conditional" for op, _ in every),
        "instructions": len(every),
        "bytes": cost.get("bytes accessed"),
        "flops": cost.get("flops"),
    }


def compiled_update(num_seeds: int, precision: str):
    """One seed-vmapped ``paper`` SAC update (state donated), compiled for this backend from shapes only."""
    cfg = PRESETS["paper"].sac
    sac = SAC(cfg.__class__(**{**vars(cfg), "precision": precision}), 24, 6)
    keys = jax.eval_shape(lambda: jax.random.split(jax.random.PRNGKey(0), num_seeds))
    state = jax.eval_shape(jax.vmap(sac.init), keys)
    f32 = lambda *shape: jax.ShapeDtypeStruct((num_seeds, *shape), jnp.float32)
    n = cfg.batch_size
    batch = replay.Transition(obs=f32(n, 24), action=f32(n, 6), reward=f32(n), next_obs=f32(n, 24), discount=f32(n))
    update = jax.jit(jax.vmap(sac.update), donate_argnums=0)
    return update.lower(state, batch, keys).compile()


def _over_budget(args, started: float, what: str) -> bool:
    spent = time.perf_counter() - started
    if args.budget_s and spent > args.budget_s:
        print(f"skipped {what}: {spent:.0f} s spent of the {args.budget_s:.0f} s budget (--budget-s)", flush=True)
        return True
    return False


def update_rows(args):
    flops = update_flops(PRESETS["paper"].sac, 24, 6)
    started = time.perf_counter()
    for seeds, precision, unroll in itertools.product(args.seeds, args.precisions, args.unrolls):
        if _over_budget(args, started, f"update seeds {seeds} {precision} unroll {unroll}"):
            continue
        sec, counts = time_update(seeds, precision, args.repeats, unroll)
        tflops = seeds * flops / sec / 1e12
        ceiling = BF16_CEILING_TFLOPS.get(device_name())
        row = _row(
            what="update",
            algo="sac",
            preset="paper",
            seeds=seeds,
            precision=precision,
            unroll=unroll,
            num_envs=None,
            seed_env_steps_per_s=None,
            updates_per_s=seeds / sec,
            ms_per_update=sec * 1e3,
            update_tflops=tflops,
            fraction_of_bf16_ceiling=None if ceiling is None else tflops / ceiling,
            wall_s_500k=None,
            scan_launches=counts["launches"],
            scan_dots=counts["dots"],
        )
        print(
            f"update seeds {seeds:2d} {precision:7s} unroll {unroll:2d}: {sec * 1e3:7.3f} ms  {tflops:7.1f} TFLOP/s  "
            f"{counts['launches']} launches in the scan ({time.perf_counter() - started:.0f} s so far)",
            flush=True,
        )
        yield row


def hlo_rows(args):
    started = time.perf_counter()
    for seeds in args.seeds:
        for precision in args.precisions:
            if _over_budget(args, started, f"hlo seeds {seeds} {precision}"):
                continue
            counts = hlo_counts(compiled_update(seeds, precision))
            print(f"hlo seeds {seeds:2d} {precision:7s}: {json.dumps(counts)}", flush=True)
            yield _row(what="hlo", algo="sac", preset="paper", seeds=seeds, precision=precision, **counts)


def run_rows(args):
    for run_dir in args.run_dirs:
        cfg = json.loads((run_dir / "config.json").read_text())
        meta = json.loads((run_dir / "meta.json").read_text())
        records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
        steady = [r["env_steps_per_s"] for r in records[1:]] or [records[0]["env_steps_per_s"]]
        rate = statistics.median(steady)
        seeds = meta["seeds"]
        total = records[-1]["env_steps"]
        updates = max(1, round(cfg["sac"]["utd"] * cfg["env"]["num_envs"]))
        flops = update_flops(PRESETS["paper"].sac, 24, 6)
        yield {
            "device": meta["devices"][0],
            "date": meta["started"][:10],
            "jax": meta["jax"],
            "command": meta["command"],
            "what": "round",
            "task": cfg["env"]["task"],
            "algo": cfg["algo"],
            "preset": "paper",
            "seeds": seeds,
            "precision": cfg["sac"]["precision"],
            "num_envs": cfg["env"]["num_envs"],
            "utd": cfg["sac"]["utd"],
            "seed_env_steps_per_s": rate,
            "updates_per_s": rate * updates / cfg["env"]["num_envs"],
            "update_tflops": None,
            "rounds_tflops_incl_env": rate * updates / cfg["env"]["num_envs"] * flops / 1e12,
            "wall_s_500k": 500_000 * seeds / rate,
            "wall_s_measured": sum(r["seconds"] for r in records),
            "env_steps": total,
        }


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mode", choices=["update", "hlo", "runs"])
    p.add_argument("run_dirs", nargs="*", type=pathlib.Path)
    p.add_argument("--seeds", nargs="+", type=int, default=[5, 1, 10])
    p.add_argument("--precisions", nargs="+", default=["tf32", "bf16"])
    p.add_argument("--unrolls", nargs="+", type=int, default=[1], help="updates per iteration of the timed loop")
    p.add_argument("--repeats", type=int, default=5, help="timed calls of UPDATES_PER_CALL updates per row")
    p.add_argument("--budget-s", type=float, default=0.0, help="skip the rows left after this many seconds (0: none)")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    add_xla_flags_argument(p)
    return p


def main():
    args = parser().parse_args()
    use_xla_flags(args.xla_flags)
    rows = {"update": update_rows, "hlo": hlo_rows, "runs": run_rows}[args.mode]
    fields = (
        "device",
        "commit",
        "what",
        "algo",
        "task",
        "seeds",
        "precision",
        "num_envs",
        "utd",
        "unroll",
        "xla_flags",
    )
    merge_rows(args.out, rows(args), fields)


if __name__ == "__main__":
    main()
