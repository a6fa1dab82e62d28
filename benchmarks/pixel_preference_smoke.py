"""Pixel runs for a few rounds on one device: compile time, seconds and frames/s per seed of each round,
and the device's peak memory, written after every measurement (a call killed at its time limit keeps
what it measured). A smoke test of the sizes and the speed, not a learning result.

Jobs are :data:`pixel_memory.CONFIGS`' flags (5 seeds, 84x84, the real replay sizes: pixel PEBBLE's
replay holds the whole 500k-step run, 51.7 GiB at 5 seeds) with rounds of ``--steps-per-round`` agent
steps, so that a few rounds pass the 2,000 seed steps. Pixel PEBBLE's rounds at 1,000 steps: 0-1 seed
steps, 2 the first feedback session (with its 100 critic-reset updates), 3 on plain rounds with DrQ-v2's updates;
DrQ-v2's: 0-1 seed steps, 2 on updates. ``frames_per_s_per_seed`` counts environment frames (2 per agent
step, action repeat 2) of one seed; ``phase`` says what a round did.

    python benchmarks/pixel_preference_smoke.py --jobs drqv2_walker pebble_walker --seeds 5 --rounds 5 \\
        --max-seconds 540
    python benchmarks/pixel_preference_smoke.py --tiny --seeds 1 --rounds 3   # probe_point_pixels, 16x16, CPU

Not yet run on a GPU (2026-11-24). ``--tiny --seeds 1`` runs end to end on the 2-core CPU (41 s idle, 2
minutes under load, both jobs). On the CPU, pixel PEBBLE with 2 or more seeds hung in ``init`` (jaxlib
0.10.2: every thread waits, two in the LAPACK kernel's ``jax::ParallelBatchMap``, the batched QR of the
orthogonal initialisation of the reward members under the seed ``vmap``); ``networks.orthogonal`` now
loops over the batch one QR at a time (same values).
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import pathlib
import sys
import time

import jax
import jax.numpy as jnp

sys.path.insert(0, str(pathlib.Path(__file__).parent))
from pixel_memory import CONFIGS, with_total_steps  # noqa: E402 - benchmarks/ is not a package

from rebel_jax.agents import frame_replay  # noqa: E402
from rebel_jax.run.cli import parse  # noqa: E402
from rebel_jax.train import Trainer, compiled, seed_keys  # noqa: E402

RESULTS = pathlib.Path(__file__).parent / "results" / "pixel_smoke.json"

TINY = [
    "--task", "probe_point_pixels", "--episode-length", "20", "--num-envs", "2", "--total-steps", "200",
    "--seed-steps", "20", "--steps-per-round", "20", "--eval-every", "20", "--eval-episodes", "1",
    "--drqv2.batch-size", "16", "--drqv2.hidden", "16", "--drqv2.feature-dim", "8", "--drqv2.nstep", "1",
]  # fmt: skip
TINY_PREFERENCE = [
    "--feedback.labels", "12", "--feedback.per-session", "4", "--feedback.interval", "20",
    "--query.segment-length", "4", "--pretrain.reset-updates", "2",
]  # fmt: skip
"""``--tiny``: 16x16 probe_point_pixels, episodes of 10 agent steps, rounds of 20 (with a preference algo,
``TINY_PREFERENCE``: a session every round)."""


def job_flags(job: str, steps_per_round: int, total_steps: int, tiny: bool) -> list[str]:
    """The CLI flags of ``job``: its :data:`CONFIGS` entry with rounds of ``steps_per_round`` agent steps
    and runs of ``total_steps`` (0: the entry's 500k; a preference run's replay holds the run), or with
    ``tiny`` its algorithm on :data:`TINY`'s probe."""
    flags = with_total_steps(CONFIGS[job], total_steps)
    if tiny:
        algo = flags[flags.index("--algo") + 1]
        return ["--preset", "tiny", "--algo", algo, *TINY, *([] if algo == "drqv2" else TINY_PREFERENCE)]
    return [*flags, "--steps-per-round", str(steps_per_round)]


def peak_gib() -> float | None:
    stats = jax.devices()[0].memory_stats() or {}
    return stats["peak_bytes_in_use"] / 2**30 if "peak_bytes_in_use" in stats else None


class Results:
    """Rows of one invocation, rewritten to ``path`` after each (other invocations' rows are kept)."""

    def __init__(self, path: pathlib.Path, run_id: str):
        self.path, self.run_id = path, run_id
        self.previous = json.loads(path.read_text()) if path.exists() else []
        self.rows: list[dict] = []

    def add(self, row: dict) -> None:
        finite = {k: None if isinstance(v, float) and not math.isfinite(v) else v for k, v in row.items()}
        self.rows.append({"run": self.run_id, **finite})  # strict JSON: NaN as null
        print(json.dumps(self.rows[-1]), flush=True)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.previous + self.rows, indent=1) + "\n")
        tmp.replace(self.path)


