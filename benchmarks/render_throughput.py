"""Render and pixel-env throughput: frames/s and ms per call of the pure-JAX camera.

Usage:
  python benchmarks/render_throughput.py [--tasks walker_walk cheetah_run] [--batches 1 64 256 1024 4096]
      [--step-batches 1024] [--size 84] [--what render env_step physics] [--out FILE]

Rows (merged into ``benchmarks/results/render_throughput.json`` by default):

- ``render``: one jitted ``vmap(camera.render)`` of ``batch`` states of camera 0 (shading,
  shadows and reflection on), median over repeated calls after a compile and warm-up call.
- ``env_step``: one agent step of the pixel task (``<task>_pixels``: action repeat 2 of the
  state task's physics, then the render and the frame stack), timed as scans of 10 steps.
- ``physics``: the same agent step without the camera (the state task stepped twice), the
  baseline of the "pixel env step <= 1.3 x physics" target.

``render`` rows are taken at ``--batches``, ``env_step`` and ``physics`` rows at ``--step-batches``
(each of those compiles the physics step again). The states are made once per task, at most
``POOL`` of them from one compiled reset, and repeated up to each batch, so a new batch
size costs only its own render compile.

``frames_per_s`` is rendered frames (``render``) or agent steps (``env_step``, ``physics``)
per second over the batch.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import statistics
import sys
import time

import jax
import jax.numpy as jnp
from timing import device_name, random_steps_seconds

from rebel_jax.envs import make_env

RESULTS = pathlib.Path(__file__).parent / "results" / "render_throughput.json"
STEPS_PER_CALL = 10
POOL = 64


def _states(env, batch: int):
    """``batch`` pixel-task states just after their resets (random poses; no step is compiled here)."""
    return jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), batch))


def _repeat(states, batch: int):
    """The first ``batch`` states of ``states`` repeated cyclically (a copy in device memory)."""
    n = states.reward.shape[0]
    index = jnp.arange(batch) % n
    return jax.block_until_ready(jax.tree.map(lambda x: jnp.take(x, index, axis=0), states))


def time_render(env, states, repeats: int = 10) -> float:
    """Median seconds of one batched render call."""
    render = jax.jit(jax.vmap(env.camera.render))
    data = states.pipeline_state
    jax.block_until_ready(render(data))  # compile + warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(render(data))
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def time_steps(env, states, repeats: int = 5) -> float:
    """Median seconds per batched agent step of ``env`` (a scan of ``STEPS_PER_CALL`` steps)."""
    return random_steps_seconds(env, states, STEPS_PER_CALL, repeats)


class _Physics:
    """The pixel task's agent step without the camera: the state task stepped ``action_repeat`` times."""

    def __init__(self, pixel_env):
        self.env, self.repeat, self.action_size = pixel_env.env, pixel_env.action_repeat, pixel_env.action_size

    def step(self, state, action):
        def one(s, _):
            return self.env.step(s, action), ()

        return jax.lax.scan(one, state, length=self.repeat)[0]


def rows(args):
    device, date = device_name(), datetime.date.today().isoformat()
    command = " ".join(["python"] + sys.argv)
    for task in args.tasks:
        env = make_env(f"{task}_pixels")
        if args.size != env.camera.height:
            from rebel_jax.envs import PixelEnv

            env = PixelEnv(env.env, size=args.size)
        pool = _states(env, min(POOL, max(args.batches + args.step_batches)))
        jobs = [(b, w) for b in sorted(set(args.batches + args.step_batches)) for w in args.what
                if (w == "render" and b in args.batches) or (w != "render" and b in args.step_batches)]  # fmt: skip
        for batch, what in jobs:
            states = _repeat(pool, batch)
            if what == "render":
                sec = time_render(env, states)
            elif what == "env_step":
                sec = time_steps(env, states)
            else:
                inner = states.replace(obs=states.info["state_obs"])
                inner = inner.replace(info={k: v for k, v in inner.info.items() if k != "state_obs"})
                sec = time_steps(_Physics(env), inner)
            row = {
                "device": device,
                "date": date,
                "jax": jax.__version__,
                "command": command,
                "task": task,
                "size": args.size,
                "batch": batch,
                "frames_per_s": batch / sec,
                "ms_per_call": sec * 1e3,
                "what": what,
                "commit": os.environ.get("REBEL_JAX_GIT_COMMIT"),
            }
            print(json.dumps(row), flush=True)
            yield row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["walker_walk", "cheetah_run"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 64, 256, 1024, 4096])
    parser.add_argument("--step-batches", nargs="+", type=int, default=[1024],
                        help="batches of the env_step and physics rows")  # fmt: skip
    parser.add_argument("--size", type=int, default=84)
    parser.add_argument("--what", nargs="+", default=["render", "env_step", "physics"],
                        choices=["render", "env_step", "physics"])  # fmt: skip
    parser.add_argument("--out", type=pathlib.Path, default=RESULTS)
    args = parser.parse_args(argv)
    old = json.loads(args.out.read_text())["rows"] if args.out.exists() else []
    # Replace rows of the same device, code, task, size, batch and kind; keep the rest. Written after
    # every row, so a call stopped at its time limit keeps what it measured.
    key = lambda r: (r["device"], r.get("commit"), r["task"], r["size"], r["batch"], r["what"])
    new = []
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for row in rows(args):
        new.append(row)
        fresh = {key(r) for r in new}
        merged = [r for r in old if key(r) not in fresh] + new
        args.out.write_text(json.dumps({"rows": merged}, indent=1) + "\n")


if __name__ == "__main__":
    jnp.zeros(())  # initialise the backend before timing
    main()
