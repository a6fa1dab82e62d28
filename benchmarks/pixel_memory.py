"""What the pixel programs need on a device, measured without running them: the bytes of the trainer's
state (``jax.eval_shape`` of the seed-vmapped ``init``, nothing allocated) and XLA's ``memory_analysis()``
and ``cost_analysis()`` of the programs lowered and compiled for this CPU with abstract inputs.

Configurations (5 seeds, 84x84, the real episode lengths), each the CLI's flags (:data:`CONFIGS`):
DrQ-v2 on walker/cheetah (SURF's DrQ-v2 settings) and pixel PEBBLE/SURF/REBEL (walker 200 labels, cheetah
1000), all with a replay of 100k transitions per seed (``pixel_feedback.DEFAULT_CAPACITY``; the preference runs'
label store keeps copies of its segments, so nothing needs the whole run; ``--flags="--buffer-capacity
500000"`` measures the whole-run replay the preference runs kept before).

Programs (each jitted and vmapped over the seeds, as ``train.compiled``):

- ``round``: ``Trainer.round`` (donated state): the program the CLI runs. Its ``temp`` bytes are the
  device's working memory beside the state; this is the row that says whether a run fits.
- ``update``: one DrQ-v2 update (sample from the replay, augment, critic + encoder, actor, target).
- ``env_step``: one vector step without updates (act, ``env.step`` of training and evaluation envs, replay write).
- ``session``: one feedback session (select, teach, reward training, relabel the whole replay, critic reset).

XLA's ``cost_analysis()`` counts a loop body once, not times its trip count (checked: a ``lax.scan`` of 10
matmuls reports the flops of one), so per-round costs are composed here from the pieces:
``updates_per_round x update + vector_steps_per_round x env_step`` (+ a session); the physics' solver loops
and the session's reward-training epochs are counted once, so those figures are lower bounds.

    XLA_FLAGS=--xla_cpu_enable_concurrency_optimized_scheduler=false PYTHONPATH=src \\
        python benchmarks/pixel_memory.py --configs drqv2_walker pebble_walker --programs state update round
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import platform
import time

import jax
import jax.numpy as jnp

from rebel_jax.run.cli import parse
from rebel_jax.train import Trainer

GIB = 2**30
GPU_BYTES = 78 * GIB
"""What an H100 gives a process (about 78 GiB of its 80 GB)."""

# SURF's pixel protocol is the presets surf_pixels_walker / surf_pixels_cheetah (rebel_jax.config._surf_pixels);
# the DrQ-v2 runs take 10 envs and rounds of 10,000 agent steps instead of its 4 envs and 1,000.
# REBEL at the lambda the rule of RESULTS.md chose on state walker_walk (0.001), carried over unchanged.
_ALGO = {
    "drqv2": ["--algo", "drqv2", "--num-envs", "10", "--steps-per-round", "10000"],
    "pebble": ["--algo", "pebble"],
    "surf": ["--algo", "surf"],
    "rebel": ["--algo", "rebel", "--rebel.lam", "0.001"],
}
CONFIGS: dict[str, list[str]] = {
    f"{algo}_{task}": ["--preset", f"surf_pixels_{task}", *flags]
    for algo, flags in _ALGO.items()
    for task in ("walker", "cheetah")
}
"""The CLI flags of each configuration (``python -m rebel_jax.train --seeds 5 FLAGS``)."""

PROGRAMS = ("state", "update", "env_step", "session", "round")


def nbytes(tree) -> int:
    """Bytes of every array (or ShapeDtypeStruct) leaf of ``tree``."""
    return sum(x.size * jnp.dtype(x.dtype).itemsize for x in jax.tree.leaves(tree))


def abstract_state(trainer: Trainer, seeds: int):
    """The seed-vmapped state's shapes (nothing allocated) and the abstract keys."""
    keys = jax.ShapeDtypeStruct((seeds, 2), jnp.uint32)
    return jax.eval_shape(jax.vmap(trainer.init), keys), keys


