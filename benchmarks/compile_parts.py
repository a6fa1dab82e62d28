"""Where a cold first round's compile goes: the whole round against its largest parts, each compiled alone.

Usage:
  python benchmarks/compile_parts.py [TRAIN FLAGS ...] [--out benchmarks/results/compile_parts.json]

The training flags (default: ``pebble --preset paper --task walker_walk --feedback.labels 100 --seeds 5``) pick the
run. Timed, each in this process with JAX's persistent compilation cache off, from the program's shapes: lowering
and compiling the round (``train.compiled``'s), and compiling alone the seed-vmapped env step and env reset of
every column's environments (training and evaluation) and one seed-vmapped SAC update. The parts overlap the
round's compile, not add up to it; a part much smaller than the round says the time is elsewhere.
"""

from __future__ import annotations

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
from timing import add_xla_flags_argument, merge_rows, provenance, use_xla_flags

from rebel_jax.run.cli import parse
from rebel_jax.train import Trainer, compiled, seed_keys

DEFAULT = ["pebble", "--preset", "paper", "--task", "walker_walk", "--feedback.labels", "100", "--seeds", "5"]
RESULTS = pathlib.Path(__file__).parent / "results" / "compile_parts.json"


def seconds(fn) -> float:
    """Wall seconds of ``fn()``."""
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def measure(flags: list[str]) -> dict:
    """Compile seconds of the round and of its parts for the run ``flags`` describes."""
    args = parse([*flags, "--run-dir", "unused"])
    trainer = Trainer(args.config, columns=args.seeds)
    init, round_fn, _ = compiled(trainer)
    keys = seed_keys(args.config.train.seed, args.seeds)
    state = jax.eval_shape(init, keys)
    lowered = []
    out = {"lower_round_s": seconds(lambda: lowered.append(round_fn.lower(state, jnp.int32(1))))}
    out["compile_round_s"] = seconds(lambda: lowered[0].compile())
    env_state, agent_state = state.env, state.agent
    actions = jax.ShapeDtypeStruct((args.seeds, trainer.num_all, trainer.env.action_size), jnp.float32)
    step = jax.jit(jax.vmap(trainer.envs.step))
    out["compile_env_step_s"] = seconds(lambda: step.lower(env_state, actions).compile())
    reset = jax.jit(jax.vmap(trainer.envs.reset))
    out["compile_env_reset_s"] = seconds(lambda: reset.lower(keys).compile())
    batch = jax.eval_shape(lambda b, k: jax.vmap(trainer.sample, (0, 0, None))(b, k, False), state.buffer, keys)
    update = jax.jit(jax.vmap(trainer.agent.update))
    out["compile_agent_update_s"] = seconds(lambda: update.lower(agent_state, batch, keys).compile())
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    add_xla_flags_argument(p)
    args, flags = p.parse_known_args()
    use_xla_flags(args.xla_flags)
    jax.config.update("jax_enable_compilation_cache", False)
    flags = flags or DEFAULT
    row = {**provenance(), "flags": " ".join(flags), **measure(flags)}
    print("  ".join(f"{k} {v:.1f}" for k, v in row.items() if k.endswith("_s")), flush=True)
    merge_rows(args.out, [row], ("device", "commit", "xla_flags", "flags"))


if __name__ == "__main__":
    main()
