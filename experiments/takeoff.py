"""``results/drqv2_takeoff.json`` and ``.png``: how many DrQ-v2 walker seeds leave the lying plateau, per arm of
the take-off test of ``notes/drqv2_audit.md`` (bf16, bf16 with the critics' output in float32, tf32), and in
DrQ-v2's own published curves, judged alike.

Usage:
  python experiments/takeoff.py

Two of our three walker seeds never learned (RESULTS.md, question 1), against 2 of 10 in DrQ-v2's own curves. A
failed seed stays at a lying policy's return (16-40, DrQ-v2's and ours) for the whole run; most seeds that learn
have left it by 120k frames (ours: 165-675 at 80k-120k frames; DrQ-v2's seed 1 passes 100 only after 160k, so the
criterion counts it as not taken off). The criterion is fixed before the runs:

- a seed **takes off** if the mean of its evaluations from ``FROM_FRAMES`` (100k) to the run's end exceeds
  ``THRESHOLD`` (100);
- per arm: seeds, seeds that took off, the rate with its 95% Clopper-Pearson interval (``scipy.stats.binomtest``);
- between two arms: Fisher's exact test, two-sided (``scipy.stats.fisher_exact``) on the 2x2 table.

An arm is named from each run's ``config.json`` (``drqv2.precision`` and ``drqv2.critic_out_f32``), never from
its directory, and run directories of one arm merge (``analysis.merge_runs``). Frames are agent steps x the
task's action repeat (``pixels.action_repeat``).

The same count at full length (``FULL_RUNS``, ``full_length``): a seed **walks** if its final return (the mean of
its last 10 evaluations, ``analysis.final_returns``, as every table of RESULTS.md) exceeds ``THRESHOLD``; runs of
one arm are pooled by seed, not merged, so that a run stopped at 480k frames is not cut to its shortest
neighbour's length. DrQ-v2's own curves are judged alike at 500k frames (``DRQV2_FINAL``).
"""

from __future__ import annotations

import itertools
import json
import pathlib

import numpy as np
import scipy.stats
from analysis import Curve, curve_figure, final_returns, load_runs, log_name, merge_runs
from pixels import action_repeat

RESULTS = pathlib.Path(__file__).parents[1] / "results"
RUNS: list[str] = [
    "pixels/drqv2_walker_120kframes_seed10_seeds8_bf16",
    "pixels/drqv2_walker_120kframes_seed10_seeds8_bf16_qf32",
]
"""The take-off runs' directories under ``results/runs`` (8 seeds to 120k frames per arm, the same seed keys;
experiments/README.md gives the command)."""
THRESHOLD = 100.0
"""Return above which a seed has left the plateau (a lying walker gets 16-40 per 1,000-frame episode)."""
FROM_FRAMES = 100_000
"""Frames from which a seed's evaluations are averaged."""
DRQV2 = "DrQ-v2's own curves (PyTorch, float32)"
"""The reference arm's name."""
DRQV2_FRAMES = np.array([100_000, 120_000])
DRQV2_RETURNS = np.array(
    [
        [35.3, 458.6, 174.4, 27.9, 127.9, 445.2, 60.9, 31.8, 175.9, 157.7],
        [46.9, 513.9, 231.2, 23.8, 217.2, 516.3, 176.0, 28.5, 239.1, 318.3],
    ]
)
"""The reference arm: DrQ-v2's walker_walk evaluations at 100k and 120k frames, seeds 1-10 in column order, from
facebookresearch/drqv2 ``curves/dmc_walker_walk.csv`` (commit d6dbadc; rows ``frame`` 100000 and 120000 of each
seed). Its frames count as ours (agent steps x action repeat 2); seeds 4 and 8 stay on the plateau to 1M frames,
seed 1 passes 100 only between 160k and 180k."""
FULL_RUNS: list[str] = [
    "pixels/drqv2_walker_500kframes_seed0_bf16",
    "pixels/drqv2_walker_500kframes_seed1_seeds2_bf16_stopped245k",
    "pixels/drqv2_walker_500kframes_seed20_seeds1_bf16_qf32",
    "pixels/drqv2_walker_500kframes_seed22_bf16_qf32",
    "pixels/drqv2_walker_500kframes_seed23_bf16_qf32",
    "pixels/drqv2_walker_500kframes_seed24_bf16_qf32",
    "pixels/drqv2_walker_500kframes_seed21_bf16_qf32",
]
"""The walker DrQ-v2 runs of today's code that reached 480k-500k frames (the 218k-frame run of earlier code is
left out)."""
DRQV2_FINAL = np.array([410.1, 953.2, 887.8, 26.4, 880.6, 915.1, 787.4, 28.0, 860.6, 922.9])
"""DrQ-v2's own final returns at 500k frames, seeds 1-10: per seed the mean of its 10 evaluations at 320k-500k
frames in facebookresearch/drqv2 ``curves/dmc_walker_walk.csv`` (commit c0c650b; rows ``frame`` 320000 to 500000
of each seed), the final return of our tables."""