def state_row(trainer: Trainer, seeds: int) -> dict:
    """Bytes of the state per seed, split by part, and for ``seeds`` seeds."""
    state, _ = abstract_state(trainer, seeds)
    parts = {
        "replay": state.buffer,
        "agent": state.agent,  # encoder, actor, critic, target critic and their Adam states
        "reward": state.reward,  # pixel ensemble, its Adam state, the label store (and SURF's pool)
        "env": state.env,
        "other": (state.episodes, state.key, state.eval_policy, state.teacher, state.lam, state.eval_trajectory),
    }
    per_seed = {f"{k}_bytes_per_seed": nbytes(v) // seeds for k, v in parts.items()}
    total = nbytes(state)
    return {**per_seed, "state_bytes_per_seed": total // seeds, "state_bytes": total, "state_gib": total / GIB}


def _programs(trainer: Trainer):
    """``name -> (function of (state, extra), extra's abstract value)``, each vmapped over the seeds."""
    step = jnp.int32(trainer.cfg.train.seed_steps)

    def update(ts):
        return trainer._updates(ts, ts.buffer, ts.key, step // trainer.num_train)

    def env_step(ts):
        key_act, _ = jax.random.split(ts.key)
        t = step // trainer.num_train
        action = trainer._act(ts, t, key_act)
        nxt = jax.vmap(trainer.env.step)(ts.env, action)
        return trainer._record(ts, nxt, action, t)

    def session(ts):
        return trainer.feedback_session(ts, jnp.bool_(True), jnp.int32(0), step)

    out = {"update": update, "env_step": env_step}
    if trainer.preference:
        out["session"] = session
    return out


def _analysis(compiled) -> dict:
    mem = compiled.memory_analysis()
    cost = compiled.cost_analysis() or {}
    if isinstance(cost, list):  # older JAX: one dict per computation
        cost = cost[0] if cost else {}
    return {
        "argument_bytes": int(mem.argument_size_in_bytes),
        "output_bytes": int(mem.output_size_in_bytes),
        "alias_bytes": int(mem.alias_size_in_bytes),
        "temp_bytes": int(mem.temp_size_in_bytes),
        "temp_gib": mem.temp_size_in_bytes / GIB,
        "flops": float(cost.get("flops", float("nan"))),
        "bytes_accessed": float(cost.get("bytes accessed", float("nan"))),
    }


def compile_row(trainer: Trainer, seeds: int, program: str) -> dict:
    """Lowers and compiles ``program`` for this backend with abstract inputs; its memory and cost analyses."""
    state, _ = abstract_state(trainer, seeds)
    start = time.time()
    if program == "round":
        fn = jax.jit(jax.vmap(trainer.round, in_axes=(0, None)), donate_argnums=0)
        lowered = fn.lower(state, jax.ShapeDtypeStruct((), jnp.int32))
    else:
        lowered = jax.jit(jax.vmap(_programs(trainer)[program])).lower(state)
    lowered_s = time.time() - start
    compiled = lowered.compile()
    compile_s = time.time() - start - lowered_s
    return {**_analysis(compiled), "lower_s": round(lowered_s, 1), "compile_s": round(compile_s, 1)}


def schedule(trainer: Trainer) -> dict:
    """Per-round counts the per-round figures are composed from."""
    cfg = trainer.cfg
    vector_steps = trainer.steps_per_round
    updates = vector_steps // trainer.update_period * trainer.updates_per_step
    out = {
        "num_envs": trainer.num_train,
        "eval_envs": cfg.train.eval_episodes,
        "capacity_per_seed": trainer.capacity,
        "total_steps": cfg.train.total_steps,
        "steps_per_round": cfg.train.steps_per_round,
        "rounds": cfg.train.num_rounds,
        "vector_steps_per_round": vector_steps,
        "updates_per_round": updates,
        "batch_size": cfg.drqv2.batch_size,
    }
    if trainer.preference:
        sessions = -(-cfg.feedback.labels // cfg.feedback.queries)
        out.update(labels=cfg.feedback.labels, per_session=cfg.feedback.queries, sessions=sessions)
    return out


def with_total_steps(flags: list[str], total_steps: int) -> list[str]:
    """``flags`` with ``--total-steps`` (0: the preset's)."""
    return [*flags, "--total-steps", str(total_steps)] if total_steps else list(flags)


def of_variant(rows: list[dict], variant: str = "") -> list[dict]:
    """The rows of ``variant`` (``--flags``), and the default's rows of the programs it has none of
    (e.g. ``state``, which no reward setting changes)."""
    mine = [r for r in rows if r.get("variant", "") == variant]
    have = {(r["config"], r["program"], r["seeds"], r["total_steps"]) for r in mine}
    default = [r for r in rows if not r.get("variant")]
    return mine + [r for r in default if (r["config"], r["program"], r["seeds"], r["total_steps"]) not in have]


def fit(rows: list[dict], name: str, seeds: int, budget: int = GPU_BYTES, variant: str = "") -> dict:
    """What fits in ``budget`` bytes for configuration ``name``, from its ``state`` and ``round`` rows at
    ``seeds`` seeds and the longest ``total_steps`` measured: the round's peak (arguments + temp; the
    state is donated, so the output aliases it), the most seeds at that length (the state and the temp
    scale with the seeds), and the longest run at ``seeds`` seeds (the replay grows with the run's length
    at a preference run's bytes per agent step; the temp does not: checked by compiling a shorter run).
    ``variant``: the rows of those ``--flags`` (:func:`of_variant`).
    """
    mine = [r for r in of_variant(rows, variant) if r["config"] == name and r["seeds"] == seeds]
    mine = [r for r in mine if "error" not in r]
    longest = max(r["total_steps"] for r in mine)
    by = {r["program"]: r for r in mine if r["total_steps"] == longest}
    state, temp = by["state"]["state_bytes"], by.get("round", {}).get("temp_bytes")
    out = {"config": name, "state_gib": state / GIB, "replay_gib_per_seed": by["state"]["replay_bytes_per_seed"] / GIB}
    if temp is None:
        return out
    peak = state + temp
    per_seed = peak / seeds
    out.update(round_temp_gib=temp / GIB, peak_gib=peak / GIB, fits=peak <= budget, max_seeds=int(budget // per_seed))
    replay = by["state"]["replay_bytes_per_seed"]
    if by["state"].get("capacity_per_seed") == longest:  # the replay holds the run: it grows with it
        per_step = replay / longest
        spare = budget - (peak - seeds * replay)
        steps = int(spare // (seeds * per_step)) // 10_000 * 10_000
        out["max_total_steps"] = steps
    return out


def table(rows: list[dict], seeds: int = 5, variant: str = "") -> str:
    """Markdown rows: the state, the round's temp and peak at ``seeds`` seeds, and what fits in 78 GiB
    (``variant``: the rows of those ``--flags``, :func:`of_variant`)."""
    lines = [
        "| config | replay / seed (GiB) | state, 5 seeds (GiB) | round temp (GiB) | round peak (GiB) | fits 78 GiB "
        "| most seeds | longest run at 5 seeds | update GFLOP | env step GFLOP | session GFLOP |",
        "|---|---:|---:|---:|---:|---|---:|---:|---:|---:|---:|",
    ]
    for name in CONFIGS:
        if not any(r["config"] == name and r["seeds"] == seeds for r in rows):
            continue
        f = fit(rows, name, seeds, variant=variant)
        flops = {
            r["program"]: r["flops"] / 1e9
            for r in of_variant(rows, variant)
            if r["config"] == name and r["seeds"] == seeds and "flops" in r and r["total_steps"] == 500_000
        }

        def cell(key, fmt="{:.1f}", f=f):
            return fmt.format(f[key]) if key in f else "not compiled"

        def gflop(program, flops=flops):
            return f"{flops[program]:,.0f}" if program in flops else "-"

        longest = f"{f['max_total_steps']:,}" if "max_total_steps" in f else "not compiled"
        if "max_total_steps" not in f and "peak_gib" in f:  # a ring: the replay does not grow with the run
            longest = "any (replay 100k)"
        fits = ("yes" if f["fits"] else "**no**") if "fits" in f else "?"
        lines.append(
            f"| {name} | {f['replay_gib_per_seed']:.2f} | {f['state_gib']:.1f} | {cell('round_temp_gib')} | "
            f"{cell('peak_gib')} | {fits} | {cell('max_seeds', '{}')} | {longest} | {gflop('update')} | "
            f"{gflop('env_step')} | {gflop('session')} |"
        )
    return "\n".join(lines)


def save(path: pathlib.Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(rows, indent=1) + "\n")
    tmp.replace(path)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    p.add_argument("--programs", nargs="+", default=list(PROGRAMS), choices=PROGRAMS)
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--total-steps", type=int, default=0, help="agent steps per seed instead of 500k (sizes the replay)")
    p.add_argument("--flags", default="", help='more CLI flags for every configuration: --flags="--a 1 --b 2"')
    p.add_argument("--out", default="benchmarks/results/pixel_memory.json")
    p.add_argument("--table", action="store_true", help="print the Markdown table of --out's rows and exit")
    p.add_argument("--variant", default="", help="with --table: the rows measured with these --flags")
    args = p.parse_args()
    if args.table:
        print(table(json.loads(pathlib.Path(args.out).read_text()), variant=args.variant))
        return
    out = pathlib.Path(args.out)
    rows = json.loads(out.read_text()) if out.exists() else []
    meta = {
        "device": f"CPU ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)",
        "jax": jax.__version__,
        "date": datetime.date.today().isoformat(),
        "seeds": args.seeds,
    }
    for name in args.configs:
        flags = with_total_steps(CONFIGS[name], args.total_steps) + args.flags.split()
        trainer = Trainer(parse(flags).config)
        command = f"python -m rebel_jax.train --seeds {args.seeds} " + " ".join(flags)
        base = {"config": name, "variant": args.flags, "command": command, **meta}
        base.update(schedule(trainer))
        if trainer.preference:
            base["member_loop"] = trainer.cfg.pixel_reward.member_loop
        for program in args.programs:
            if program == "session" and not trainer.preference:
                continue
            start = time.time()
            try:
                if program == "state":
                    row = state_row(trainer, args.seeds)
                else:
                    row = compile_row(trainer, args.seeds, program)
            except Exception as error:  # noqa: BLE001 - a failed program is a result too
                row = {"error": f"{type(error).__name__}: {str(error)[:300]}"}
            row = {**base, "program": program, **row, "seconds": round(time.time() - start, 1)}
            fields = ("config", "variant", "program", "seeds", "total_steps")
            rows = [r for r in rows if tuple(r.get(k, "") for k in fields) != tuple(row[k] for k in fields)]
            rows.append(row)
            save(out, rows)
            shown = {k: row[k] for k in ("state_gib", "temp_gib", "flops", "error", "seconds") if k in row}
            print(json.dumps({"config": name, "program": program, **shown}), flush=True)


if __name__ == "__main__":
    main()
