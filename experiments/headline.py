"""``results/headline.json``: PEBBLE on walker_walk at the ``paper`` preset, 10 seeds, and the running std's effect.

Usage:
  python experiments/headline.py      # writes results/headline.json, results/headline_walker_walk.png

Two questions, from the run directories in ``RUNS``:

- ``pebble``: the README's PEBBLE walker_walk row (100 labels, the oracle, 500k steps, bf16): both final-return
  measures (:func:`analysis.measured`) beside the published 453.43 +- 159.43 (Zhu, Liu, Gu et al., Table 1, the
  authors' code at 100 labels and 500k steps).
- ``running_std``: ``--pretrain.running-std exact`` minus ``bpref`` (the preset's, B-Pref's form), paired by PRNG
  key over the seeds both runs have (:func:`analysis.paired_difference`), by both measures.
"""

from __future__ import annotations

import json
import pathlib

from analysis import curve_figure, keyed_run, load_runs, measured, paired_difference

RESULTS = pathlib.Path(__file__).parents[1] / "results"
RUNS = {
    "bpref": "headline/pebble_walker_100_bf16_10seeds",
    "exact": "headline/pebble_walker_100_bf16_exact",
}
PUBLISHED = {"mean": 453.43, "std": 159.43}


def main() -> None:
    runs = {name: keyed_run(RESULTS / "runs" / log) for name, log in RUNS.items()}
    for name, log in RUNS.items():
        cfg = json.loads((RESULTS / "runs" / log / "config.json").read_text())
        if cfg["pretrain"]["running_std"] != name:
            raise ValueError(f"{log}: running_std {cfg['pretrain']['running_std']!r}, not {name!r}")
    bpref = runs["bpref"]
    table = {
        "pebble": {
            "log": f"results/runs/{RUNS['bpref']}",
            "end_of_run": measured(bpref["end_of_run"]),
            "last10": measured(bpref["last10"]),
            "published": PUBLISHED,
        }
        | {k: bpref[k] for k in ("device", "date", "jax", "commit", "command")},
        "running_std": {
            "exact_minus_bpref": [paired_difference(runs["exact"], bpref, m) for m in ("end_of_run", "last10")],
            "runs": {name: {"log": f"results/runs/{RUNS[name]}"} | run for name, run in runs.items()},
        },
    }
    (RESULTS / "headline.json").write_text(json.dumps(table, indent=1) + "\n")
    curves = {f"PEBBLE, running std {name}": load_runs(RESULTS / "runs" / log) for name, log in RUNS.items()}
    curve_figure(curves, RESULTS / "headline_walker_walk.png", "PEBBLE, walker_walk, 100 labels, oracle teacher")
    e, l10 = table["pebble"]["end_of_run"], table["pebble"]["last10"]
    print(
        f"PEBBLE walker_walk, {e['seeds']} seeds: end of run {e['mean']:.1f} +- {e['std']:.1f}, last 10 evaluations "
        f"{l10['mean']:.1f} +- {l10['std']:.1f}, IQM {l10['iqm']:.1f} {l10['iqm_ci']}; published 453 +- 159"
    )
    for d in table["running_std"]["exact_minus_bpref"]:
        print(
            f"exact minus bpref ({d['measure']}, {len(d['keys'])} keys): {d['mean']:.1f} {d['mean_ci']}, "
            f"{d['positive']} of {d['pairs']} positive (sign test p {d['sign_test_p']})"
        )


if __name__ == "__main__":
    main()
