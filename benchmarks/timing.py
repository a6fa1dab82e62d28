"""Shared timing for the benchmarks: median seconds per inner step of a jitted stateful call."""

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

from rebel_jax.run.cli import _git_commit


def add_xla_flags_argument(p: argparse.ArgumentParser) -> None:
    """``--xla-flags FLAGS``: this process's XLA_FLAGS (:func:`use_xla_flags`), recorded in each row."""
    p.add_argument(
        "--xla-flags",
        default=None,
        help="XLA_FLAGS for this process, e.g. --xla-flags=--xla_gpu_enable_command_buffer=... (default: the "
        "environment's)",
    )


def use_xla_flags(flags: str | None) -> None:
    """Sets XLA_FLAGS to ``flags`` (None keeps the environment's). XLA reads them when its first backend starts,
    so call this before anything runs on a device."""
    if flags is not None:
        os.environ["XLA_FLAGS"] = flags


def xla_flags() -> str:
    """The XLA_FLAGS this process runs with: the ``xla_flags`` of a result row."""
    return os.environ.get("XLA_FLAGS", "")


def device_name() -> str:
    """The first device's kind (e.g. ``NVIDIA H100 80GB HBM3``), or ``cpu``: the ``device`` of a result row."""
    return jax.devices()[0].device_kind if jax.default_backend() != "cpu" else "cpu"


def provenance() -> dict:
    """What every result row says about where it ran: device, date, JAX version, commit and command."""
    return {
        "device": device_name(),
        "date": datetime.date.today().isoformat(),
        "jax": jax.__version__,
        "xla_flags": xla_flags(),
        "commit": _git_commit(),
        "command": " ".join(["python"] + sys.argv),
    }


def merge_rows(out: pathlib.Path, rows, fields: tuple[str, ...]) -> None:
    """Writes each row of ``rows`` into ``out``'s ``{"rows": [...]}`` as it comes, replacing an earlier row
    with the same ``fields`` (a field a row lacks counts as None). With ``commit`` among them, a measurement
    replaces only its own code's: the rows of other commits stay, as the numbers quoted from them."""
    results = json.loads(out.read_text()) if out.exists() else {"rows": []}
    key = lambda r: tuple(r.get(f) for f in fields)
    out.parent.mkdir(parents=True, exist_ok=True)
    for row in rows:
        results["rows"] = [r for r in results["rows"] if key(r) != key(row)] + [row]
        out.write_text(json.dumps(results, indent=1) + "\n")


def median_seconds(run, state, per_call: int, repeats: int = 5) -> float:
    """Median seconds per inner step of ``state = run(state, key)`` after a compile + warm-up call.

    Args:
      run: jitted ``(state, key) -> state`` doing ``per_call`` inner steps.
      state: its initial state.
      per_call: inner steps per call.
      repeats: timed calls.
    """
    state = jax.block_until_ready(run(state, jax.random.PRNGKey(1)))  # compile + warm-up
    times = []
    for i in range(repeats):
        t0 = time.perf_counter()
        state = jax.block_until_ready(run(state, jax.random.PRNGKey(2 + i)))
        times.append((time.perf_counter() - t0) / per_call)
    return statistics.median(times)


def random_steps_seconds(env, states, per_call: int, repeats: int = 5) -> float:
    """Median seconds per batched step of ``env`` from ``states`` under uniformly random actions.

    Args:
      env: an environment with ``step`` and ``action_size``.
      states: a batch of its states (leading axis).
      per_call: steps per jitted call (one ``lax.scan``).
      repeats: timed calls.
    """
    batch = states.reward.shape[0]

    def body(state, key):
        action = jax.random.uniform(key, (batch, env.action_size), minval=-1, maxval=1)
        return jax.vmap(env.step)(state, action), ()

    @jax.jit
    def run(state, key):
        state, _ = jax.lax.scan(body, state, jax.random.split(key, per_call))
        return state

    return median_seconds(run, states, per_call, repeats)