def run_job(job: str, args, results: Results, deadline: float) -> None:
    flags = job_flags(job, args.steps_per_round, args.total_steps, args.tiny)
    cfg = parse(flags).config
    trainer = Trainer(cfg)
    repeat = getattr(trainer.env, "action_repeat", 1)
    command = f"python -m rebel_jax.train --seeds {args.seeds} {' '.join(flags)}"
    base = {"job": job, "seeds": args.seeds, "command": command, "seed_loop": cfg.drqv2.seed_loop}
    start = time.time()
    init, round_fn, _ = compiled(trainer)
    state = jax.block_until_ready(init(seed_keys(0, args.seeds)))
    init_s = time.time() - start
    buffer = frame_replay.nbytes(jax.tree.map(lambda x: x[0], state.buffer))
    start = time.time()
    program = round_fn.lower(state, jnp.int32(0)).compile()
    compile_s = time.time() - start
    results.add({**base, "what": "compile", "init_s": round(init_s, 2), "compile_s": round(compile_s, 2),
                 "replay_gb_per_seed": buffer / 1e9, "peak_gib": peak_gib()})  # fmt: skip
    last = 0.0  # the first round always runs (the caller's own timeout bounds it); later ones are estimated
    for r in range(args.rounds):
        if time.time() + last > deadline:
            reason = "--max-seconds: the next round would not fit"
            results.add({**base, "what": "stopped", "round": r, "reason": reason})
            return
        start = time.time()
        state, metrics = program(state, jnp.int32(r))
        metrics = jax.device_get(metrics)
        seconds = last = time.time() - start
        session = bool(trainer.preference and metrics["session"].mean() == 1.0)
        seeding = (r + 1) * cfg.train.steps_per_round <= cfg.train.seed_steps
        phase = "seed steps" if seeding else ("session + updates" if session else "updates")
        steps = cfg.train.steps_per_round
        shown = (
            "labels_used",
            "reward_epochs",
            "reward_accuracy_all",
            "reward_correlation_replay",
            "critic_loss",
            "diverged",
        )
        results.add(
            {
                **base,
                "what": "round",
                "round": r,
                "phase": phase,
                "seconds": round(seconds, 3),
                "agent_steps_per_s_per_seed": steps / seconds,
                "frames_per_s_per_seed": steps * repeat / seconds,
                "frames_per_s_all_seeds": steps * repeat * args.seeds / seconds,
                "peak_gib": peak_gib(),
                **{k: float(metrics[k].mean()) for k in shown if k in metrics},
            }
        )


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--jobs", nargs="+", default=["drqv2_walker", "pebble_walker"], choices=list(CONFIGS))
    p.add_argument("--seeds", type=int, default=5)
    p.add_argument("--rounds", type=int, default=5, help="rounds per job, compile excluded")
    p.add_argument("--steps-per-round", type=int, default=1000, help="agent steps per seed and round")
    p.add_argument("--total-steps", type=int, default=0, help="agent steps of the run (sizes a preference replay)")
    p.add_argument("--max-seconds", type=float, default=540.0, help="wall-time cap of the whole invocation")
    p.add_argument("--tiny", action="store_true", help="probe_point_pixels at 16x16 (a CPU check)")
    p.add_argument("--out", type=pathlib.Path, default=RESULTS)
    return p


def main() -> None:
    args = parser().parse_args()
    deadline = time.time() + args.max_seconds
    stamp = datetime.datetime.now().isoformat(timespec="seconds")
    results = Results(args.out, stamp)
    device = jax.devices()[0]
    print(json.dumps({"device": str(device), "kind": device.device_kind, "jax": jax.__version__}), flush=True)
    results.add({"what": "meta", "device": device.device_kind, "backend": jax.default_backend(), "jax": jax.__version__,
                 "max_seconds": args.max_seconds, "argv": sys.argv[1:]})  # fmt: skip
    for job in args.jobs:
        if time.time() >= deadline:
            results.add({"job": job, "what": "stopped", "reason": "--max-seconds"})
            continue
        try:
            run_job(job, args, results, deadline)
        except Exception as error:  # noqa: BLE001 - e.g. out of memory: recorded, the next job still runs
            results.add({"job": job, "what": "error", "error": f"{type(error).__name__}: {str(error)[:500]}"})


if __name__ == "__main__":
    main()
