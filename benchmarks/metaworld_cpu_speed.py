"""Env steps per second of Meta-World itself (the ``metaworld`` package, MuJoCo on the CPU): one process, and N.

Usage (in an environment with ``metaworld`` installed, not the project's: Meta-World 3.1.1 pins mujoco 3.3.0):

  python benchmarks/metaworld_cpu_speed.py [--tasks drawer-open door-open] [--processes 1 2] [--steps 5000]

Each task is built as the preference-RL code bases build it (rll-research/BPref@f3ece2e:utils.py,
``make_metaworld_env``): ``ALL_V3_ENVIRONMENTS[<task>-v3]()``, a fresh random object position at every reset
(``_freeze_rand_vec = False``), ``_set_task_called = True``, seeded. A process steps one environment with uniform random
actions in [-1, 1]^4 for ``--steps`` steps, resetting after each 500-step episode (the resets are counted in the time,
as in training). With ``--processes N`` N processes (``multiprocessing``, one environment each, no pinning) run at
once after a common start: the rate is all their steps over the longest one's time. The JSON keeps the CPU's model,
its core count and the load averages before and after (other work on the machine slows the processes). Writes
``benchmarks/results/metaworld_cpu_speed.json`` (with ``--out``: elsewhere).
"""

from __future__ import annotations

import argparse
import datetime
import json
import multiprocessing as mp
import os
import pathlib
import platform
import shlex
import sys
import time

import numpy as np

RESULTS = pathlib.Path(__file__).parents[1] / "benchmarks" / "results" / "metaworld_cpu_speed.json"


def make(task: str, seed: int):
    """Meta-World's ``<task>-v3`` as the preference-RL code bases build it (see the module's docstring)."""
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    env = ALL_V3_ENVIRONMENTS[f"{task}-v3"]()
    env._freeze_rand_vec = False
    env._set_task_called = True
    env.seed(seed)
    return env


def run(task: str, steps: int, seed: int, start=None) -> tuple[int, float]:
    """Steps one environment ``steps`` times with random actions, resetting after each episode.

    Args:
      task: Meta-World's task name without the version.
      steps: env steps to time.
      seed: the environment's and the actions' seed.
      start: a barrier to wait at before timing (several processes), or None.

    Returns:
      (steps, seconds).
    """
    env = make(task, seed)
    rng = np.random.default_rng(seed)
    env.reset()
    for _ in range(20):  # warm up
        env.step(rng.uniform(-1, 1, 4).astype(np.float32))
    env.reset()
    if start is not None:
        start.wait()
    t = 0
    began = time.perf_counter()
    for _ in range(steps):
        _, _, _, truncated, _ = env.step(rng.uniform(-1, 1, 4).astype(np.float32))
        t += 1
        if truncated or t >= env.max_path_length:
            env.reset()
            t = 0
    return steps, time.perf_counter() - began


def _worker(args: tuple) -> tuple[int, float]:
    task, steps, seed, start = args
    return run(task, steps, seed, start)


def measure(task: str, processes: int, steps: int) -> dict:
    """``processes`` processes at once, each stepping its own environment ``steps`` times.

    Returns:
      The rate (all steps over the longest process's time), and the per-process rates.
    """
    if processes == 1:
        n, seconds = run(task, steps, 0)
        return {"steps_per_s": n / seconds, "per_process_steps_per_s": [n / seconds], "seconds": seconds}
    ctx = mp.get_context("spawn")
    with ctx.Manager() as manager:
        start = manager.Barrier(processes)
        with ctx.Pool(processes) as pool:
            out = pool.map(_worker, [(task, steps, seed, start) for seed in range(processes)])
    longest = max(s for _, s in out)
    return {
        "steps_per_s": sum(n for n, _ in out) / longest,
        "per_process_steps_per_s": [n / s for n, s in out],
        "seconds": longest,
    }


def cpu_model() -> str:
    """The CPU's model name (/proc/cpuinfo), or the platform's processor string."""
    try:
        for line in pathlib.Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def versions() -> dict:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for package in ("metaworld", "mujoco", "gymnasium", "numpy"):
        try:
            out[package] = metadata.version(package)
        except metadata.PackageNotFoundError:
            out[package] = None
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tasks", nargs="+", default=["drawer-open", "door-open"])
    parser.add_argument("--processes", nargs="+", type=int, default=[1, os.cpu_count() or 1])
    parser.add_argument("--steps", type=int, default=5000, help="env steps per process")
    parser.add_argument("--out", type=pathlib.Path, default=RESULTS)
    parser.add_argument("--note", default="", help="free text stored with the results (e.g. what else ran)")
    args = parser.parse_args(argv)
    load_before = os.getloadavg()
    if args.steps < 1 or any(p < 1 for p in args.processes):
        parser.error("--steps and --processes must be >= 1")
    results = {}
    for task in args.tasks:
        results[task] = {}
        for p in args.processes:
            results[task][str(p)] = measure(task, p, args.steps)
            print(f"{task} processes={p}: {results[task][str(p)]['steps_per_s']:.0f} env steps/s", flush=True)
    out = {
        "what": "env steps per second of the metaworld package (MuJoCo on the CPU), random actions, resets counted",
        "device": {"cpu": cpu_model(), "cores": os.cpu_count(), "note": args.note},
        "load_average_1_5_15_min": {"before": load_before, "after": os.getloadavg()},
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "versions": versions(),
        "command": "python benchmarks/metaworld_cpu_speed.py " + shlex.join(sys.argv[1:] if argv is None else argv),
        "steps_per_process": args.steps,
        "results": results,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
