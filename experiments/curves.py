"""Learning curves and JSON summaries from finished runs (``python -m rebel_jax.train``).

Usage:
  python experiments/curves.py RUN_DIR [RUN_DIR ...] [--labels A B ...] --name NAME [--caveat TEXT] [--out-dir DIR]

Writes ``DIR/NAME.json`` (``analysis.summary`` of each run: task, algo, preset, seeds,
env_steps, final_returns = per seed the mean of the last 10 evaluations, mean, std, iqm,
iqm_ci, curve, device, date, command) and ``DIR/NAME.png`` with mean +- std of the evaluation
return of every run; ``DIR`` defaults to ``results/``.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from analysis import load_runs, plot_curves, summary  # noqa: E402

RESULTS = pathlib.Path(__file__).parents[1] / "results"


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dirs", nargs="+", type=pathlib.Path)
    p.add_argument("--labels", nargs="*")
    p.add_argument("--name", required=True)
    p.add_argument("--out-dir", type=pathlib.Path, default=RESULTS)
    p.add_argument("--caveat", help="a warning stored with the numbers (e.g. a bug the runs had)")
    args = p.parse_args()
    labels = args.labels or [d.name for d in args.run_dirs]
    summaries = [summary(d) for d in args.run_dirs]
    out = summaries[0] if len(summaries) == 1 else {"runs": dict(zip(labels, summaries, strict=True))}
    if args.caveat:
        out = {"caveat": args.caveat, **out}
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / f"{args.name}.json").write_text(json.dumps(out, indent=1, allow_nan=False))
    fig, ax = plt.subplots(figsize=(6, 4))
    plot_curves(ax, {label: load_runs(d) for label, d in zip(labels, args.run_dirs, strict=True)})
    ax.set_title(args.name)
    fig.tight_layout()
    fig.savefig(args.out_dir / f"{args.name}.png", dpi=120)
    for label, s in zip(labels, summaries, strict=True):
        low, high = s["iqm_ci"]
        print(
            f"{label}: {s['mean']:.1f} +- {s['std']:.1f}, IQM {s['iqm']:.1f} [{low:.1f}, {high:.1f}]"
            f" over {s['seeds']} seeds at {s['env_steps']} steps"
        )


if __name__ == "__main__":
    main()
