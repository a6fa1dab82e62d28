"""Env throughput (steps/s, ms per step) and solver fidelity against dm_control.

Usage:
  python benchmarks/env_throughput.py throughput [--batches 1 16 256 1024 4096] [--impl warp] [--out FILE]
  python benchmarks/env_throughput.py fidelity [--out FILE]   # needs dm_control (CPU is fine)

``throughput`` times one jitted vmapped control step per task, batch size and solver
preset (``default`` and ``dm_control``), with MJX's JAX or Warp step (``--impl``), after a
warm-up, as the median of repeated scans of 20 steps. ``fidelity`` compares MJX under several solver settings with
dm_control on (a) one control step from the same 200 states along a random-action
trajectory and (b) 1000-step open-loop rollouts of the same action sequence from the
same initial state. Results are merged into ``benchmarks/results/env_throughput.json``.
"""

from __future__ import annotations

import argparse
import functools
import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from timing import add_xla_flags_argument, provenance, random_steps_seconds, use_xla_flags

from rebel_jax.envs import IMPLS, SOLVERS, TASKS, Solver, make_env
from rebel_jax.run.logging import write_json

RESULTS = pathlib.Path(__file__).parent / "results" / "env_throughput.json"
STEPS_PER_CALL = 20


def _load(path: pathlib.Path) -> dict:
    return json.loads(path.read_text()) if path.exists() else {"rows": [], "fidelity": {}}


def time_rollout(env, batch: int, repeats: int = 5) -> tuple[float, float]:
    """Seconds to compile and run a first control step of ``batch`` environments (with ``--impl warp``, Warp also
    builds its kernels then, where its kernel cache lacks them), and the median seconds per control step after."""
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), batch))
    start = time.perf_counter()
    jax.block_until_ready(jax.jit(jax.vmap(env.step))(state, jnp.zeros((batch, env.action_size))))
    first = time.perf_counter() - start
    return first, random_steps_seconds(env, state, STEPS_PER_CALL, repeats)


def throughput(args):
    """Yields one result row per (task, solver, batch)."""
    for task in args.tasks:
        for solver in args.solvers:
            for batch in args.batches:
                if solver == "dm_control" and batch > args.max_dm_batch:
                    continue
                flags = {"unroll_substeps": args.unroll, "all_contacts": args.all_contacts, "impl": args.impl}
                env = make_env(task, solver=solver, worlds=batch, **flags)  # Warp's contact buffer: batch worlds
                first, sec = time_rollout(env, batch)
                row = {
                    **provenance(),
                    "task": task,
                    "solver": solver,
                    "unroll_substeps": args.unroll,
                    "all_contacts": args.all_contacts,
                    "impl": args.impl,
                    "batch": batch,
                    "env_steps_per_s": batch / sec,
                    "ms_per_step": sec * 1e3,
                    "first_step_s": first,
                }
                yield row
                print(
                    f"{task:13s} {solver:10s} {args.impl:4s} batch {batch:5d}: {sec * 1e3:8.2f} ms/step "
                    f"{batch / sec:12,.0f} steps/s (first step {first:.1f} s)"
                )
                sys.stdout.flush()


def _open_loop(env, state, actions):
    """Observations and rewards of ``env`` under a fixed action sequence."""

    def body(s, a):
        s = env.step(s, a)
        return s, (s.obs, s.reward)

    return jax.lax.scan(body, state, actions)[1]


def _dm_obs(ts) -> np.ndarray:
    return np.concatenate([np.atleast_1d(v) for v in ts.observation.values()])


def _controls(control, action: np.ndarray) -> np.ndarray:
    """dm_control's controls (float64) of ``action`` in [-1, 1], by the env's ``control``."""
    return np.asarray(control(jnp.asarray(action, jnp.float32)), np.float64)


