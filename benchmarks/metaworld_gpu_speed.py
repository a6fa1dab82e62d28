"""Env steps per second of the Meta-World tasks on MJX (jitted, vmapped), per task, physics impl and batch size.

Usage:
  python benchmarks/metaworld_gpu_speed.py [--tasks metaworld_drawer-open ...] [--impls jax,warp]
      [--batches 1,64,1024] [--steps 500] [--repeats 3] [--out FILE]

Each measurement is one jitted call: a ``lax.scan`` of ``--steps`` vector steps of ``batch`` environments (brax's
``VmapWrapper``, as the trainer steps them) under uniformly random actions in [-1, 1]^4. As in the trainer
(``rebel_jax.train.trainer.Trainer.vector_step``), every environment is reset together under ``lax.cond`` at each
episode boundary, so with ``--steps`` a multiple of ``--episode-length`` (Meta-World: 500) a call runs whole episodes
and the resets are counted in the time. The call is traced and lowered (``lower_s``) and compiled by
XLA ahead of time (``compile_s``; a task's batch sizes compile ``--compile-workers`` at once, each program's own
seconds, ``compiled_at_once`` saying how many shared the host), run once as a warm-up (``first_call_s``), then timed
``--repeats`` times after ``block_until_ready``; ``env_steps_per_s`` is ``batch * steps`` over the median.

A (task, impl) pairing the project refuses (a task of ``rebel_jax.envs.metaworld.STEP_REFUSED``, Meta-World with
``impl='warp'``, or ``warp`` without the ``warp-lang`` package) is skipped: its one-line reason is printed and kept
as a row with ``refused``. Each row also carries the one-process rate of the ``metaworld`` package (MuJoCo on the
CPU) from ``benchmarks/results/metaworld_cpu_speed.json`` where that file has the task. Rows are merged into
``benchmarks/results/metaworld_gpu_speed.json`` as each measurement finishes (a row replaces only the same code's
measurement of the same setting).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import importlib.util
import json
import pathlib
import statistics
import time

import jax
import jax.numpy as jnp
from timing import add_xla_flags_argument, merge_rows, provenance, use_xla_flags

from rebel_jax.envs import IMPLS, METAWORLD_TASKS, VmapWrapper, make_env, metaworld

RESULTS = pathlib.Path(__file__).parent / "results" / "metaworld_gpu_speed.json"
CPU_RESULTS = pathlib.Path(__file__).parent / "results" / "metaworld_cpu_speed.json"
FIELDS = ("device", "commit", "xla_flags", "task", "impl", "batch", "steps", "episode_length")


def warp_missing() -> str | None:
    """Why MuJoCo Warp cannot run here (``warp-lang`` or MJX's ``mujoco_warp`` not importable), or None."""
    for module in ("warp", "mujoco.mjx.third_party.mujoco_warp"):
        try:
            found = importlib.util.find_spec(module) is not None
        except ImportError:
            found = False
        if not found:
            return f"impl='warp' needs {module}, which is not importable here"
    return None


def refusal(task: str, impl: str, episode_length: int) -> tuple[object | None, str | None]:
    """The environment of ``task`` under ``impl``, or why the pairing is refused.

    Returns:
      (env, None), or (None, a one-line reason).
    """
    if impl == "warp" and (why := warp_missing()):
        return None, why
    try:
        return make_env(task, episode_length=episode_length, impl=impl), None
    except ValueError as e:
        return None, str(e)


def cpu_rate(task: str, path: pathlib.Path = CPU_RESULTS) -> float | None:
    """The ``metaworld`` package's one-process env steps per second of ``task`` (metaworld_cpu_speed.py), or None."""
    if not path.exists():
        return None
    one = json.loads(path.read_text())["results"].get(task.removeprefix(metaworld.PREFIX), {}).get("1")
    return one["steps_per_s"] if one else None


def rollout(env, batch: int, steps: int):
    """A jittable ``(states, t, key) -> (states, t)``: ``steps`` vector steps with random actions from vector step
    ``t``, every environment reset together at each episode boundary (as the trainer's ``vector_step``)."""
    envs = VmapWrapper(env, batch_size=batch)

    def body(carry, key):
        states, t = carry
        key_reset, key_act = jax.random.split(key)
        new_episode = (t % env.episode_length == 0) & (t > 0)
        states = jax.lax.cond(new_episode, lambda: envs.reset(key_reset), lambda: states)
        action = jax.random.uniform(key_act, (batch, env.action_size), minval=-1, maxval=1)
        return (envs.step(states, action), t + 1), ()

    def run(states, t, key):
        return jax.lax.scan(body, (states, t), jax.random.split(key, steps))[0]

    return envs, run


def lower(env, batch: int, steps: int) -> dict:
    """Traces and lowers the ``steps``-step call of ``batch`` environments; resets them (jitted)."""
    envs, run = rollout(env, batch, steps)
    states = jax.block_until_ready(jax.jit(envs.reset)(jax.random.PRNGKey(0)))
    t = jnp.zeros((), jnp.int32)
    start = time.perf_counter()
    lowered = jax.jit(run).lower(states, t, jax.random.PRNGKey(1))
    return {"lowered": lowered, "states": states, "t": t, "lower_s": time.perf_counter() - start}


def compile_timed(lowered) -> tuple[object, float]:
    """XLA's compile of ``lowered`` and its seconds."""
    start = time.perf_counter()
    compiled = lowered.compile()
    return compiled, time.perf_counter() - start


def compile_all(lowered: list, workers: int) -> list[tuple[object, float]]:
    """Compiles each of ``lowered``, ``workers`` at once (XLA's compile releases Python's lock)."""
    if workers <= 1:
        return [compile_timed(low) for low in lowered]
    with concurrent.futures.ThreadPoolExecutor(workers) as pool:
        return list(pool.map(compile_timed, lowered))


def measure(compiled, states, t, batch: int, steps: int, repeats: int) -> dict:
    """First-call seconds and the median seconds of ``compiled``, a ``steps``-step call of ``batch`` envs."""
    start = time.perf_counter()
    states, t = jax.block_until_ready(compiled(states, t, jax.random.PRNGKey(2)))
    first = time.perf_counter() - start
    times = []
    for i in range(repeats):
        start = time.perf_counter()
        states, t = jax.block_until_ready(compiled(states, t, jax.random.PRNGKey(3 + i)))
        times.append(time.perf_counter() - start)
    seconds = statistics.median(times)
    return {
        "env_steps_per_s": batch * steps / seconds,
        "ms_per_vector_step": seconds / steps * 1e3,
        "call_s": seconds,
        "call_s_all": times,
        "first_call_s": first,
    }


def rows(args):
    """Yields one result row per (task, impl, batch), or one per refused (task, impl)."""
    for task in args.tasks:
        cpu = cpu_rate(task)
        for impl in args.impls:
            common = {
                **provenance(),
                "task": task,
                "impl": impl,
                "steps": args.steps,
                "episode_length": args.episode_length,
                "repeats": args.repeats,
                "metaworld_cpu_one_process_steps_per_s": cpu,
            }
            env, why = refusal(task, impl, args.episode_length)
            if why:
                print(f"{task} {impl}: skipped: {why}", flush=True)
                yield {**common, "batch": None, "refused": why}
                continue
            # MuJoCo Warp's contact buffer holds every world of a vmapped step: an environment per batch size.
            sized = {
                b: env if impl == "jax" else make_env(task, episode_length=args.episode_length, impl=impl, worlds=b)
                for b in args.batches
            }
            env.build_warp_kernels()
            lowered = [lower(sized[batch], batch, args.steps) for batch in args.batches]
            workers = min(args.compile_workers, len(lowered))
            start = time.perf_counter()
            compiled = compile_all([low["lowered"] for low in lowered], workers)
            print(f"{task} {impl}: compiled {len(lowered)} programs in {time.perf_counter() - start:.1f} s", flush=True)
            for batch, low, (program, compile_s) in zip(args.batches, lowered, compiled, strict=True):
                r = measure(program, low["states"], low["t"], batch, args.steps, args.repeats)
                r = {**r, "lower_s": low["lower_s"], "compile_s": compile_s, "compiled_at_once": workers}
                print(
                    f"{task} {impl} batch {batch}: {r['env_steps_per_s']:,.0f} env steps/s "
                    f"({r['ms_per_vector_step']:.2f} ms/vector step; lower {r['lower_s']:.1f} s, compile "
                    f"{compile_s:.1f} s ({workers} at once), first call {r['first_call_s']:.1f} s)",
                    flush=True,
                )
                yield {**common, "batch": batch, **r}


def _positive_ints(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"every value must be >= 1, got {text!r}")
    return values


def _impls(text: str) -> list[str]:
    values = text.split(",")
    if bad := [v for v in values if v not in IMPLS]:
        raise argparse.ArgumentTypeError(f"unknown impl {bad[0]!r}; one of {', '.join(IMPLS)}")
    return values


def _task(text: str) -> str:
    name = text if text.startswith(metaworld.PREFIX) else f"{metaworld.PREFIX}{text}"
    if name.removeprefix(metaworld.PREFIX) not in metaworld.TASKS:
        valid = ", ".join(f"{metaworld.PREFIX}{t}" for t in metaworld.TASKS)
        raise argparse.ArgumentTypeError(f"unknown Meta-World task {text!r}; valid: {valid}")
    return name


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--tasks",
        nargs="+",
        type=_task,
        default=list(METAWORLD_TASKS),
        help="Meta-World tasks, with or without the metaworld_ prefix (default: those whose step runs)",
    )
    p.add_argument("--impls", type=_impls, default=list(IMPLS), help="comma-separated impls (default: jax,warp)")
    p.add_argument("--batches", type=_positive_ints, default=[1, 64, 1024], help="comma-separated batch sizes")
    p.add_argument("--steps", type=int, default=metaworld.EPISODE_LENGTH, help="vector steps per timed call")
    p.add_argument("--episode-length", type=int, default=metaworld.EPISODE_LENGTH, help="steps between resets")
    p.add_argument("--repeats", type=int, default=3, help="timed calls per measurement (median)")
    p.add_argument(
        "--compile-workers",
        type=int,
        default=3,
        help="a task's programs (one per batch size) compiled at once (default: %(default)s)",
    )
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    add_xla_flags_argument(p)
    return p


def main(argv: list[str] | None = None) -> None:
    p = parser()
    args = p.parse_args(argv)
    if min(args.steps, args.episode_length, args.repeats, args.compile_workers) < 1:
        p.error("--steps, --episode-length, --repeats and --compile-workers must be >= 1")
    use_xla_flags(args.xla_flags)
    print(f"device: {jax.devices()[0].device_kind}, JAX {jax.__version__}", flush=True)
    merge_rows(args.out, rows(args), FIELDS)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
