"""The faithful-baseline table (B-Pref's protocol) from the runs' logs: ``results/baselines.json``.

Usage:
  python experiments/baselines.py     # writes results/baselines.json, results/baselines_<task>.png
                                      # and prints a Markdown table

Every setting in a row is read from that run's ``config.json`` and ``meta.json``; returns are read
from its ``metrics.jsonl`` (per seed, the evaluation return logged at a step) or ``final.json``.
A run that stopped before its ``total_steps`` (stopped early, e.g. by a time limit) says so in ``complete``.
"""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
from analysis import _per_seed, _records, bootstrap_ci, iqm, sample_std

from rebel_jax.run.plots import load_runs, plot_curves

ROOT = pathlib.Path(__file__).parents[1]
RESULTS = ROOT / "results"
STEPS = (100_000, 190_000, 200_000, 270_000, 300_000, 330_000, 500_000, 750_000, 790_000, 1_000_000)
"""Steps at which every run's return is reported (where the run got that far)."""

# (log directory under results/runs, the columns of a grid run that are this method, published
# mean at the run's total steps, rung name). Published: PEBBLE and SURF at 500k (walker) from the
# SURF paper's walker_walk table at 100 labels (Park et al., ICLR 2022).
RUNS = [
    (
        "paper/rebel_walker_100_neg",
        "lam=0",
        453,
        "0: earlier protocol (uniform, lecun init, rows pool, 40 envs, utd 0.25)",
    ),
    (
        "baselines/pebble_walker_100",
        None,
        453,
        "3: + disagreement, torch init, complete-episode pool (10 envs), reset update",
    ),
    (
        "baselines/pebble_walker_100_utd1_stopped270k",
        None,
        453,
        "4 (first try, stopped at 270k): + utd 1 (B-Pref's)",
    ),
    ("baselines/pebble_walker_100_utd1", None, 453, "4: + utd 1 (B-Pref's)"),
    ("baselines/surf_walker_100", None, 661, "SURF on rung 3 (utd 0.3)"),
    ("baselines/surf_walker_100_utd1", None, 661, "SURF on rung 4 (utd 1)"),
    ("baselines/pebble_walker_100_utd1_bf16_seed1", None, 453, "4 in bf16, five new seeds (--seed 1)"),
    ("baselines/surf_walker_100_utd1_bf16", None, 661, "SURF on rung 4 in bf16 (same seeds)"),
    ("baselines/pebble_walker_1000_bf16", None, None, "PEBBLE, 1,000 labels, rung 4 in bf16"),
    ("baselines/sac_cheetah_fixed", None, None, "SAC, cheetah_run, fixed reset"),
    ("baselines/pebble_cheetah_100_1m_bf16", None, 546, "PEBBLE, cheetah_run, 1M (bf16)"),
    ("baselines/surf_cheetah_100_1m_bf16_stopped270k", None, 557, "SURF, cheetah_run (bf16), stopped at 270k"),
    ("baselines/surf_cheetah_100_1m_bf16", None, 557, "SURF, cheetah_run, 1M (bf16)"),
    (
        "baselines/surf_cheetah_100_1m_bf16_ru100_stopped790k",
        None,
        557,
        "SURF, cheetah_run, reward_update 100 (bf16), stopped at 790k",
    ),
    ("baselines/surf_cheetah_100_1m_bf16_ru100", None, 557, "SURF, cheetah_run, reward_update 100, 1M (bf16)"),
]


def _columns(meta: dict, select: str | None) -> list[int]:
    if select is None:
        return list(range(meta["columns"]))
    lam = float(select.split("=")[1])
    return [i for i, value in enumerate(meta["lams"]) if value == lam]


def _at_steps(run: pathlib.Path, columns: list[int]) -> dict[int, list[float]]:
    """Per seed, the evaluation return logged at each step of ``STEPS`` the run reached."""
    out = {}
    for record in _records(run):
        if record["env_steps"] in STEPS and record.get("eval_return") is not None:
            values = _per_seed(record["eval_return"])
            out[record["env_steps"]] = [values[i] for i in columns]
    return out