def run_config(run_dir: pathlib.Path) -> dict:
    """A take-off run's ``config.json``: DrQ-v2 on walker_walk pixels, else a ``ValueError``."""
    cfg = json.loads((run_dir / "config.json").read_text())
    if cfg["algo"] != "drqv2" or not cfg["env"]["task"].startswith("walker_walk"):
        raise ValueError(
            f"{run_dir}: the take-off test is DrQ-v2 on walker_walk pixels, not {cfg['algo']} on {cfg['env']['task']}"
        )
    return cfg


def arm(cfg: dict) -> str:
    """The arm a run belongs to, from its config."""
    drqv2 = cfg["drqv2"]
    return drqv2["precision"] + (" + float32 critic output" if drqv2.get("critic_out_f32", False) else "")


def took_off(frames: np.ndarray, returns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per seed, its mean evaluation from ``FROM_FRAMES`` on and whether it exceeds ``THRESHOLD``."""
    late = frames >= FROM_FRAMES
    if not late.any():
        raise ValueError(f"no evaluation at or after {FROM_FRAMES} frames (the last is {frames[-1]})")
    means = np.nanmean(returns[late], axis=0)
    return means, means > THRESHOLD


def arm_curves(run_dirs: list[pathlib.Path]) -> tuple[dict[str, Curve], dict[str, list[str]]]:
    """Per arm its seeds' evaluation curve against frames (its run directories merged), and its logs."""
    parts: dict[str, list] = {}
    logs: dict[str, list[str]] = {}
    for run_dir in run_dirs:
        cfg = run_config(run_dir)
        steps, returns = load_runs(run_dir)
        parts.setdefault(arm(cfg), []).append((steps * action_repeat(cfg["env"]["task"]), returns))
        logs.setdefault(arm(cfg), []).append(log_name(run_dir, RESULTS))
    return {name: merge_runs(*runs) for name, runs in parts.items()}, logs


def tally(
    scores: dict[str, np.ndarray], frames: dict[str, list[int]], logs: dict[str, list[str]], count: str, score: str
) -> tuple[dict, list[dict]]:
    """Per arm its seeds' ``scores`` (under the key ``score``), how many exceed ``THRESHOLD`` (under ``count``),
    the rate with its 95% Clopper-Pearson interval, its ``frames`` and ``logs``; Fisher's two-sided test for every
    pair of arms."""
    arms = {}
    for name, values in scores.items():
        up = values > THRESHOLD
        ci = scipy.stats.binomtest(int(up.sum()), len(up)).proportion_ci(0.95, method="exact")
        arms[name] = {
            "seeds": len(up),
            count: int(up.sum()),
            "rate": float(up.mean()),
            "rate_ci": [round(float(ci.low), 3), round(float(ci.high), 3)],
            score: [round(float(v), 1) for v in values],
            "frames": frames[name][0] if len(frames[name]) == 1 else frames[name],
            "log": logs[name],
        }
    tests = []
    for a, b in itertools.combinations(arms, 2):
        table = [[arms[x][count], arms[x]["seeds"] - arms[x][count]] for x in (a, b)]
        tests.append({"arms": [a, b], "table": table, "fisher_p": float(scipy.stats.fisher_exact(table)[1])})
    return arms, tests


def summary(curves: dict[str, Curve], logs: dict[str, list[str]]) -> dict:
    """Per arm of ``curves`` (:func:`arm_curves`' and any reference's, e.g. DrQ-v2's own curves in ``main``) its
    seeds' late means, take-offs, rate and interval, and its ``logs``; Fisher's test for every pair of arms."""
    means = {name: took_off(frames, returns)[0] for name, (frames, returns) in curves.items()}
    last = {name: [int(frames[-1])] for name, (frames, _) in curves.items()}
    arms, tests = tally(means, last, logs, "took_off", "late_means")
    return {"threshold": THRESHOLD, "from_frames": FROM_FRAMES, "arms": arms, "fisher": tests}


def full_length(run_dirs: list[pathlib.Path], reference: dict[str, tuple[np.ndarray, int, str]]) -> dict:
    """Per arm of ``run_dirs`` (named by config) and of ``reference`` (``{name: (final returns, frames, log)}``)
    its seeds' final returns (``analysis.final_returns`` of each run, pooled by seed), how many walk, the rate and
    interval, the frames of its runs' last evaluations and its logs; Fisher's test for every pair of arms."""
    scores: dict[str, list] = {}
    frames: dict[str, list[int]] = {}
    logs: dict[str, list[str]] = {}
    for run_dir in run_dirs:
        cfg = run_config(run_dir)
        steps, returns = load_runs(run_dir)
        name = arm(cfg)
        scores.setdefault(name, []).extend(final_returns(returns))
        last = int(steps[-1]) * action_repeat(cfg["env"]["task"])
        seen = frames.setdefault(name, [])
        if last not in seen:
            seen.append(last)
        logs.setdefault(name, []).append(log_name(run_dir, RESULTS))
    for name, (values, at, log) in reference.items():
        scores[name], frames[name], logs[name] = list(values), [at], [log]
    arms, tests = tally({k: np.asarray(v) for k, v in scores.items()}, frames, logs, "walked", "final_returns")
    return {"threshold": THRESHOLD, "arms": arms, "fisher": tests}


def main() -> None:
    if not RUNS:
        print("no take-off runs listed in RUNS yet (experiments/README.md: the take-off test)")
        return
    curves, logs = arm_curves([RESULTS / "runs" / d for d in RUNS])
    reference = {DRQV2: (DRQV2_FRAMES, DRQV2_RETURNS)}
    out = summary(curves | reference, logs | {DRQV2: ["facebookresearch/drqv2 curves/dmc_walker_walk.csv (d6dbadc)"]})
    csv = "facebookresearch/drqv2 curves/dmc_walker_walk.csv (c0c650b)"
    out["full_length"] = full_length([RESULTS / "runs" / d for d in FULL_RUNS], {DRQV2: (DRQV2_FINAL, 500_000, csv)})
    (RESULTS / "drqv2_takeoff.json").write_text(json.dumps(out, indent=1) + "\n")
    title = f"DrQ-v2 walker_walk pixels: take-off (mean from {FROM_FRAMES // 1000}k frames > {THRESHOLD:g})"
    xlabel = "frames (agent steps x action repeat)"
    curve_figure(curves, RESULTS / "drqv2_takeoff.png", title, xlabel=xlabel, seeds=True)
    print("| arm | seeds | took off | rate [95% CI] | late means |")
    print("|---|---:|---:|---:|---|")
    for name, a in out["arms"].items():
        print(f"| {name} | {a['seeds']} | {a['took_off']} | {a['rate']:.2f} {a['rate_ci']} | {a['late_means']} |")
    for t in out["fisher"]:
        print(f"Fisher's exact test, {t['arms'][0]} against {t['arms'][1]}: p = {t['fisher_p']:.3f}")
    full = out["full_length"]
    print(f"\nAt full length (final return > {THRESHOLD:g}):\n| arm | seeds | walked | rate [95% CI] | final returns |")
    print("|---|---:|---:|---:|---|")
    for name, a in full["arms"].items():
        print(f"| {name} | {a['seeds']} | {a['walked']} | {a['rate']:.2f} {a['rate_ci']} | {a['final_returns']} |")
    for t in full["fisher"]:
        print(f"Fisher's exact test, {t['arms'][0]} against {t['arms'][1]}: p = {t['fisher_p']:.3f}")


if __name__ == "__main__":
    main()
