"""Which part of a run's program compiles when sharded over every visible device, and how long it takes.

Usage:
  python benchmarks/sharded_compile.py [--preset tiny] [--algo pebble] [--task walker_walk]
      [--parts init round vector_step session evaluate] [--modes shard_map partitioner] [--seeds-per-device 2]

Each (part, mode) is compiled (``lower(...).compile()``, nothing runs) in a process of its own, so a compiler
crash (a segmentation fault) is reported as one row instead of ending the check. Parts are the seed-vmapped
``init``, ``round``, one ``vector_step`` (the round's scan body), one feedback ``session`` (state tasks) and
``evaluate`` of the run's trainer. Modes: ``shard_map``, each device compiling its block of
seeds (what ``train.compiled`` does, :func:`rebel_jax.sweep.per_device`), and ``partitioner``, one program
``jax.jit`` with the seed sharding on its inputs and outputs, split by XLA's SPMD partitioner.
Prints one JSON line per row: part, mode, devices, status (``ok``, ``error: ...`` or ``signal N``), seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time

PARTS = ("init", "round", "vector_step", "session", "evaluate")
MODES = ("shard_map", "partitioner")


def _functions(trainer):
    """part -> (seed-vmapped function, which positional arguments carry the seed axis)."""
    import jax

    return {
        "init": (jax.vmap(trainer.init), (True,)),
        "round": (jax.vmap(trainer.round, in_axes=(0, None)), (True, False)),
        "vector_step": (jax.vmap(trainer.vector_step, in_axes=(0, None)), (True, False)),
        "session": (jax.vmap(trainer.feedback_session, in_axes=(0, None, None)), (True, False, False)),
        "evaluate": (jax.vmap(trainer.evaluate, in_axes=(0, 0, None)), (True, True, False)),
    }


def compile_part(preset: str, algo: str, task: str, part: str, mode: str, per_device: int) -> float:
    """Compiles one part in one mode; returns the seconds ``compile`` took."""
    import jax
    import jax.numpy as jnp

    from rebel_jax import api, config, sweep, train

    base = config.PRESETS[preset]
    cfg = dataclasses.replace(base, algo=algo, env=dataclasses.replace(base.env, task=task))
    trainer = api.make_trainer(cfg)
    seeds = per_device * jax.device_count()
    sharding = sweep.seed_sharding(seeds)
    keys = train.seed_keys(0, seeds)
    state = jax.eval_shape(jax.vmap(trainer.init), keys)
    fn, batched = _functions(trainer)[part]
    args = {
        "init": (keys,),
        "round": (state, jnp.int32(1)),
        "vector_step": (state, jnp.int32(1)),
        "session": (state, jnp.asarray(True), jnp.int32(0)),  # the first feedback session (state tasks)
        "evaluate": (jax.eval_shape(lambda s: trainer.policy_params(s), state), keys, jnp.asarray(False)),
    }[part]

    def placed(x, seeded):
        if sharding is None or not hasattr(x, "shape"):
            return x
        return jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=sharding if seeded else None)

    args = tuple(jax.tree.map(lambda x, s=s: placed(x, s), a) for a, s in zip(args, batched, strict=True))
    if sharding is None or mode == "partitioner":
        program = jax.jit(fn, out_shardings=sharding)
    else:
        program = jax.jit(sweep.per_device(fn, sharding, batched))
    lowered = program.lower(*args)
    start = time.perf_counter()
    lowered.compile()
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--algo", default="pebble")
    parser.add_argument("--task", default="walker_walk")
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--seeds-per-device", type=int, default=2)
    parser.add_argument("--one", nargs=2, metavar=("PART", "MODE"), help=argparse.SUPPRESS)  # the child process
    args = parser.parse_args(argv)
    if args.one:
        seconds = compile_part(args.preset, args.algo, args.task, *args.one, args.seeds_per_device)
        print(json.dumps({"seconds": round(seconds, 2)}))
        return
    import jax

    devices = [str(d) for d in jax.devices()]
    for part in args.parts:
        for mode in args.modes:
            common = ["--preset", args.preset, "--algo", args.algo, "--task", args.task]
            command = [sys.executable, __file__, *common, "--seeds-per-device", str(args.seeds_per_device)]
            done = subprocess.run([*command, "--one", part, mode], capture_output=True, text=True)
            if done.returncode < 0:
                status, seconds = f"signal {-done.returncode}", None
            elif done.returncode:
                status, seconds = "error: " + (done.stderr.strip().splitlines() or ["?"])[-1][:300], None
            else:
                status, seconds = "ok", json.loads(done.stdout.strip().splitlines()[-1])["seconds"]
            row = {"part": part, "mode": mode, "devices": devices, "task": args.task, "algo": args.algo}
            print(json.dumps({**row, "status": status, "compile_seconds": seconds}), flush=True)


if __name__ == "__main__":
    main()
