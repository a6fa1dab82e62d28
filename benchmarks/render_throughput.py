"""Render and pixel-env throughput: frames/s and ms per call of the pure-JAX camera.

Usage:
  python benchmarks/render_throughput.py [--tasks walker_walk cheetah_run] [--batches 1 64 256 1024 4096]
      [--size 84] [--what render env_step physics] [--out FILE]

Rows (merged into ``benchmarks/results/render_throughput.json`` by default):

- ``render``: one jitted ``vmap(camera.render)`` of ``batch`` states of camera 0 (shading,
  shadows and reflection on), median over repeated calls after a compile and warm-up call.
- ``env_step``: one agent step of the pixel task (``<task>_pixels``: action repeat 2 of the
  state task's physics, then the render and the frame stack), timed as scans of 10 steps.
- ``physics``: the same agent step without the camera (the state task stepped twice), the
  baseline of the issue's "pixel env step <= 1.3 x physics" target.

``frames_per_s`` is rendered frames (``render``) or agent steps (``env_step``, ``physics``)
per second over the batch.
"""

from __future__ import annotations

import argparse
import datetime
import json
import pathlib
import statistics
import sys
import time

import jax
import jax.numpy as jnp
from timing import random_steps_seconds

from rebel_jax.envs import make_env

RESULTS = pathlib.Path(__file__).parent / "results" / "render_throughput.json"
STEPS_PER_CALL = 10


def _device() -> str:
    return jax.devices()[0].device_kind if jax.default_backend() != "cpu" else "cpu"


def _states(env, batch: int):
    """``batch`` pixel-task states a few random steps after their resets (varied poses)."""
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(0), batch))
    step = jax.jit(jax.vmap(env.step))
    for i in range(3):
        action = jax.random.uniform(jax.random.PRNGKey(i), (batch, env.action_size), minval=-1, maxval=1)
        state = step(state, action)
    return state


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
    device, date = _device(), datetime.date.today().isoformat()
    command = " ".join(["python"] + sys.argv)
    for task in args.tasks:
        env = make_env(f"{task}_pixels")
        if args.size != env.camera.height:
            from rebel_jax.envs import PixelEnv

            env = PixelEnv(env.env, size=args.size)
        for batch in args.batches:
            states = _states(env, batch)
            for what in args.what:
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
                }
                print(json.dumps(row), flush=True)
                yield row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["walker_walk", "cheetah_run"])
    parser.add_argument("--batches", nargs="+", type=int, default=[1, 64, 256, 1024, 4096])
    parser.add_argument("--size", type=int, default=84)
    parser.add_argument("--what", nargs="+", default=["render", "env_step", "physics"],
                        choices=["render", "env_step", "physics"])  # fmt: skip
    parser.add_argument("--out", type=pathlib.Path, default=RESULTS)
    args = parser.parse_args(argv)
    new = list(rows(args))
    old = json.loads(args.out.read_text())["rows"] if args.out.exists() else []
    # Replace rows of the same device, task, size, batch and kind; keep the rest.
    key = lambda r: (r["device"], r["task"], r["size"], r["batch"], r["what"])
    fresh = {key(r) for r in new}
    merged = [r for r in old if key(r) not in fresh] + new
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"rows": merged}, indent=1) + "\n")


if __name__ == "__main__":
    jnp.zeros(())  # initialise the backend before timing
    main()
