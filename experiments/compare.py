"""The paper's comparison figure from finished runs: curves, IQM with bootstrap intervals, sample efficiency.

Usage:
  python experiments/compare.py RUN_DIR [RUN_DIR ...] --name NAME [--reference LABEL] [--out-dir DIR]

Each run directory (``python -m rebel_jax.train``) contributes one method per lambda: a REBEL
run with ``--lam-grid`` is split into its lambdas (``rebel lam=-0.1``; lambda 0 is labelled
``pebble (rebel lam=0)``, which it equals bit for bit), other runs are labelled by their algo.
Run directories of the same method (e.g. seeds split over several GPU calls with different
``--seed``) are merged. Writes ``DIR/NAME.json`` (per method: final returns per seed, mean,
std, IQM with its 95% percentile-bootstrap interval, mean curve, and the sample-efficiency
ratio against ``--reference``: env steps the other method needs to reach a common return over
the steps the reference needs) and ``DIR/NAME.png`` (mean +- std curves and IQM bars), and
prints a Markdown table for RESULTS.md.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from analysis import (  # noqa: E402
    bootstrap_ci,
    common_threshold,
    distinct_evaluations,
    final_returns,
    iqm,
    load_runs,
    merge_runs,
    plot_curves,
    plot_iqm,
    sample_efficiency_ratio,
)

RESULTS = pathlib.Path(__file__).parents[1] / "results"


def methods(run_dir: pathlib.Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """The run's curves per method label: ``{label: (steps, returns (evals, seeds))}``.

    A grid run (``--lam-grid``, ``--teacher-grid``) is split into one label per grid point.
    """
    cfg = json.loads((run_dir / "config.json").read_text())
    meta = json.loads((run_dir / "meta.json").read_text())
    steps, returns = load_runs(run_dir)
    columns = returns.shape[1]
    lams = meta.get("lams") or [None] * columns
    teachers = meta.get("teachers") or [None] * columns
    out: dict[str, list[int]] = {}
    for i, (lam, teacher) in enumerate(zip(lams, teachers, strict=True)):
        if lam is None:
            label = cfg["algo"]
        else:
            label = "pebble (rebel lam=0)" if lam == 0 else f"rebel lam={lam:g}"
        out.setdefault(label + (f", {teacher}" if teacher else ""), []).append(i)
    return {label: (steps, returns[:, idx]) for label, idx in out.items()}


def gather(run_dirs: list[pathlib.Path]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Every method's curve, the seeds of run directories with the same label merged."""
    parts: dict[str, list] = {}
    for run_dir in run_dirs:
        for label, curve in methods(run_dir).items():
            parts.setdefault(label, []).append(curve)
    return {label: merge_runs(*runs) for label, runs in parts.items()}


def compare(curves: dict[str, tuple[np.ndarray, np.ndarray]], reference: str | None) -> dict:
    """Per-method statistics (see the module docstring) of ``gather``'s curves."""
    finals = {label: final_returns(returns) for label, (_, returns) in curves.items()}
    threshold = common_threshold(np.nanmean(f) for f in finals.values())
    reference = reference or next(iter(curves))
    out = {"threshold": threshold, "reference": reference, "methods": {}}
    for label, (steps, returns) in curves.items():
        scores = finals[label][np.isfinite(finals[label])]
        mean_curve = (steps, np.nanmean(returns, axis=1))
        ref_steps, ref_returns = curves[reference]
        ratio = sample_efficiency_ratio(
            distinct_evaluations((ref_steps, np.nanmean(ref_returns, axis=1)[:, None])),
            distinct_evaluations((mean_curve[0], mean_curve[1][:, None])),
            threshold,
        )
        out["methods"][label] = {
            "seeds": int(returns.shape[1]),
            "env_steps": int(steps[-1]),
            "final_returns": scores.tolist(),
            "mean": float(scores.mean()),
            "std": float(scores.std()),
            "iqm": float(iqm(scores)),
            "iqm_ci": list(bootstrap_ci(scores, iqm)),
            "steps_ratio_vs_reference": ratio,
            "curve": {"env_steps": steps.tolist(), "mean": mean_curve[1].tolist()},
        }
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dirs", nargs="+", type=pathlib.Path)
    p.add_argument("--name", required=True)
    p.add_argument("--reference", help="method label the sample-efficiency ratios are relative to (default: first)")
    p.add_argument("--out-dir", type=pathlib.Path, default=RESULTS)
    args = p.parse_args()
    curves = gather(args.run_dirs)
    result = compare(curves, args.reference)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    plot_curves(left, curves)
    plot_iqm(right, {label: m["final_returns"] for label, m in result["methods"].items()})
    left.set_title(args.name)
    fig.tight_layout()
    fig.savefig(args.out_dir / f"{args.name}.png", dpi=120)
    ratio = f"steps to {result['threshold']:.0f} / those of {result['reference']}"
    print(f"| method | seeds | env steps | final mean +- std | IQM [95% CI] | {ratio} |")
    print("|---|---:|---:|---:|---:|---:|")
    for label, m in result["methods"].items():
        low, high = m["iqm_ci"]
        print(
            f"| {label} | {m['seeds']} | {m['env_steps']:,} | {m['mean']:.1f} +- {m['std']:.1f} "
            f"| {m['iqm']:.1f} [{low:.1f}, {high:.1f}] | {m['steps_ratio_vs_reference']:.2f} |"
        )


if __name__ == "__main__":
    main()
