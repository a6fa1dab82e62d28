"""Learning curves and JSON summaries from finished runs (``python -m rebel_jax.train``).

Usage:
  python experiments/curves.py RUN_DIR [RUN_DIR ...] [--labels A B ...] --name NAME

Writes ``results/NAME.json`` (task, algo, preset, seeds, env_steps, final_returns = per
seed the mean of the last 10 evaluations, mean, std, curve, device, date, command) per run
and ``results/NAME.png`` with mean +- std of the evaluation return of every run.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

RESULTS = pathlib.Path(__file__).parents[1] / "results"


def summarize(run_dir: pathlib.Path) -> dict:
    """The schema of RESULTS.md from one run directory."""
    cfg = json.loads((run_dir / "config.json").read_text())
    meta = json.loads((run_dir / "meta.json").read_text())
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    evals = [r for r in records if r.get("eval_return") is not None and None not in r["eval_return"]]
    steps = [r["env_steps"] for r in evals]
    returns = np.array([r["eval_return"] for r in evals])  # (evaluations, seeds)
    final = returns[-10:].mean(axis=0)
    return {
        "task": cfg["env"]["task"],
        "algo": cfg["algo"],
        "preset": "paper",
        "seeds": meta["seeds"],
        "env_steps": records[-1]["env_steps"],
        "num_envs": cfg["env"]["num_envs"],
        "utd": cfg["sac"]["utd"],
        "final_returns": final.tolist(),
        "mean": float(final.mean()),
        "std": float(final.std()),
        "curve": {"env_steps": steps, "mean": returns.mean(axis=1).tolist(), "std": returns.std(axis=1).tolist()},
        "evaluation": "in-batch deterministic episodes (see rebel_jax.train), 10 per seed per 1000-step episode",
        "device": meta["devices"][0],
        "date": meta["started"][:10],
        "command": meta["command"],
    }


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dirs", nargs="+", type=pathlib.Path)
    p.add_argument("--labels", nargs="*")
    p.add_argument("--name", required=True)
    args = p.parse_args()
    labels = args.labels or [d.name for d in args.run_dirs]
    summaries = [summarize(d) for d in args.run_dirs]
    out = summaries[0] if len(summaries) == 1 else {"runs": dict(zip(labels, summaries, strict=True))}
    (RESULTS / f"{args.name}.json").write_text(json.dumps(out, indent=1))
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, s in zip(labels, summaries, strict=True):
        x, m, sd = (np.array(s["curve"][k]) for k in ("env_steps", "mean", "std"))
        ax.plot(x, m, label=f"{label} ({s['seeds']} seeds)")
        ax.fill_between(x, m - sd, m + sd, alpha=0.25)
    ax.set_xlabel("environment steps")
    ax.set_ylabel("evaluation return (true reward)")
    ax.set_title(args.name)
    ax.legend()
    fig.tight_layout()
    fig.savefig(RESULTS / f"{args.name}.png", dpi=120)
    for label, s in zip(labels, summaries, strict=True):
        print(f"{label}: {s['mean']:.1f} +- {s['std']:.1f} over {s['seeds']} seeds at {s['env_steps']} steps")


if __name__ == "__main__":
    main()
