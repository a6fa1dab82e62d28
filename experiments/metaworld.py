"""``results/metaworld.json``, ``results/metaworld_sac.png`` and ``results/metaworld_pbrl.png``: SAC on Meta-World's
true reward, and PEBBLE and QPA on an oracle teacher's labels, success rates.

Usage:
  python experiments/metaworld.py

The runs of ``RUNS`` (``--preset paper_metaworld`` or ``qpa_metaworld``, ``--impl warp``). Per run, read from its
logs: the settings (``config.json``), the device, date, JAX version, commit and commands (``meta.json``, with every
``--resume``), and from ``metrics.jsonl`` the rounds' evaluations (``train.eval_episodes`` episodes per seed every
10k steps, each episode's policy frozen at its start; an episode succeeds if any of its steps does, as B-Pref's
``evaluate`` counts, rll-research/BPref@f3ece2e:train_SAC.py:78) and the labels used: per seed the success rate at
the last evaluation and the mean of the last 10 evaluations, their mean and sample std over seeds, the return at the
last evaluation, and the first step at which every seed's success rate is 0.9 or more. ``final.json``'s separate
end-of-run evaluation is reported where ``FINAL_NOT_USED`` does not say why it cannot be.
The figures: each run's success rate, mean +- std over seeds with each seed's curve; SAC's in one, the preference
methods' in the other.
"""

from __future__ import annotations

import json

import numpy as np
from analysis import curve_figure, load_runs, sample_std
from rebel import RESULTS

RUNS = (
    ("SAC", "button-press", "metaworld/sac_button-press_stopped770k"),
    ("SAC", "drawer-open", "metaworld/sac_drawer-open_1m"),
    ("SAC", "sweep-into", "metaworld/sac_sweep-into_stopped745k"),
    ("PEBBLE", "button-press", "metaworld/pebble_button-press_stopped800k"),
    ("PEBBLE", "sweep-into", "metaworld/pebble_sweep-into_1m"),
    ("QPA", "drawer-open", "metaworld/qpa_drawer-open_stopped585k"),
)
"""Each run: (method, task, its directory under results/runs)."""
FINAL_NOT_USED = {
    "metaworld/sac_drawer-open_1m": (
        "its final evaluation ran the policy's and the random actions' episodes from one reset per episode, under "
        "Warp's step before the reset's drawer position followed the data's batch (fixed since; "
        "tests/test_envs_metaworld.py::test_warp_step_under_nested_vmap_equals_the_flat_batch): every seed's worlds "
        "but the first seed's stepped with another episode's drawer"
    ),
}
"""Runs whose ``final.json`` is not a valid measurement, and why."""
LAST = 10
"""Evaluations averaged for the ``last10`` measure."""


def settings(cfg: dict, meta: dict) -> dict:
    """What a reader needs to know of a run's configuration, read from its ``config.json`` and ``meta.json``."""
    sac, train, env = cfg["sac"], cfg["train"], cfg["env"]
    labels = {}
    if cfg["algo"] != "sac":
        feedback, reward = cfg["feedback"], cfg["reward"]
        labels = {
            "labels": feedback["labels"],
            "labels_per_session": feedback["per_session"],
            "session_interval": feedback["interval"],
            "reward_max_epochs": reward["max_epochs"],
            "reward_ensemble": reward["ensemble_size"],
        }
        if cfg["algo"] == "qpa":
            labels["qpa_reward_session"] = cfg["qpa"]["reward_session"]
            labels["qpa_recent_episodes"] = cfg["qpa"]["recent_episodes"]
    return {
        "algo": cfg["algo"],
        "task": env["task"],
        "impl": env["impl"],
        "seeds": meta["seeds"],
        "num_envs": env["num_envs"],
        "episode_length": env["episode_length"],
        "total_steps": train["total_steps"],
        "eval_every": train["eval_every"],
        "eval_episodes": train["eval_episodes"],
        "network": f"{sac['depth']}x{sac['hidden']}",
        "batch_size": sac["batch_size"],
        "actor_lr": sac["actor_lr"],
        "critic_lr": sac["critic_lr"],
        "utd": sac["utd"],
        "precision": sac["precision"],
        **labels,
    }


