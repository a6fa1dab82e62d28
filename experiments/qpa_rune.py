"""``results/qpa_rune.json``: QPA and RUNE beside SAC, PEBBLE, PEBBLE+SURF and REBEL on B-Pref's protocol.

Usage:
  python experiments/qpa_rune.py

Six methods on two tasks (``RUNS``: walker_walk at 500k steps, cheetah_run at 1M, 100 labels, the oracle, 5 seeds
or more each). The rows are :func:`rebel.rows`: final returns (per seed the mean of its last 10 evaluations), the
IQM with its 95% bootstrap interval, the env steps to the baselines' threshold (80% of the lowest final mean of
SAC, PEBBLE and PEBBLE+SURF: QPA's and RUNE's rows do not move it) and the sample-efficiency ratio against PEBBLE.
Each row adds:

- ``end_of_run``: the mean and std over seeds of the end-of-run evaluation (``final.json``), the number the
  published figures report;
- ``published``: QPA's, RUNE's, PEBBLE's and SURF's figures in ``PUBLISHED``;
- ``paired``: the method against PEBBLE seed by seed, over the seeds whose key (``train.seed``, seed index) both
  have: the final-return differences, how many are positive, and the sign test's p.

Also writes ``results/qpa_rune_<task>.png``: each method's mean +- std curve over seeds.
"""

from __future__ import annotations

import json
import pathlib

import numpy as np
from analysis import curve_figure, final_returns, sample_std, sign_counted
from compare import gather, methods
from rebel import PEBBLE, RESULTS, rows

RUNS = {  # task -> run directories under results/runs
    "walker_walk": [
        "sac_walker_walk",
        "baselines/pebble_walker_100_utd1",
        "baselines/pebble_walker_100_utd1_bf16_seed1",
        "baselines/surf_walker_100_utd1_bf16",
        "rebel/rebel_walker_100_lams_0.001_-0.001_bf16",
        "qpa_rune/qpa_walker_100_500k_bf16",
        "qpa_rune/rune_walker_100_500k_bf16",
    ],
    "cheetah_run": [
        "baselines/sac_cheetah_fixed",
        "baselines/pebble_cheetah_100_1m_bf16",
        "baselines/surf_cheetah_100_1m_bf16_ru100",
        "rebel/rebel_cheetah_100_1m_lam0.001_bf16",
        "qpa_rune/qpa_cheetah_100_1m_bf16",
        "qpa_rune/rune_cheetah_100_1m_bf16",
    ],
}
KEEP = ("sac", "pebble", "surf", "surf (reward_update 100)", "rebel lam=0.001", "qpa", "rune")
"""The method labels that are rows (REBEL at the lambda chosen on walker_walk; SURF as it met its figure)."""
PUBLISHED = {
    # Zhu, Liu, Gu et al., "Improving Reward Models with Proximal Policy Exploration for Preference-Based
    # Reinforcement Learning", Table 1: their runs of each method's official code at QPA's budgets (walker_walk
    # 100 labels 500k steps, cheetah_run 100 labels 1M), 5 seeds, mean +- std of the final 10 evaluation episodes
    # pooled over seeds. QPA's own paper is not quoted; RUNE's paper reports Meta-World only.
    ("walker_walk", "pebble"): (453.43, 159.43),
    ("walker_walk", "surf"): (661.01, 91.72),
    ("walker_walk", "rune"): (414.62, 182.16),
    ("walker_walk", "qpa"): (796.08, 147.94),
    ("cheetah_run", "pebble"): (545.77, 130.00),
    ("cheetah_run", "surf"): (556.78, 59.323),
    ("cheetah_run", "rune"): (508.60, 186.06),
    ("cheetah_run", "qpa"): (578.89, 133.14),
}


def end_of_run_returns(run_dirs: list[pathlib.Path], columns: list[list[int]]) -> list[float]:
    """The end-of-run evaluation (``final.json``'s ``final_eval_return``) of the given columns of each run, pooled."""
    return [
        json.loads((d / "final.json").read_text())["final_eval_return"][i]
        for d, cols in zip(run_dirs, columns, strict=True)
        for i in cols
    ]


