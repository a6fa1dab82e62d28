"""``results/quadruped.json``: SAC and PEBBLE on quadruped_walk against their published figures.

Usage:
  python experiments/quadruped.py

The runs of ``RUNS`` (``--preset paper_quadruped``, 1M steps; PEBBLE with 1,000 labels and the oracle). Per
method: the final returns (per seed the mean of its last 10 evaluations) with mean, std and IQM and its 95%
bootstrap interval (:func:`compare.compare`); the end-of-run evaluation's mean +- std over seeds
(:func:`qpa_rune.end_of_run`, with its IQM), the number the published figures give; the published figure
(``PUBLISHED``) and the target: SAC at 90% of its published mean or more, PEBBLE within one published std of its
published mean.
Also writes ``results/quadruped_walk.png``: each method's mean +- std curve over seeds.
"""

from __future__ import annotations

import json

import numpy as np
from analysis import bootstrap_ci, curve_figure, iqm
from compare import compare, gather, methods
from qpa_rune import end_of_run, end_of_run_returns
from rebel import RESULTS

RUNS = ["quadruped/sac_quadruped_walk_1m_bf16", "quadruped/pebble_quadruped_walk_1000_1m_bf16"]
"""Run directories under results/runs."""
PUBLISHED = {
    # State SAC at B-Pref's settings (1024x2, batch 1024, lr 1e-4), 1M steps: pytorch_sac's logged runs 39-41,
    # the last evaluation of each (denisyarats/pytorch_sac@3ecf5008abc6ee6bddb2ee4d02e099e57511c458:data/sac.csv).
    "sac": {"mean": 502.5, "std": 349.7, "source": "pytorch_sac data/sac.csv, runs 39-41", "target": "90% of mean"},
    # Zhu, Liu, Gu et al., "Improving Reward Models with Proximal Policy Exploration for Preference-Based
    # Reinforcement Learning", Table 1 (PEBBLE's official code, 1,000 labels, 1M steps, 5 seeds).
    "pebble 1000 labels": {"mean": 364.46, "std": 138.98, "source": "PPE paper, Table 1", "target": "one std"},
}


def met(published: dict, value: float) -> bool:
    """Whether ``value`` meets ``published``'s target."""
    if published["target"] == "90% of mean":
        return value >= 0.9 * published["mean"]
    return abs(value - published["mean"]) <= published["std"]


def main() -> None:
    run_dirs = [RESULTS / "runs" / log for log in RUNS]
    curves, infos = gather(run_dirs)
    stats = compare(curves, "sac")
    curve_figure(curves, RESULTS / "quadruped_walk.png", "quadruped_walk, 1M steps (PEBBLE: 1,000 labels, oracle)")
    table = []
    for label, m in stats["methods"].items():
        dirs = infos[label]["run_dirs"]
        columns = [methods(d)[label][1]["columns"] for d in dirs]
        end = end_of_run(dirs, columns)
        values = np.array(end_of_run_returns(dirs, columns))
        end |= {"iqm": round(float(iqm(values)), 1), "iqm_ci": [round(float(x), 1) for x in bootstrap_ci(values, iqm)]}
        published = PUBLISHED[label]
        info = {k: v for k, v in infos[label].items() if k != "run_dirs"}
        table.append(
            {"method": label, **{k: v for k, v in m.items() if k != "curve"}, "end_of_run": end}
            | {"published": published, "target_met": met(published, end["mean"]), **info}
        )
    (RESULTS / "quadruped.json").write_text(json.dumps({"rows": table}, indent=1) + "\n")
    print("| method | seeds | IQM [95% CI] | final mean +- std | end of run, mean +- std | published | target |")
    print("|---|---:|---:|---:|---:|---:|---|")
    for r in table:
        e, p = r["end_of_run"], r["published"]
        low, high = r["iqm_ci"]
        target = f"{p['target']}: {'met' if r['target_met'] else 'missed'}"
        print(
            f"| {r['method']} | {r['seeds']} | {r['iqm']:.1f} [{low:.1f}, {high:.1f}] | {r['mean']:.1f} +- "
            f"{r['std']:.1f} | {e['mean']:.1f} +- {e['std']:.1f} | {p['mean']:.1f} +- {p['std']:.1f} | {target} |"
        )


if __name__ == "__main__":
    main()
