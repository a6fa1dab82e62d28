"""Which part of a run's program compiles when sharded over every visible device, and how long it takes.

Usage:
  python benchmarks/sharded_compile.py [--preset tiny] [--algo pebble] [--task walker_walk]
      [--parts init round vector_step session evaluate] [--modes per_device shard_map partitioner]
      [--seeds-per-device 2] [--jobs 1] [--log-passes]

Each (part, mode) is compiled (``lower(...).compile()``, nothing runs) in a process of its own, so a compiler
crash (a segmentation fault) is reported as one row instead of ending the check; ``--jobs`` runs that many
at once. Parts are the seed-vmapped ``init``, ``round``, one ``vector_step`` (the round's scan body), one
feedback ``session`` (state tasks) and ``evaluate`` of the run's trainer. Modes:

- ``per_device``: what ``train.compiled`` does (:func:`rebel_jax.train.placement.per_device`): the one-device program
  of a block of seeds, compiled for each device;
- ``shard_map``: one SPMD program in which each device runs its block of seeds (``jax.shard_map``, with
  zero-size arrays kept outside it);
- ``partitioner``: one program ``jax.jit`` with the seed sharding on its inputs and outputs, split by XLA's
  SPMD partitioner.

Prints one JSON line per row: part, mode, devices, status (``ok``, ``error: ...`` or ``signal N``), seconds;
after a crash, ``last_lines`` holds the child's last lines of output (with ``--log-passes``, XLA logs each
HLO pass it runs, so they name the pass that crashed).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import dataclasses
import json
import os
import subprocess
import sys
import time

PARTS = ("init", "round", "vector_step", "session", "evaluate")
MODES = ("per_device", "shard_map", "partitioner")


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

    from rebel_jax import api, config
    from rebel_jax.train import placement
    from rebel_jax.train import trainer as train

    base = config.PRESETS[preset]
    cfg = dataclasses.replace(base, algo=algo, env=dataclasses.replace(base.env, task=task))
    trainer = api.make_trainer(cfg)
    seeds = per_device * jax.device_count()
    sharding = placement.seed_sharding(seeds)
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
        lowered = [jax.jit(fn, out_shardings=sharding).lower(*args)]
    elif mode == "shard_map":
        lowered = [jax.jit(shard_map_blocks(fn, sharding, batched)).lower(*args)]
    else:  # per_device: each device's block, placed on that device
        lowered = [jax.jit(fn).lower(*_block_on(args, batched, d, jax.device_count())) for d in jax.devices()]
    start = time.perf_counter()
    for program in lowered:
        program.compile()
    return time.perf_counter() - start


def _block_on(args, batched, device, blocks: int):
    """Shapes of one device's block of ``args`` (the seeded leaves' first axis divided by ``blocks``), on ``device``."""
    import jax

    one = jax.sharding.SingleDeviceSharding(device)

    def block(x, seeded):
        if not hasattr(x, "shape"):
            return x
        shape = (x.shape[0] // blocks, *x.shape[1:]) if seeded else x.shape
        return jax.ShapeDtypeStruct(shape, x.dtype, sharding=one)

    return tuple(jax.tree.map(lambda x, s=s: block(x, s), a) for a, s in zip(args, batched, strict=True))


def shard_map_blocks(fn, sharding, batched):
    """``fn`` under ``jax.shard_map``, each device running its block of seeds; zero-size arrays stay outside.

    XLA's GPU compiler (JAX 0.11.2) crashed on a ``shard_map`` whose outputs mix zero-size and other
    arrays, so those are passed around it and returned as new empty arrays.
    """
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax.sharding import PartitionSpec

    mesh, seeds, same, blocks = sharding.mesh, sharding.spec, PartitionSpec(), sharding.mesh.size

    def run(*args):
        leaves, treedef = jax.tree.flatten(args)
        split = np.repeat(np.asarray(batched, bool), [len(jax.tree.leaves(a)) for a in args])
        kept = [i for i, x in enumerate(leaves) if x.size]
        outputs, out_treedef = jax.tree.flatten(jax.eval_shape(fn, *args))
        kept_out = [i for i, x in enumerate(outputs) if x.size]

        def block(*kept_leaves):
            full = [
                jnp.zeros((x.shape[0] // blocks, *x.shape[1:]) if split[i] else x.shape, x.dtype)
                for i, x in enumerate(leaves)
            ]
            for i, x in zip(kept, kept_leaves, strict=True):
                full[i] = x
            out = jax.tree.leaves(fn(*jax.tree.unflatten(treedef, full)))
            return [out[i] for i in kept_out]

        in_specs = tuple(seeds if split[i] else same for i in kept)
        mapped = jax.shard_map(block, mesh=mesh, in_specs=in_specs, out_specs=[seeds] * len(kept_out), check_vma=False)
        result = [jnp.zeros(x.shape, x.dtype) for x in outputs]
        for i, x in zip(kept_out, mapped(*[leaves[i] for i in kept]), strict=True):
            result[i] = x
        return jax.tree.unflatten(out_treedef, result)

    return run


def _row(done: subprocess.CompletedProcess) -> dict:
    """status, compile_seconds (and last_lines after a failure) of one child process."""
    if done.returncode == 0:
        return {"status": "ok", "compile_seconds": json.loads(done.stdout.strip().splitlines()[-1])["seconds"]}
    lines = (done.stdout + done.stderr).strip().splitlines()
    if done.returncode < 0:
        status = f"signal {-done.returncode}"
    else:
        status = "error: " + (done.stderr.strip().splitlines() or ["?"])[-1][:300]
    return {"status": status, "compile_seconds": None, "last_lines": [line[:300] for line in lines[-6:]]}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--algo", default="pebble")
    parser.add_argument("--task", default="walker_walk")
    parser.add_argument("--parts", nargs="+", choices=PARTS, default=list(PARTS))
    parser.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    parser.add_argument("--seeds-per-device", type=int, default=2)
    parser.add_argument("--jobs", type=int, default=1, help="child processes at once")
    parser.add_argument("--log-passes", action="store_true", help="XLA logs each HLO pass (names a crashing one)")
    parser.add_argument("--one", nargs=2, metavar=("PART", "MODE"), help=argparse.SUPPRESS)  # the child process
    args = parser.parse_args(argv)
    if args.one:
        seconds = compile_part(args.preset, args.algo, args.task, *args.one, args.seeds_per_device)
        print(json.dumps({"seconds": round(seconds, 2)}))
        return
    import jax

    devices = [str(d) for d in jax.devices()]
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false")  # several children share the devices
    if args.log_passes:
        env.update(TF_CPP_MIN_LOG_LEVEL="0", TF_CPP_VMODULE="hlo_pass_pipeline=1")
    common = ["--preset", args.preset, "--algo", args.algo, "--task", args.task]
    command = [sys.executable, __file__, *common, "--seeds-per-device", str(args.seeds_per_device)]
    rows = [(part, mode) for part in args.parts for mode in args.modes]

    def one(row):
        return subprocess.run([*command, "--one", *row], capture_output=True, text=True, env=env)

    with concurrent.futures.ThreadPoolExecutor(args.jobs) as pool:
        for (part, mode), done in zip(rows, pool.map(one, rows), strict=True):
            row = {"part": part, "mode": mode, "devices": devices, "task": args.task, "algo": args.algo}
            print(json.dumps({**row, **_row(done)}), flush=True)


if __name__ == "__main__":
    main()