def fidelity(args) -> dict:
    """Errors of MJX (several solver settings) against dm_control (float64, its own solver)."""
    from dm_control import suite  # test-only dependency

    candidates = {
        "dm_control": SOLVERS["dm_control"],
        "4/8": Solver(4, 8),
        "2/5": Solver(2, 5),
        "1/4": Solver(1, 4),
        "1/4 no eulerdamp": Solver(1, 4, eulerdamp=False),
    }
    candidates = {label: candidates[label] for label in args.candidates}
    out = {}
    for task in args.tasks:
        domain, name = task.split("_")
        ref = suite.load(domain, name, task_kwargs={"random": 0})
        rng = np.random.default_rng(0)
        plain = make_env(task)
        # dm_control's controls of actions in [-1, 1] (the quadruped maps them onto its control ranges).
        ctrl = functools.partial(_controls, jax.jit(plain.control))
        # Reference trajectory of random actions: states, actions, next obs, rewards.
        ref.reset()
        states, actions, next_obs, rewards = [], [], [], []
        for _ in range(args.fidelity_states):
            phys = ref.physics
            data = phys.data
            states.append((data.qpos.copy(), data.qvel.copy(), data.qacc_warmstart.copy(), data.act.copy()))
            a = rng.uniform(-1, 1, plain.action_size)
            ts = ref.step(ctrl(a))
            actions.append(a)
            next_obs.append(_dm_obs(ts))
            rewards.append(ts.reward)
        next_obs, rewards = np.array(next_obs), np.array(rewards)
        # Open-loop rollout of a fixed action sequence from dm_control's reset state.
        ref.reset()
        q0, v0 = ref.physics.data.qpos.copy(), ref.physics.data.qvel.copy()
        seq = np.random.default_rng(1).uniform(-1, 1, (1000, plain.action_size))
        ref_traj, ref_ret = [], 0.0
        for a in seq:
            ts = ref.step(ctrl(a))
            ref_traj.append(_dm_obs(ts))
            ref_ret += ts.reward
        ref_traj = np.array(ref_traj)
        out[task] = {"dm_control_return": ref_ret}
        for label, solver in candidates.items():
            env = make_env(task, solver=solver)
            base = jax.jit(env.reset)(jax.random.PRNGKey(0))

            def with_state(q, v, w, act, base=base):
                d = base.pipeline_state.replace(qpos=q, qvel=v, qacc_warmstart=w, act=act)
                return base.replace(pipeline_state=d)

            qs, vs, ws, acts = (jnp.asarray(np.array([s[i] for s in states]), jnp.float32) for i in range(4))
            batch = jax.jit(jax.vmap(with_state))(qs, vs, ws, acts)
            nxt = jax.jit(jax.vmap(env.step))(batch, jnp.asarray(np.array(actions), jnp.float32))
            obs_err = np.abs(np.asarray(nxt.obs) - next_obs)
            rew_err = np.abs(np.asarray(nxt.reward) - rewards)

            q, v = jnp.asarray(q0, jnp.float32), jnp.asarray(v0, jnp.float32)
            start = with_state(q, v, jnp.zeros_like(v), base.pipeline_state.act)
            traj, rew = jax.jit(functools.partial(_open_loop, env))(start, jnp.asarray(seq, jnp.float32))
            dev = np.abs(np.asarray(traj) - ref_traj).mean(axis=1)
            out[task][label] = {
                "solver": vars(solver),
                "one_step_obs_abs_err_mean": float(obs_err.mean()),
                "one_step_obs_abs_err_max": float(obs_err.max()),
                "one_step_reward_abs_err_mean": float(rew_err.mean()),
                "one_step_reward_abs_err_max": float(rew_err.max()),
                "rollout_obs_abs_dev_at": {str(t): float(dev[t - 1]) for t in (10, 100, 1000)},
                "rollout_return": float(np.sum(np.asarray(rew))),
            }
            r = out[task][label]
            print(
                f"{task:13s} {label:17s} 1-step obs err mean {r['one_step_obs_abs_err_mean']:.2e} "
                f"max {r['one_step_obs_abs_err_max']:.2e} reward err max {r['one_step_reward_abs_err_max']:.2e} | "
                f"rollout dev@10 {dev[9]:.2e} @100 {dev[99]:.2e} @1000 {dev[999]:.2e} "
                f"return {r['rollout_return']:.1f} (dm_control {ref_ret:.1f})"
            )
            sys.stdout.flush()
    return out


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("mode", choices=["throughput", "fidelity"])
    p.add_argument("--tasks", nargs="+", default=sorted(TASKS))
    p.add_argument("--solvers", nargs="+", default=["default", "dm_control"])
    p.add_argument("--batches", nargs="+", type=int, default=[1, 16, 256, 1024, 4096])
    p.add_argument("--unroll", action="store_true", help="unroll the physics substeps of a control step")
    p.add_argument(
        "--all-contacts",
        action="store_true",
        help="check every geom pair, also those a task leaves out as never near (the quadruped's; docs/tasks.md)",
    )
    p.add_argument("--impl", choices=IMPLS, default="jax", help="the physics step's implementation (MJX's impl)")
    p.add_argument("--max-dm-batch", type=int, default=4096, help="skip dm_control solver above this batch")
    p.add_argument("--fidelity-states", type=int, default=200)
    p.add_argument(
        "--candidates",
        nargs="+",
        default=["dm_control", "4/8", "2/5", "1/4", "1/4 no eulerdamp"],
        help="fidelity: the solver settings to compare (labels of fidelity's table)",
    )
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    add_xla_flags_argument(p)
    return p


def main():
    args = parser().parse_args()
    use_xla_flags(args.xla_flags)
    results = _load(args.out)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if args.mode == "throughput":
        key = lambda r: (  # A row replaces only its own code's measurement: other commits' rows stay.
            r["device"],
            r.get("commit"),
            r["task"],
            r["solver"],
            r["batch"],
            r.get("unroll_substeps", False),
            r.get("xla_flags", ""),
            r.get("all_contacts"),  # None: measured before the option existed, with every pair
            r.get("impl", "jax"),
        )
        for row in throughput(args):
            # Rows of the two presets form the main table; every setting also goes to the sweep behind the choice.
            plain = not (args.unroll or row["xla_flags"] or args.all_contacts) and args.impl == "jax"
            main_table = row["solver"] in SOLVERS and plain
            parts = ("rows", "solver_sweep") if main_table else ("solver_sweep",)
            for part in parts:
                results[part] = [r for r in results.get(part, []) if key(r) != key(row)] + [row]
            write_json(args.out, results)  # strict JSON: a diverged solver's NaN as null
    else:
        results["fidelity"] = {**provenance(), "tasks": fidelity(args)}
        write_json(args.out, results)


if __name__ == "__main__":
    main()
