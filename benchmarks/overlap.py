"""Can the physics and the SAC updates of a vector step run at the same time on one GPU?

Usage:
  python benchmarks/overlap.py [--task walker_walk] [--columns 5] [--num-envs 20] [--updates 10] [--steps 100]
      [--modes physics updates serial independent stream stream_updates] [--solver default] [--hidden 0]
      [--batch-size 0]
      [--out benchmarks/results/overlap.json] [--xla-flags=FLAGS]

A vector step of the trainer at B-Pref's protocol is one control step of every column's environments
(``--num-envs`` each: 10 training and 10 evaluation at the ``paper`` preset) and ``--updates`` SAC updates of
every column (the ``paper`` preset's sizes, bf16). The physics is latency-bound: its kernels leave most of the
GPU idle. This times ``--steps`` such vector steps in one ``lax.scan`` (uniformly random actions, one fixed
minibatch per column), per mode:

- ``physics``: the env steps alone; ``updates``: the updates alone;
- ``serial``: both, each column's minibatch reading the step's new observations, as in the trainer, whose updates
  sample a replay that already holds the step's transitions;
- ``independent``: both, the minibatch not reading them (a replay one vector step behind);
- ``stream``: ``independent`` with the env step annotated to run on a second GPU stream
  (:func:`rebel_jax.train.on_second_stream`);
- ``stream_updates``: ``independent`` with the updates on the second stream instead.

``--solver`` picks the physics solver (``default:unrolled`` has no data-dependent loop, whose predicate the host
reads back on every trip).

If XLA runs the two at once, ``independent`` or ``stream`` take less than ``physics + updates``, at best their
maximum. The stream annotation is for GPUs (the trainer applies it only there): on a 2-core CPU (JAX 0.10.2,
2026-11-28, ``--solver default:unrolled``, 1 column of 2 envs, 2 updates of a 16-wide SAC) ``stream`` took 6.7 s
per vector step against 2.9 ms for ``physics``. Rows merge into ``--out`` by device, commit, XLA flags and settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import pathlib

import jax
from sac_profile import random_minibatch
from timing import add_xla_flags_argument, median_seconds, merge_rows, provenance, use_xla_flags

from rebel_jax.agents.sac import SAC
from rebel_jax.config import PRESETS
from rebel_jax.envs import make_env
from rebel_jax.train import on_second_stream

MODES = ("physics", "updates", "serial", "independent", "stream", "stream_updates")
RESULTS = pathlib.Path(__file__).parent / "results" / "overlap.json"


def vector_steps(env, sac: SAC, mode: str, columns: int, num_envs: int, updates: int, steps: int):
    """(jitted ``(state, key) -> state`` doing ``steps`` vector steps in ``mode``, its first state)."""
    keys = jax.random.split(jax.random.PRNGKey(0), columns)
    env_state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(1), columns * num_envs))
    agent = jax.jit(jax.vmap(sac.init))(keys)
    batch = random_minibatch(sac, keys)
    physics = jax.vmap(env.step)

    def body(carry, key):
        env_state, agent = carry
        key_act, key_update = jax.random.split(key)
        if mode != "updates":
            action = jax.random.uniform(key_act, (columns * num_envs, env.action_size), minval=-1, maxval=1)
            env_state = (on_second_stream(physics) if mode == "stream" else physics)(env_state, action)
        if mode != "physics":
            minibatch = batch
            if mode == "serial":  # Row 0 of each column's minibatch: its first environment's new observation.
                new_obs = env_state.obs.reshape(columns, num_envs, -1)[:, 0]
                minibatch = batch.replace(obs=batch.obs.at[:, 0].set(new_obs))

            def update(agent, key):
                return jax.vmap(sac.update)(agent, minibatch, jax.random.split(key, columns))[0], None

            def all_updates(agent, key):
                return jax.lax.scan(update, agent, jax.random.split(key, updates))[0]

            agent = (on_second_stream(all_updates) if mode == "stream_updates" else all_updates)(agent, key_update)
        return (env_state, agent), None

    def run(state, key):
        return jax.lax.scan(body, state, jax.random.split(key, steps))[0]

    return jax.jit(run), (env_state, agent)


def measure(args):
    """Yields one result row per mode."""
    base = PRESETS["paper"].sac
    cfg = dataclasses.replace(
        base, precision="bf16", hidden=args.hidden or base.hidden, batch_size=args.batch_size or base.batch_size
    )
    env = make_env(args.task, args.solver)
    sac = SAC(cfg, env.observation_size, env.action_size)
    for mode in args.modes:
        run, state = vector_steps(env, sac, mode, args.columns, args.num_envs, args.updates, args.steps)
        seconds = median_seconds(run, state, args.steps, args.repeats)
        print(f"{mode:12s} {seconds * 1e3:8.2f} ms per vector step", flush=True)
        yield {
            **provenance(),
            "task": args.task,
            "solver": args.solver,
            "columns": args.columns,
            "num_envs": args.num_envs,
            "updates": args.updates,
            "hidden": cfg.hidden,
            "batch_size": cfg.batch_size,
            "mode": mode,
            "ms_per_vector_step": seconds * 1e3,
        }


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--task", default="walker_walk")
    p.add_argument("--solver", default="default", help="the physics solver (rebel_jax.envs.SOLVERS, or ...:unrolled)")
    p.add_argument("--columns", type=int, default=5, help="seeds in one vmapped program")
    p.add_argument("--num-envs", type=int, default=20, help="environments per column (training and evaluation)")
    p.add_argument("--updates", type=int, default=10, help="SAC updates per vector step (utd x training envs)")
    p.add_argument("--steps", type=int, default=100, help="vector steps per timed call")
    p.add_argument("--repeats", type=int, default=5, help="timed calls")
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    p.add_argument("--hidden", type=int, default=0, help="SAC hidden width (0: the paper preset's)")
    p.add_argument("--batch-size", type=int, default=0, help="SAC minibatch (0: the paper preset's)")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    add_xla_flags_argument(p)
    return p


def main():
    args = parser().parse_args()
    for name in ("columns", "num_envs", "updates", "steps", "repeats"):
        if getattr(args, name) < 1:
            raise SystemExit(f"error: --{name.replace('_', '-')} must be >= 1; got {getattr(args, name)}")
    use_xla_flags(args.xla_flags)
    fields = (
        "device",
        "commit",
        "xla_flags",
        "task",
        "solver",
        "columns",
        "num_envs",
        "updates",
        "hidden",
        "batch_size",
        "mode",
    )
    merge_rows(args.out, measure(args), fields)


if __name__ == "__main__":
    main()
