"""The table of "How fast is a Meta-World step?": MuJoCo Warp's step on a GPU beside Meta-World on the same host's CPUs.

Usage:
  python benchmarks/metaworld_speed_table.py [--commit PREFIX] [--gpu FILE] [--cpu FILE]

Reads the rows of ``benchmarks/results/metaworld_gpu_speed.json`` (``metaworld_gpu_speed.py``) measured at the code
``--commit`` (default: the last row's) and the ``metaworld`` package's rates on the GPU host's CPUs
(``benchmarks/results/metaworld_cpu_speed_host.json``, ``metaworld_cpu_speed.py``), and prints one markdown row per
task and batch: env steps per second, milliseconds a vector step, and the ratios to one CPU process and to the most
processes measured on the host; then one row per task with the CPU's rates at each process count.
"""

from __future__ import annotations

import argparse
import json
import pathlib

RESULTS = pathlib.Path(__file__).parent / "results"


def rows_at(gpu: dict, commit: str | None) -> list[dict]:
    """The measured (not refused) rows of ``commit`` (a prefix), or of the last row's commit (rows are merged in
    the order they were measured)."""
    measured = [r for r in gpu["rows"] if "env_steps_per_s" in r]
    if commit is None:
        commit = measured[-1]["commit"]
    rows = [r for r in measured if r["commit"].startswith(commit)]
    if not rows:
        raise SystemExit(f"error: no measured row of code {commit!r} in the GPU results")
    return sorted(rows, key=lambda r: (r["task"], r["impl"], r["batch"]))


def ratio(row: dict, rates: dict | None, processes: int) -> str:
    """The GPU row's rate over the CPU's with ``processes`` processes (blank where the CPU did not run the task)."""
    return "" if rates is None else f"{row['env_steps_per_s'] / rates[str(processes)]['steps_per_s']:.1f}"


def table(rows: list[dict], cpu: dict) -> str:
    """Markdown: task, step, batch, env steps/s, ms a vector step, x one CPU process, x the host's CPUs."""
    most = max(int(n) for n in next(iter(cpu["results"].values())))
    out = [
        f"| task | step | batch | env steps/s | ms a vector step | x one CPU process | x {most} CPU processes |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        task = r["task"].removeprefix("metaworld_")
        rates = cpu["results"].get(task)
        out.append(
            f"| {task} | {r['impl']} | {r['batch']:,} | {r['env_steps_per_s']:,.0f} | {r['ms_per_vector_step']:.2f} | "
            f"{ratio(r, rates, 1)} | {ratio(r, rates, most)} |"
        )
    for task, rates in cpu["results"].items():  # one row per task: its processes and rates, in order
        ordered = sorted(rates.items(), key=lambda kv: int(kv[0]))
        processes = " / ".join(n for n, _ in ordered)
        steps = " / ".join(f"{rate['steps_per_s']:,.0f}" for _, rate in ordered)
        out.append(f"| {task} | `metaworld` on the CPU, processes | {processes} | {steps} | | | |")
    return "\n".join(out)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--commit", help="the GPU rows' code (a prefix of its commit); default: the last row's")
    p.add_argument("--gpu", type=pathlib.Path, default=RESULTS / "metaworld_gpu_speed.json")
    p.add_argument("--cpu", type=pathlib.Path, default=RESULTS / "metaworld_cpu_speed_host.json")
    args = p.parse_args()
    gpu, cpu = (json.loads(path.read_text()) for path in (args.gpu, args.cpu))
    rows = rows_at(gpu, args.commit)
    print(table(rows, cpu))
    print(
        f"\nGPU: {rows[0]['device']}, JAX {rows[0]['jax']}, {rows[0]['date']}, code {rows[0]['commit'][:7]}: "
        f"`{rows[0]['command']}`"
    )
    print(f"CPU: {cpu['device']['cpu']} ({cpu['device']['cores']} cores), {cpu['date'][:10]}: `{cpu['command']}`")


if __name__ == "__main__":
    main()