def diagnostics(run: pathlib.Path, columns: list[int]) -> dict:
    """What a curve did besides its end, from ``metrics.jsonl``: the best in-batch evaluation mean and its
    step, the mean Q and critic loss over the last 10 rounds, and each seed's last learned-vs-true
    segment-return correlation (``reward_correlation_return``, logged at sessions).

    Over the last 10 rounds also the learned reward that the critic implies, ``q * (1 - gamma) - gamma *
    alpha * entropy`` (the soft Bellman fixed point with a constant reward; an estimate for runs that
    predate the per-round metrics), and where logged the per-round ``round_learned_mean`` and
    ``round_learned_saturated`` on the policy's own transitions (``train.ROUND_REWARD_METRICS``)."""
    records = _records(run)

    def series(key: str) -> list[tuple[int, list[float]]]:
        out = []
        for r in records:
            if r.get(key) is not None:
                values = [_per_seed(r[key])[i] for i in columns]
                if all(v is not None and math.isfinite(v) for v in values):
                    out.append((r["env_steps"], values))
        return out

    evals = series("eval_return")
    best_step, best = max(((s, float(np.mean(v))) for s, v in evals), key=lambda sv: sv[1])
    last = lambda key: round(float(np.mean([v for _, values in series(key)[-10:] for v in values])), 3)  # noqa: E731
    correlations = series("reward_correlation_return")
    gamma = json.loads((run / "config.json").read_text())["sac"]["gamma"]
    q, alpha, entropy = (np.asarray([v for _, v in series(k)[-10:]]) for k in ("q", "alpha", "entropy"))
    logged = lambda key: last(key) if series(key) else None  # noqa: E731
    return {
        "best_eval_mean": round(best, 1),
        "best_eval_step": best_step,
        "q_last10": last("q"),
        "critic_loss_last10": last("critic_loss"),
        "reward_correlation_return": [round(v, 2) for v in correlations[-1][1]] if correlations else None,
        "implied_reward_last10": round(float(np.mean(q * (1 - gamma) - gamma * alpha * entropy)), 3),
        "round_learned_mean_last10": logged("round_learned_mean"),
        "round_learned_saturated_last10": logged("round_learned_saturated"),
    }


def row(log: str, select: str | None, published: float | None, rung: str) -> dict:
    run = RESULTS / "runs" / log
    cfg = json.loads((run / "config.json").read_text())
    meta = json.loads((run / "meta.json").read_text())
    records = _records(run)
    columns = _columns(meta, select)
    last = records[-1]["env_steps"]
    final = run / "final.json"
    if final.exists():
        values = json.loads(final.read_text())["final_eval_return"]
        returns, source = [values[i] for i in columns], "final.json (frozen policy, 10 episodes)"
    else:
        values = _per_seed(next(r["eval_return"] for r in reversed(records) if r.get("eval_return") is not None))
        returns, source = [values[i] for i in columns], "last in-batch evaluation in metrics.jsonl"
    x = np.asarray(returns, float)
    ci = bootstrap_ci(x)
    return {
        "rung": rung,
        "task": cfg["env"]["task"],
        "algo": cfg["algo"] if select is None else f"pebble (rebel {select})",
        "labels": cfg["feedback"]["labels"] if cfg["algo"] != "sac" else None,
        "teacher": "oracle" if cfg["algo"] != "sac" else None,
        "sampling": cfg["query"]["sampling"] if cfg["algo"] != "sac" else None,
        "pool": cfg["query"].get("pool", "rows") if cfg["algo"] != "sac" else None,
        "reward_init": cfg["reward"].get("init", "lecun") if cfg["algo"] != "sac" else None,
        "reset_updates": cfg["pretrain"].get("reset_updates", 0) if cfg["algo"] != "sac" else None,
        "surf_reward_update": cfg["surf"]["reward_update"] if cfg["algo"] == "surf" else None,
        "num_envs": cfg["env"]["num_envs"],
        "utd": cfg["sac"]["utd"],
        "precision": cfg["sac"]["precision"],
        "seed": cfg["train"]["seed"],
        "seeds": len(columns),
        "env_steps": last,
        "total_steps": cfg["train"]["total_steps"],
        "complete": last >= cfg["train"]["total_steps"],
        "returns_source": source,
        "final_returns": [round(v, 2) for v in returns],
        "mean": round(float(x.mean()), 2),
        "std": round(sample_std(x), 2),
        "iqm": round(float(iqm(x)), 2),
        "iqm_ci": [round(v, 2) if math.isfinite(v) else None for v in ci],
        "returns_at": {str(s): round(float(np.mean(v)), 1) for s, v in _at_steps(run, columns).items()},
        "diagnostics": diagnostics(run, columns),
        "published": published,
        "device": ", ".join(meta["devices"]),
        "date": meta["started"][:10],
        "jax": meta["jax"],
        "command": meta["command"],
        "log": f"results/runs/{log}",
    }


POOLED = {  # rung name of a pooled row -> the rungs it pools
    "4, pooled: TF32 seeds (--seed 0) and bf16 seeds (--seed 1), 10 seeds": [
        "4: + utd 1 (B-Pref's)",
        "4 in bf16, five new seeds (--seed 1)",
    ],
}
"""Rows whose runs differ only in matmul precision and base seed (checked on their config.json)."""

_MAY_DIFFER = {("sac", "precision"), ("train", "seed")}


def _settings(log: str) -> dict:
    cfg = json.loads((RESULTS / "runs" / log / "config.json").read_text())
    return {(group, key): value for group, values in cfg.items() if isinstance(values, dict)
            for key, value in values.items()} | {("algo", ""): cfg["algo"]}  # fmt: skip


