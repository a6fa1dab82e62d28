"""Runs a plan of training jobs side by side on one machine's GPUs, within one wall-clock call.

Usage:
  python experiments/gpu_batch.py PLAN.json --seconds 540 [--runs-dir runs/batch] [--out DIR]

A plan is a JSON list of jobs ``{"name": str, "gpu": int, "args": [train flags...]}``. Every
job runs ``python -m rebel_jax.train ARGS --run-dir RUNS_DIR/NAME`` on its GPU (jobs sharing a
GPU split its memory). Each gets ``--time-limit`` so that it checkpoints and stops before the
call ends; a job whose run directory already holds a checkpoint is resumed, and a finished one
(``final.json``) is skipped. So the same command, called again on a machine that kept
``RUNS_DIR``, carries every job further until all are done. The small log files (config, meta,
metrics, final) are copied to ``--out`` (e.g. ``$OUT``) after each call; the last lines printed
are a table of where every job stands.
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time

LOGS = ("config.json", "meta.json", "metrics.jsonl", "final.json")
CHECKPOINT_EVERY = 10
"""Rounds between checkpoints besides the one at the time limit (insurance against a crash)."""


def _state(run_dir: pathlib.Path) -> str:
    if (run_dir / "final.json").exists():
        return "done"
    # Complete orbax saves only: an interrupted one is a temporary ``<step>.orbax-checkpoint-tmp-*``.
    if any(p.name.isdigit() for p in (run_dir / "checkpoints").glob("*")):
        return "resume"
    if (run_dir / "config.json").exists():  # started, killed before its first checkpoint: --resume restarts it
        return "resume"
    return "new"


def _command(job: dict, run_dir: pathlib.Path, seconds: float, state: str) -> list[str]:
    cmd = [sys.executable, "-m", "rebel_jax.train", *job["args"], "--run-dir", str(run_dir)]
    cmd += ["--time-limit", f"{seconds:.0f}", "--checkpoint-every", str(CHECKPOINT_EVERY)]
    cmd += ["--no-progress", "--no-tensorboard"]
    return cmd + (["--resume"] if state == "resume" else [])


def run_summary(run_dir: pathlib.Path) -> tuple[int, str]:
    """(env steps reached, mean of the last logged evaluation) from a run's metrics."""
    metrics = run_dir / "metrics.jsonl"
    if not metrics.exists():
        return 0, "-"
    rows = [json.loads(line) for line in metrics.read_text().splitlines() if line.strip()]
    evals = [row for row in rows if "eval_return" in row]
    last = f"{sum(evals[-1]['eval_return']) / len(evals[-1]['eval_return']):.1f}" if evals else "-"
    return (rows[-1]["env_steps"] if rows else 0), last


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("plan", type=pathlib.Path)
    parser.add_argument("--seconds", type=float, required=True, help="wall time each job may use in this call")
    parser.add_argument("--runs-dir", type=pathlib.Path, default=pathlib.Path("runs/batch"))
    parser.add_argument("--out", type=pathlib.Path, default=None, help="where to copy the log files")
    args = parser.parse_args()
    jobs = json.loads(args.plan.read_text())
    names = [job["name"] for job in jobs]
    if len(set(names)) != len(names):
        raise SystemExit(f"error: job names repeat in {args.plan}: {names}")
    per_gpu = collections.Counter(job["gpu"] for job in jobs)
    procs = {}
    for job in jobs:
        run_dir = args.runs_dir / job["name"]
        state = _state(run_dir)
        if state == "done":
            continue
        env = dict(os.environ, CUDA_VISIBLE_DEVICES=str(job["gpu"]))
        env["XLA_PYTHON_CLIENT_MEM_FRACTION"] = f"{0.9 / per_gpu[job['gpu']]:.2f}"
        run_dir.mkdir(parents=True, exist_ok=True)
        log = open(run_dir / "stdout.log", "a")  # noqa: SIM115 (closed below)
        cmd = _command(job, run_dir, args.seconds, state)
        print(f"[{job['name']}] gpu {job['gpu']} ({state}): {' '.join(cmd[1:])}", flush=True)
        procs[job["name"]] = (subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT), log)
    started = time.time()
    for name, (proc, log) in procs.items():
        try:
            proc.wait(timeout=max(1.0, args.seconds + 60 - (time.time() - started)))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
            print(f"[{name}] killed: it overran --seconds by a minute", flush=True)
        log.close()
        if proc.returncode:
            print(f"[{name}] exit {proc.returncode}; tail of its log:", flush=True)
            print("".join((args.runs_dir / name / "stdout.log").read_text().splitlines(keepends=True)[-15:]))
    print(f"\n{'job':36s} {'state':7s} {'env steps':>10s} {'last eval':>10s}")
    for job in jobs:
        run_dir = args.runs_dir / job["name"]
        steps, last = run_summary(run_dir)
        print(f"{job['name']:36s} {_state(run_dir):7s} {steps:>10d} {last:>10s}")
        if args.out is not None:
            (args.out / job["name"]).mkdir(parents=True, exist_ok=True)
            for file in (*LOGS, "stdout.log"):
                if (run_dir / file).exists():
                    shutil.copy(run_dir / file, args.out / job["name"] / file)


if __name__ == "__main__":
    main()
