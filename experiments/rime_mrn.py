"""``results/rime_mrn.json``: MRN and RIME, each against PEBBLE on the same keys and protocol.

Usage:
  python experiments/rime_mrn.py      # writes results/rime_mrn.json and one figure per protocol (FIGURES)

Each entry of ``RUNS`` pairs a method's run with the PEBBLE run of the same protocol (task, labels, teacher, steps,
precision: checked on their ``config.json``). Per entry: both final-return measures of each
(:func:`analysis.measured`) and the method minus PEBBLE paired by PRNG key (:func:`analysis.paired_difference`).
"""

from __future__ import annotations

import json
import pathlib

from analysis import curve_figure, keyed_run, load_runs, measured, paired_difference

RESULTS = pathlib.Path(__file__).parents[1] / "results"
RUNS = [  # (name, method run, PEBBLE run of the same protocol), under results/runs
    (
        "MRN, walker_walk, 100 labels, 500k",
        "rime_mrn/mrn_walker_100_500k_bf16",
        "headline/pebble_walker_100_bf16_10seeds",
    ),
    (
        "RIME, walker_walk, 1,000 labels, mistake teacher 0.3, 300k",
        "rime_mrn/rime_walker_mistake_300k_bf16",
        "rime_mrn/pebble_walker_mistake_300k_bf16",
    ),
]
FIGURES = {  # PEBBLE run -> (figure under results/, title)
    "headline/pebble_walker_100_bf16_10seeds": ("rime_mrn_walker_walk.png", "walker_walk, 100 labels, oracle teacher"),
    "rime_mrn/pebble_walker_mistake_300k_bf16": (
        "rime_walker_walk_mistake.png",
        "walker_walk, 1,000 labels, mistake teacher (eps 0.3)",
    ),
}
SAME = (("env", "task"), ("feedback", "labels"), ("teacher", None), ("train", "total_steps"), ("sac", "precision"))
"""The settings a method's run and its PEBBLE run must share."""


def _check_protocol(method_log: str, pebble_log: str) -> None:
    cfgs = [json.loads((RESULTS / "runs" / log / "config.json").read_text()) for log in (method_log, pebble_log)]
    for group, key in SAME:
        values = [c[group] if key is None else c[group][key] for c in cfgs]
        if values[0] != values[1]:
            raise ValueError(f"{method_log} and {pebble_log} differ in {group}{'.' + key if key else ''}: {values}")


def main() -> None:
    table, curves = [], {log: {} for log in FIGURES}
    for name, method_log, pebble_log in RUNS:
        _check_protocol(method_log, pebble_log)
        method, pebble = keyed_run(RESULTS / "runs" / method_log), keyed_run(RESULTS / "runs" / pebble_log)
        table.append(
            {
                "name": name,
                "method": {"log": f"results/runs/{method_log}"}
                | method
                | {m: measured(method[m]) for m in ("end_of_run", "last10")},
                "pebble": {"log": f"results/runs/{pebble_log}"}
                | {m: measured(pebble[m]) for m in ("end_of_run", "last10")},
                "minus_pebble": [paired_difference(method, pebble, m) for m in ("end_of_run", "last10")],
            }
        )
        curves[pebble_log][name.split(",")[0]] = load_runs(RESULTS / "runs" / method_log)
        curves[pebble_log].setdefault("PEBBLE", load_runs(RESULTS / "runs" / pebble_log))
    (RESULTS / "rime_mrn.json").write_text(json.dumps({"rows": table}, indent=1) + "\n")
    for pebble_log, (figure, title) in FIGURES.items():
        curve_figure(curves[pebble_log], RESULTS / figure, title)
    for row in table:
        m, p = row["method"]["end_of_run"], row["pebble"]["end_of_run"]
        print(
            f"{row['name']}: end of run {m['mean']:.1f} +- {m['std']:.1f} ({m['seeds']} seeds), "
            f"PEBBLE {p['mean']:.1f} +- {p['std']:.1f} ({p['seeds']} seeds)"
        )
        for d in row["minus_pebble"]:
            print(
                f"  minus PEBBLE ({d['measure']}, {len(d['keys'])} keys): {d['mean']:.1f} {d['mean_ci']}, "
                f"{d['positive']} of {d['pairs']} positive (sign test p {d['sign_test_p']}, signed rank p "
                f"{d['signed_rank_p']})"
            )


if __name__ == "__main__":
    main()
