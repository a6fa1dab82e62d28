"""Where a pixel preference session spends its time, part by part, on one seed: one epoch of the pixel reward
ensemble's training over ``--labels`` stored pairs with the Bradley-Terry term alone (PEBBLE's), the same epoch with
REBEL's value term added (for a REBEL job), and the relabelling of the whole replay, each at every
``--pixel-reward.precision`` asked for.

A session of the first pixel cheetah run (PEBBLE and REBEL columns side by side, 4 columns, tf32) took
55-150 s against 5.9 s for a plain round (BENCHMARKS.md, "Pixels"), so a session's cost
decides how long a pixel preference run takes. A session trains up to ``pixel_reward.max_epochs`` epochs (it stops
once the ensemble fits its labels), so its training costs about epochs x one epoch's seconds; in a ``--lam-grid``
program every column computes REBEL's term (lambda 0 multiplies it), so PEBBLE's columns there cost REBEL's epoch.

The state is the trainer's own (``Trainer.init``: the real replay, label store and networks, :data:`CONFIGS`'
shapes) with its counters set full: the replay holds ``--rows`` rows (default all) and the label store ``--labels``
pairs. Their contents are the initial zeros, which cost the same arithmetic as real frames. Timing only.

    python benchmarks/pixel_session_parts.py --jobs rebel_cheetah pebble_walker --labels 200 --precisions tf32 bf16
    python benchmarks/pixel_session_parts.py --tiny --jobs rebel_cheetah --labels 8   # probe_point_pixels, CPU

With ``--columns C`` (default 4, 0 for none) it also times whole sessions (``Trainer.feedback_session``:
select, teach, train, relabel) vmapped over C columns as the trainer runs them, with ``pixel_reward.session_loop``
on and off (``--session-loops``): batched, the members' convolutions are grouped over the columns. Each session
trains ``max_epochs`` epochs (``--pixel-reward.stop-accuracy 1``: it never stops early; the row's ``epochs``), an
upper bound on a session, whose epochs vary (3-19 in that run).

Rows go to ``benchmarks/results/pixel_session_parts.json`` (``--out``): per part and precision the compile seconds,
the median seconds of ``--repeats`` calls after it, and the device's peak memory.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import pathlib
import statistics
import sys
import time

import jax
import jax.numpy as jnp

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from pixel_memory import CONFIGS  # noqa: E402 - benchmarks/ is not a package
from pixel_preference_smoke import Results, job_flags, peak_gib  # noqa: E402
from timing import provenance  # noqa: E402

from rebel_jax.agents import frame_replay
from rebel_jax.preference import reward_model, reward_train  # noqa: E402
from rebel_jax.run.cli import parse  # noqa: E402
from rebel_jax.train import Trainer, TrainState, seed_keys  # noqa: E402

RESULTS = pathlib.Path(__file__).parent / "results" / "pixel_session_parts.json"


def filled(ts: TrainState, labels: int, rows: int | None) -> TrainState:
    """``ts`` with ``labels`` stored pairs and ``rows`` written replay rows (None: all of them)."""
    data = ts.reward.data
    if not 0 < labels <= data.capacity:
        raise SystemExit(f"--labels {labels}: the label store holds 1..{data.capacity} pairs for this job")
    data = data.replace(
        count=jnp.asarray(labels, data.count.dtype), ptr=jnp.asarray(labels % data.capacity, data.ptr.dtype)
    )
    size = ts.buffer.rows if rows is None else min(rows, ts.buffer.rows)
    return ts.replace(
        reward=ts.reward.replace(data=data), buffer=ts.buffer.replace(size=jnp.asarray(size, ts.buffer.size.dtype))
    )


def parts(trainer: Trainer, relabel_rows: tuple[int, ...] = ()) -> dict:
    """``name -> function of (ts, key)`` for each part of a session that this job's algorithm runs, and the
    relabelling at each of ``relabel_rows`` rows per ``lax.map`` step besides the trainer's
    ``pixel_reward.relabel_rows``
    (``relabel_<rows>``: a larger chunk means fewer, larger steps; the same rewards)."""
    rcfg = trainer.cfg.pixel_reward
    agent_step = jnp.int32(trainer.cfg.train.total_steps // 2)  # any step past the seed steps

    def epoch_bt(ts, key):
        return reward_train.train_epoch(rcfg, ts.reward, key)[0].params

    def epoch_rebel(ts, key):
        # The trainer's own REBEL term, as ``Trainer.learn`` builds it (``--rebel.form`` and source included).
        terms = trainer.method.reward_terms(trainer, ts, jax.random.fold_in(key, 1), agent_step)
        return reward_train.train_epoch(rcfg, ts.reward, key, terms)[0].params

    def relabel(rows, ts, key):
        del key  # Deterministic.
        reward = lambda obs, action: reward_model.mean_reward(rcfg, ts.reward.params, obs, action)  # noqa: E731
        return frame_replay.relabel(ts.buffer, reward, rows).learned_reward

    out = {"epoch_bt": epoch_bt, "relabel": functools.partial(relabel, rcfg.relabel_rows)}
    others = [rows for rows in relabel_rows if rows != rcfg.relabel_rows]
    out |= {f"relabel_{rows}": functools.partial(relabel, rows) for rows in others}
    if trainer.cfg.algo == "rebel":
        out["epoch_bt_rebel"] = epoch_rebel
    return out


def time_part(fn, *args, repeats: int, vary_key: bool = True):
    """Compile seconds, the median seconds of ``repeats`` calls of ``jit(fn)(*args)`` (nothing donated) and the
    last call's output. With ``vary_key`` the last argument is a key, folded with each call's index."""
    start = time.time()
    program = jax.jit(fn).lower(*args).compile()
    compile_s = time.time() - start
    seconds = []
    for r in range(repeats):
        call = (*args[:-1], jax.random.fold_in(args[-1], r)) if vary_key else args
        start = time.time()
        out = jax.block_until_ready(program(*call))
        seconds.append(time.time() - start)
    return compile_s, statistics.median(seconds), out


def time_sessions(job: str, precision: str, loop: bool, args, results: Results) -> None:
    """Compile seconds and the median seconds of whole sessions of ``--columns`` columns, vmapped as the trainer
    runs them, with ``session_loop`` = ``loop``."""
    switch = "--pixel-reward.session-loop" if loop else "--pixel-reward.no-session-loop"
    flags = [*job_flags(job, 1000, 0, args.tiny), "--pixel-reward.precision", precision, switch]
    flags += ["--pixel-reward.stop-accuracy", "1"]  # every epoch up to max_epochs: a session's upper bound
    trainer = Trainer(parse(flags).config)
    ts = jax.jit(jax.vmap(trainer.init))(seed_keys(0, args.columns))
    ts = jax.jit(jax.vmap(lambda t: filled(t, args.labels, args.rows)))(ts)
    step = jnp.int32(trainer.cfg.train.total_steps // 2)
    session = jax.vmap(lambda t: trainer.feedback_session(t, jnp.bool_(False), step, jnp.int32(1)))
    compile_s, seconds, (_, metrics) = time_part(session, ts, repeats=args.repeats, vary_key=False)
    results.add({"job": job, "precision": precision, "labels": args.labels, "what": "session",
                 "columns": args.columns, "session_loop": loop, "compile_s": round(compile_s, 2),
                 "seconds": round(seconds, 4), "repeats": args.repeats,
                 "epochs": float(jnp.mean(metrics["reward_epochs"])), "peak_gib": peak_gib(),
                 "command": f"python -m rebel_jax.train --seeds {args.columns} {' '.join(flags)}"})  # fmt: skip


def run_job(job: str, precision: str, args, results: Results) -> None:
    flags = [*job_flags(job, 1000, 0, args.tiny), "--pixel-reward.precision", precision]
    cfg = parse(flags).config
    trainer = Trainer(cfg)
    ts = filled(jax.jit(trainer.init)(jax.random.PRNGKey(0)), args.labels, args.rows)
    base = {
        "job": job,
        "precision": precision,
        "labels": args.labels,
        "rows": int(ts.buffer.size),
        "num_envs": cfg.env.num_envs,
        "members": cfg.pixel_reward.ensemble_size,
        "batch_size": cfg.pixel_reward.batch_size,
        "command": f"python -m rebel_jax.train {' '.join(flags)}",
    }
    for name, fn in parts(trainer, tuple(args.relabel_rows)).items():
        compile_s, seconds, _ = time_part(fn, ts, jax.random.PRNGKey(0), repeats=args.repeats)
        results.add({**base, "what": name, "compile_s": round(compile_s, 2), "seconds": round(seconds, 4),
                     "repeats": args.repeats, "peak_gib": peak_gib()})  # fmt: skip


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    preference = [name for name in CONFIGS if not name.startswith("drqv2")]
    p.add_argument("--jobs", nargs="+", default=["rebel_cheetah"], choices=preference)
    p.add_argument("--labels", type=int, default=200, help="stored pairs (SURF's walker budget is 200)")
    p.add_argument("--rows", type=int, default=None, help="written replay rows (default: all)")
    p.add_argument("--precisions", nargs="+", default=["tf32", "bf16"], choices=["tf32", "bf16", "highest"])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument(
        "--relabel-rows", type=int, nargs="*", default=[8], help="relabel chunks to time besides the config's"
    )
    p.add_argument("--columns", type=int, default=4, help="columns of the whole-session timings (0: none)")
    p.add_argument("--session-loops", nargs="+", default=["on", "off"], choices=["on", "off"])
    p.add_argument("--tiny", action="store_true", help="probe_point_pixels at 16x16 (a CPU check)")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    return p


def main() -> None:
    args = parser().parse_args()
    results = Results(args.out, datetime.datetime.now().isoformat(timespec="seconds"))
    results.add({"what": "meta", **provenance(), "backend": jax.default_backend()})
    for job in args.jobs:
        for precision in args.precisions:
            try:
                run_job(job, precision, args, results)
                for loop in args.session_loops if args.columns else ():
                    time_sessions(job, precision, loop == "on", args, results)
            except Exception as error:  # noqa: BLE001 - e.g. out of memory: recorded, the next one still runs
                error = f"{type(error).__name__}: {str(error)[:500]}"
                results.add({"job": job, "precision": precision, "what": "error", "error": error})


if __name__ == "__main__":
    main()