def provenance(meta: dict) -> dict:
    """Device, date, JAX version, commit and every command of the run (its start and each ``--resume``)."""
    parts = [{"command": meta["command"], "started": meta["started"]}] + [
        {"command": r["command"], "started": r["started"]} for r in meta.get("resumed", [])
    ]
    return {
        "device": ", ".join(meta["devices"]),
        "date": meta["started"][:10],
        "jax": meta["jax"],
        "commit": meta.get("git_commit"),
        "commands": parts,
    }


def first_step_all_at(steps: np.ndarray, success: np.ndarray, level: float = 0.9) -> int | None:
    """The first evaluation step at which every seed's success rate is ``level`` or more, or None."""
    hit = np.flatnonzero((success >= level).all(axis=1))
    return int(steps[hit[0]]) if hit.size else None


def row(method: str, task: str, log: str) -> tuple[dict, tuple]:
    """One run's table row, and its success curve for the figures."""
    run_dir = RESULTS / "runs" / log
    cfg = json.loads((run_dir / "config.json").read_text())
    meta = json.loads((run_dir / "meta.json").read_text())
    steps, success = load_runs(run_dir, "eval_success")
    _, returns = load_runs(run_dir, "eval_return")
    last, last10 = success[-1], success[-LAST:].mean(axis=0)
    entry = {
        "method": method,
        "task": task,
        "run": f"results/runs/{log}",
        **settings(cfg, meta),
        "env_steps": int(steps[-1]),
        "finished": int(steps[-1]) >= cfg["train"]["total_steps"],
        "success_last": {"per_seed": last.tolist(), "mean": float(last.mean()), "std": sample_std(last)},
        "success_last10": {"per_seed": last10.tolist(), "mean": float(last10.mean()), "std": sample_std(last10)},
        "return_last": {"mean": float(returns[-1].mean()), "std": sample_std(returns[-1])},
        "labels_used": labels_used(run_dir, cfg),
        "all_seeds_at_0.9_from": first_step_all_at(steps, success),
        **provenance(meta),
    }
    final = run_dir / "final.json"
    if log in FINAL_NOT_USED:
        entry["final_json"] = {"used": False, "why": FINAL_NOT_USED[log]}
    elif final.exists():
        values = json.loads(final.read_text())
        entry["final_json"] = {"used": True, "success": values["final_eval_success"], "return": values["mean"]}
    stop = "" if entry["finished"] else f", stopped at {entry['env_steps'] // 1000}k"
    return entry, (f"{method} {task}{stop}", (steps, success))


def labels_used(run_dir, cfg: dict) -> dict | None:
    """The labels the teacher had given at the run's last round, mean over seeds, and the budget; None for SAC."""
    if cfg["algo"] == "sac":
        return None
    _, used = load_runs(run_dir, "labels_used")
    return {"used": float(used[-1].mean()), "budget": cfg["feedback"]["labels"]}


def main() -> None:
    rows, curves = zip(*(row(*run) for run in RUNS), strict=True)
    (RESULTS / "metaworld.json").write_text(json.dumps({"rows": list(rows)}, indent=1) + "\n")
    for name, title, mine in (
        ("metaworld_sac.png", "SAC on Meta-World's reward (paper_metaworld, MuJoCo Warp)", lambda m: m == "SAC"),
        ("metaworld_pbrl.png", "PEBBLE and QPA on an oracle's labels (MuJoCo Warp)", lambda m: m != "SAC"),
    ):
        curve_figure(
            {label: c for (label, c), r in zip(curves, rows, strict=True) if mine(r["method"])},
            RESULTS / name,
            f"{title}: success rate",
            seeds=True,
            ylabel="success rate (evaluation episodes per seed)",
        )
    print(
        "| method | task | seeds | steps | labels used | success at the last evaluation | last 10 evaluations "
        "| return | all seeds >= 0.9 |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        s, s10, ret, used = r["success_last"], r["success_last10"], r["return_last"], r["labels_used"]
        first = r["all_seeds_at_0.9_from"]
        asked = "-" if used is None else f"{used['used']:,.0f} of {used['budget']:,}"
        print(
            f"| {r['method']} | {r['task']} | {r['seeds']} | {r['env_steps']:,} | "
            f"{asked} | "
            f"{s['mean']:.2f} +- {s['std']:.2f} | {s10['mean']:.2f} +- {s10['std']:.2f} | "
            f"{ret['mean']:.0f} +- {ret['std']:.0f} | {'-' if first is None else f'{first:,}'} |"
        )


if __name__ == "__main__":
    main()