def pooled(rung: str, parts: list[dict]) -> dict:
    """One row of the seeds of ``parts``, after checking that their configs differ only in ``_MAY_DIFFER``."""
    logs = [p["log"].removeprefix("results/runs/") for p in parts]
    first = _settings(logs[0])
    for log in logs[1:]:
        other = _settings(log)
        # Settings added by later code (in one config only) are left out; every shared one must agree.
        differ = {k for k in first.keys() & other.keys() if first[k] != other[k]} - _MAY_DIFFER
        if differ:
            raise ValueError(f"cannot pool {logs[0]} and {log}: they differ in {sorted(differ)}")
    if not all(p["complete"] for p in parts):
        raise ValueError(f"cannot pool {logs}: not every run reached its total_steps")
    x = np.asarray([v for p in parts for v in p["final_returns"]], float)
    ci = bootstrap_ci(x)
    steps = set.intersection(*(set(p["returns_at"]) for p in parts))
    return parts[0] | {
        "rung": rung,
        "precision": sorted({p["precision"] for p in parts}),
        "seed": [p["seed"] for p in parts],
        "seeds": len(x),
        "final_returns": [round(v, 2) for v in x],
        "mean": round(float(x.mean()), 2),
        "std": round(sample_std(x), 2),
        "iqm": round(float(iqm(x)), 2),
        "iqm_ci": [round(v, 2) if math.isfinite(v) else None for v in ci],
        "returns_at": {  # seed-weighted mean of the parts' means
            s: round(sum(p["returns_at"][s] * p["seeds"] for p in parts) / len(x), 1) for s in sorted(steps, key=int)
        },
        "device": sorted({p["device"] for p in parts}),
        "date": sorted({p["date"] for p in parts}),
        "jax": sorted({p["jax"] for p in parts}),
        "command": [p["command"] for p in parts],
        "log": [p["log"] for p in parts],
    }


FIGURES = {  # task -> (rung name in RUNS -> legend label), for results/baselines_<task>.png
    "walker_walk": {
        "0: earlier protocol (uniform, lecun init, rows pool, 40 envs, utd 0.25)": "PEBBLE, rung 0 (earlier protocol)",
        "4: + utd 1 (B-Pref's)": "PEBBLE, rung 4 (B-Pref's protocol)",
        "4 in bf16, five new seeds (--seed 1)": "PEBBLE, rung 4, bf16, new seeds",
        "SURF on rung 4 (utd 1)": "PEBBLE+SURF, rung 4",
        "SURF on rung 4 in bf16 (same seeds)": "PEBBLE+SURF, rung 4, bf16",
    },
    "cheetah_run": {
        "SAC, cheetah_run, fixed reset": "SAC, true reward (40 envs, utd 0.25)",
        "PEBBLE, cheetah_run, 1M (bf16)": "PEBBLE (B-Pref's protocol, bf16)",
        "SURF, cheetah_run, 1M (bf16)": "PEBBLE+SURF (B-Pref's protocol, bf16)",
        "SURF, cheetah_run, reward_update 100, 1M (bf16)": "PEBBLE+SURF, reward_update 100",
    },
}
PUBLISHED = {  # task -> (name -> (published mean, its step))
    "walker_walk": {"PEBBLE": (453, 500_000), "PEBBLE+SURF": (661, 500_000)},
    "cheetah_run": {"PEBBLE": (546, 1_000_000), "PEBBLE+SURF": (557, 1_000_000)},
}
"""The published means at 100 labels: walker_walk at 500k from the SURF paper's table (Park et al., ICLR 2022),
cheetah_run at 1M (the re-run of the authors' code that RESULTS.md quotes)."""


def figure(task: str, path: pathlib.Path) -> None:
    """Mean +- std over seeds of ``task``'s runs in ``FIGURES``, with the published means."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    curves = {}
    for log, select, _, rung in RUNS:
        if rung in FIGURES[task]:
            steps, returns = load_runs(RESULTS / "runs" / log)
            columns = _columns(json.loads((RESULTS / "runs" / log / "meta.json").read_text()), select)
            curves[FIGURES[task][rung]] = (steps, returns[:, columns])
    fig, ax = plt.subplots(figsize=(7, 4.5))
    plot_curves(ax, curves)
    for i, (name, (value, step)) in enumerate(PUBLISHED[task].items()):
        label = f"{name} published ({step // 1000}k)"
        ax.scatter([step], [value], marker="*", s=120, color=f"C{i + len(curves)}", label=label, zorder=3)
    ax.legend(fontsize=8)
    ax.set_title(f"{task}, 100 labels, oracle teacher")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    rows = [row(*spec) for spec in RUNS]
    by_rung = {r["rung"]: r for r in rows}
    rows += [pooled(rung, [by_rung[p] for p in parts]) for rung, parts in POOLED.items()]
    (RESULTS / "baselines.json").write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    for task in FIGURES:
        figure(task, RESULTS / f"baselines_{task}.png")
    print("| rung | env steps run | " + " | ".join(f"{s // 1000}k" for s in STEPS) + " | last eval, mean +- std |")
    print("|---|---:|" + "---:|" * len(STEPS) + "---:|")
    for r in rows:
        at = " | ".join(str(r["returns_at"].get(str(s), "")) for s in STEPS)
        print(f"| {r['rung']} | {r['env_steps'] // 1000}k | {at} | {r['mean']:.1f} +- {r['std']:.1f} |")


if __name__ == "__main__":
    main()