def end_of_run(run_dirs: list[pathlib.Path], columns: list[list[int]]) -> dict:
    """Mean and std over the pooled seeds of the end-of-run evaluation (:func:`end_of_run_returns`)."""
    values = end_of_run_returns(run_dirs, columns)
    return {"mean": round(float(np.mean(values)), 2), "std": round(sample_std(values), 2), "seeds": len(values)}


def keyed_returns(run_dirs: list[pathlib.Path], label: str) -> dict[tuple[int, int], float]:
    """``{(train.seed, seed index): final return}`` of ``label``'s seeds in ``run_dirs`` (seed i's key is
    ``fold_in(PRNGKey(train.seed), i)`` in every program)."""
    out = {}
    for d in run_dirs:
        (_, returns), info = methods(d)[label]
        for i, r in enumerate(final_returns(returns)):
            out[(info["train_seed"], i)] = float(r)
    return out


def paired(mine: dict, pebble: dict) -> dict:
    """The method minus PEBBLE over the keys both have, with the sign test (:func:`analysis.sign_counted`)."""
    keys = sorted(set(mine) & set(pebble))
    return sign_counted({"keys": [list(k) for k in keys], "differences": [round(mine[k] - pebble[k], 2) for k in keys]})


def task_rows(task: str, logs: list[str]) -> list[dict]:
    """The task's rows of :data:`KEEP` with their end-of-run, published and paired entries; writes its figure."""
    run_dirs = [RESULTS / "runs" / log for log in logs]
    curves, infos = gather(run_dirs)
    kept = {label: curve for label, curve in curves.items() if label in KEEP}
    curve_figure(kept, RESULTS / f"qpa_rune_{task}.png", f"{task}, 100 labels, oracle teacher (B-Pref's protocol)")
    pebble_label = next(label for label in PEBBLE if label in curves)
    pebble = keyed_returns(infos[pebble_label]["run_dirs"], pebble_label)
    out = []
    for row in rows(task, run_dirs):
        if row["method"] not in KEEP:
            continue
        label = row["method"]
        dirs = infos[label]["run_dirs"]
        published = PUBLISHED.get((task, row["algo"]))
        out.append(
            row
            | {
                "end_of_run": end_of_run(dirs, [methods(d)[label][1]["columns"] for d in dirs]),
                "published": dict(zip(("mean", "std"), published, strict=True)) if published else None,
                "paired": None if label == pebble_label else paired(keyed_returns(dirs, label), pebble),
            }
        )
    return out


def main() -> None:
    table = [row for task, logs in RUNS.items() for row in task_rows(task, logs)]
    (RESULTS / "qpa_rune.json").write_text(json.dumps({"rows": table}, indent=1) + "\n")
    print(
        "| task | method | seeds | IQM [95% CI] | end of run, mean +- std | published, mean +- std "
        "| steps to threshold | vs PEBBLE [95% CI] | minus PEBBLE by key: mean (positive of pairs, p) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in table:
        e, p, pair = r["end_of_run"], r["published"], r["paired"]
        published = f"{p['mean']:.1f} +- {p['std']:.1f}" if p else "-"
        by_key = (
            f"{np.mean(pair['differences']):+.1f} ({pair['positive']} of {pair['pairs']}, p = {pair['sign_test_p']})"
            if pair and pair["pairs"]
            else "-"
        )
        print(
            f"| {r['task']} | {r['method']} | {r['seeds']} | {r['iqm']:.1f} [{r['iqm_ci'][0]}, {r['iqm_ci'][1]}] "
            f"| {e['mean']:.1f} +- {e['std']:.1f} | {published} | {r['steps_to_threshold']} ({r['threshold']:.0f}) "
            f"| {r['efficiency_vs_pebble']} [{r['efficiency_ci'][0]}, {r['efficiency_ci'][1]}] | {by_key} |"
        )


if __name__ == "__main__":
    main()
