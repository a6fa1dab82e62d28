"""``results/rebel.json``: REBEL against SAC, PEBBLE and PEBBLE+SURF on B-Pref's protocol.

Usage:
  python experiments/rebel.py

Each task's run directories (``RUNS``) are split into methods by ``compare.methods`` (a ``--lam-grid``
run into its lambdas; seeds of one method in several directories merged, as ``compare.gather``). One
row per method:

- ``final_returns``: per seed the mean of its last 10 evaluations (``analysis.final_returns``, the
  convention of ``compare.py``; ``baselines.json`` reports the end-of-run frozen evaluation instead);
- ``iqm_ci``: the 95% percentile-bootstrap interval of the IQM over seeds;
- ``steps_to_threshold``: the env steps (interpolated) at which the seed-mean curve first reaches the task's
  ``threshold``, ``analysis.common_threshold`` of the baselines' final means (80% of the lowest among SAC,
  PEBBLE and PEBBLE+SURF, ``BASELINES``: REBEL's rows do not move it, so adding a REBEL run changes no other
  row; a REBEL row whose curve never reaches it has steps null and ratio 0);
- ``efficiency_vs_pebble``: PEBBLE's steps to the threshold over the method's
  (``analysis.sample_efficiency_ratio``): 1.7 reads "70% more sample-efficient than PEBBLE", the
  paper's claim; ``efficiency_ci`` its seed-bootstrap interval (``sample_efficiency_ratio_ci``); ``pebble``
  names the PEBBLE it is against: under an imperfect teacher that teacher's PEBBLE (lambda 0 of the same
  ``--lam-grid 0 LAM`` program), else the oracle's;
- ``efficiency_vs_surf`` and ``efficiency_vs_surf_ci``: the same against PEBBLE+SURF (``SURF``: the run that met
  its published figure; null without one);
- ``device`` and ``date`` (sorted, each once), ``command``, ``train_seed`` and ``log`` (per run): every run the
  row pools (``compare.pooled_info``).

Also writes ``results/rebel_<task>.png``, one figure per task: each method's mean +- std curve over seeds; and
``results/rebel_lambda_walker_walk.png``: the IQM with its interval per lambda of the paper's V against PEBBLE's;
``results/rebel_teachers_walker_walk.png``: PEBBLE's and REBEL's (at the chosen lambda) IQM per B-Pref teacher.
The task figures draw the oracle teacher's methods only.

``STOPPED`` lists REBEL runs stopped early (at 140k steps); they are not rows. For them and for
every run above that logs them, ``rebel.json``'s ``on_policy_reward`` gives, per method, the learned
reward on the policy's own training transitions (``train.ROUND_REWARD_METRICS``), averaged over the
rounds from ``ON_POLICY_FROM`` steps and over seeds: its mean, the share of steps where it is
saturated, and its per-step correlation with the true reward. Their returns at equal steps come from
``compare.py --max-steps`` (RESULTS.md).

``sign_pairs`` sets +lambda against -lambda seed by seed within one lambda-grid program (its lambdas share
their seed keys), with a two-sided sign test, per lambda and pooled; ``estimator_pairs`` likewise the paper's
on-policy V against the replay window's V at the same lambda, and ``output_pairs`` the paper's tanh reward
against the sigmoid one (programs of the same ``--seed``: seed i has the same key in both; :func:`paper_pairs`);
``teacher_pairs`` REBEL against PEBBLE within each imperfect teacher's program (:func:`teacher_pairs`).

``chosen_lambda`` applies the rule of RESULTS.md that picks the lambda carried to cheetah_run (walker_walk
only). ``estimator`` and ``variant`` are read from the run's ``config.json``: where REBEL's V comes from
(``rebel.source``) and which form of the term it is (``rebel.form``, normalised or not, the reward's
output). Only runs of B-Pref's protocol (RESULTS.md, question 1) belong in ``RUNS``.
"""

from __future__ import annotations

import json
import math
import pathlib

import numpy as np
from analysis import (
    bootstrap_ci,
    common_threshold,
    curve_figure,
    distinct_evaluations,
    final_returns,
    iqm,
    log_name,
    mean_curve,
    sample_efficiency_ratio,
    sample_efficiency_ratio_ci,
    sign_counted,
    steps_to_reach,
)
from compare import compare, gather, methods

from rebel_jax.preference.feedback import ROUND_REWARD_METRICS
from rebel_jax.preference.teachers import PRESETS
from rebel_jax.run.plots import records as _records

RESULTS = pathlib.Path(__file__).parents[1] / "results"
RUNS = {  # task -> run directories under results/runs (REBEL's runs join them as they land)
    "walker_walk": [
        "sac_walker_walk",
        "baselines/pebble_walker_100_utd1",
        "baselines/pebble_walker_100_utd1_bf16_seed1",
        "baselines/surf_walker_100_utd1_bf16",
        "rebel/rebel_walker_100_lams_0.01_-0.01_bf16",
        "rebel/rebel_walker_100_lams_0.001_-0.001_bf16",
        "rebel/rebel_walker_100_lams_0.001_0.01_replay_bf16",
        "rebel/rebel_walker_100_lams_0.001_0.01_sigmoid_bf16",
        "rebel/rebel_walker_100_lams_0.1_-0.1_bf16",
        "rebel/rebel_walker_100_lams_0_0.001_noisy_bf16",
        "rebel/rebel_walker_100_lams_0_0.001_mistake_bf16",
        "rebel/rebel_walker_100_lams_0_0.001_skip_bf16",
        "rebel/rebel_walker_100_lams_0_0.001_equal_bf16",
        "rebel/rebel_walker_100_lams_0_0.001_myopic_bf16",
    ],
    "cheetah_run": [
        "baselines/sac_cheetah_fixed",
        "baselines/pebble_cheetah_100_1m_bf16",
        "baselines/surf_cheetah_100_1m_bf16",
        "baselines/surf_cheetah_100_1m_bf16_ru100",
        "rebel/rebel_cheetah_100_1m_lam0.001_bf16",
    ],
}
STOPPED = {  # task -> REBEL runs stopped early (not rows; see the module docstring)
    "walker_walk": [
        "rebel/rebel_walker_100_lams_0.1_-0.1_bf16_stopped140k",
        "rebel/rebel_walker_100_lams_0.01_-0.01_bf16_stopped140k",
    ],
}
ON_POLICY_FROM = 40_000
"""First env step of the rounds that ``on_policy_reward`` averages (after the first two feedback sessions)."""
PAPER_VARIANT = "lower_bound, raw, tanh output"
"""``rows``' ``variant`` of the paper's term (eq. "bilevel_rlhf_fo_lb" with the tanh reward, not normalised)."""
SIGMOID_VARIANT = "lower_bound, raw, sigmoid output"
"""``rows``' ``variant`` of the literal lower bound with the reward r >= 0 it assumes (``--reward.output sigmoid``)."""
PEBBLE = ("pebble", "pebble (rebel lam=0)")
"""Method labels of ``compare.methods`` that are PEBBLE (the reference of ``efficiency_vs_pebble``)."""
BASELINES = ("sac", "pebble", "surf")
"""The algorithms whose final means set the threshold (``common_threshold``): a row of any other method (REBEL,
QPA, RUNE) never moves it; of PEBBLE+SURF only the run ``SURF`` names."""
SURF = {"walker_walk": "surf", "cheetah_run": "surf (reward_update 100)"}
"""Per task the method label of the PEBBLE+SURF run that met its published figure, the reference of
``efficiency_vs_surf`` (the paper's claim names both baselines): on cheetah_run ``reward_update`` 100."""


def _round(x: float, digits: int = 2) -> float | str | None:
    """JSON-safe: NaN (undefined) as null, an infinite ratio (only one method reaches) as "inf"."""
    if math.isnan(x):
        return None
    return round(float(x), digits) if math.isfinite(x) else "inf"


def _log_dir(log: str) -> pathlib.Path:
    """A row's ``log`` entry (``results/runs/...``) as its run directory."""
    return RESULTS / "runs" / log.removeprefix("results/runs/")


def _setting(run_dir: pathlib.Path, algo: str) -> tuple[str | None, str | None]:
    """``(estimator, variant)`` of a REBEL run's term; None for the other algorithms."""
    cfg = json.loads((run_dir / "config.json").read_text())
    if algo != "rebel":
        return None, None
    rebel = cfg["rebel"]
    variant = [rebel["form"], "normalized" if rebel["normalize"] else "raw", f"{cfg['reward']['output']} output"]
    return rebel["source"], ", ".join(variant)


def rows(task: str, run_dirs: list[pathlib.Path], figure_path: pathlib.Path | None = None) -> list[dict]:
    """One row per method of ``task``'s runs (see the module docstring); the task's figure if a path is given."""
    curves, infos = gather(run_dirs)
    if figure_path is not None:
        oracle = {label: curve for label, curve in curves.items() if infos[label]["teacher"] in (None, "oracle")}
        curve_figure(oracle, figure_path, f"{task}, 100 labels, oracle teacher (B-Pref's protocol)")
    reference = next((label for label in PEBBLE if label in curves), None)
    surf = SURF.get(task)
    surf = surf if surf in curves else None
    if reference is None:
        raise ValueError(f"{task}: no PEBBLE run among {[str(d) for d in run_dirs]}")

    # PEBBLE+SURF counts by the run that met its published figure (``SURF``), so each task has one threshold
    # whichever SURF runs sit beside it (on cheetah_run the ``reward_update`` 1000 run is a row, not a baseline).
    def is_baseline(label: str) -> bool:
        algo = infos[label]["algo"]
        return label in PEBBLE or (algo in BASELINES and (algo != "surf" or surf in (None, label)))

    baselines = [label for label in curves if is_baseline(label)]
    threshold = common_threshold(np.nanmean(final_returns(curves[label][1])) for label in baselines)
    stats = compare(curves, reference, threshold)

    def against(curve, other: str | None) -> tuple[float, tuple[float, float]]:
        """``other``'s steps to the threshold over the curve's, with its seed-bootstrap interval (NaN without it)."""
        if other is None:
            return math.nan, (math.nan, math.nan)
        ratio = sample_efficiency_ratio(distinct_evaluations(curve), distinct_evaluations(curves[other]), threshold)
        return ratio, sample_efficiency_ratio_ci(curve, curves[other], threshold)

    def pebble_of(label: str) -> str:
        """PEBBLE under ``label``'s teacher (the oracle's PEBBLE where no run of that teacher holds one)."""
        teacher = infos[label]["teacher"]
        if teacher in (None, "oracle"):
            return reference
        return next((p + f", {teacher}" for p in PEBBLE if p + f", {teacher}" in curves), reference)

    out = []
    for label, (steps, returns) in curves.items():
        m, info = stats["methods"][label], infos[label]
        mean_steps, mean_returns = mean_curve(distinct_evaluations((steps, returns)))
        pebble = pebble_of(label)
        efficiency, ci = against((steps, returns), pebble)
        vs_surf, surf_ci = against((steps, returns), surf)
        estimator, variant = _setting(info["run_dirs"][0], info["algo"])
        out.append(
            {
                "method": label,
                "task": info["task"],
                "algo": info["algo"],
                "lam": info["lam"],
                "estimator": estimator,
                "variant": variant,
                "labels": info["labels"],
                "teacher": info["teacher"],
                "num_envs": info["num_envs"],
                "utd": info["utd"],
                "train_seed": info["train_seed"],
                "seeds": m["seeds"],
                "env_steps": m["env_steps"],
                "final_returns": [round(v, 2) for v in final_returns(returns)],
                "mean": round(m["mean"], 2),
                "std": round(m["std"], 2),
                "iqm": round(m["iqm"], 2),
                "iqm_ci": [_round(v) for v in m["iqm_ci"]],
                "threshold": round(threshold, 2),
                "steps_to_threshold": _round(steps_to_reach(mean_steps, mean_returns, threshold), None),
                "efficiency_vs_pebble": _round(efficiency),
                "efficiency_ci": [_round(v) for v in ci],
                "pebble": pebble,
                "efficiency_vs_surf": _round(vs_surf),
                "efficiency_vs_surf_ci": [_round(v) for v in surf_ci],
                "device": info["device"],
                "date": info["date"],
                "command": info["command"],
                "log": [log_name(d, RESULTS) for d in info["run_dirs"]],
            }
        )
    return out


def paper_rows(rows: list[dict], steps: int = 500_000) -> list[dict]:
    """The REBEL rows of the paper's V (on-policy, lower bound, raw, tanh) and the oracle teacher that reach
    ``steps``, by lambda."""
    paper = [
        r
        for r in rows
        if r["algo"] == "rebel"
        and r["teacher"] == "oracle"
        and r["lam"] != 0
        and r["estimator"] == "onpolicy"
        and r["variant"] == PAPER_VARIANT
        and r["env_steps"] >= steps
    ]
    return sorted(paper, key=lambda r: r["lam"])


def _save_iqm_figure(fig, ax, path: pathlib.Path, title: str) -> None:
    """Labels an IQM figure's y axis, titles it, adds the legend and writes it to ``path``."""
    import matplotlib.pyplot as plt

    ax.set_ylabel("final return, IQM over seeds")
    ax.set_title(title)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)  # below: clear of the bars
    fig.tight_layout()
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)


def lambda_figure(rows: list[dict], path: pathlib.Path, title: str) -> tuple[list[float], list[float]]:
    """Writes ``path``: per lambda of :func:`paper_rows` its IQM with the 95% interval, over PEBBLE's IQM and
    interval (a line and a band) and PEBBLE+SURF's IQM (dashed, where ``SURF`` names a row); lambda on a
    symmetric log axis. A final return is per seed the mean of its last 10 evaluations. Returns the lambdas
    and IQMs drawn."""
    import matplotlib.pyplot as plt

    paper = paper_rows(rows)
    pebble = next(r for r in rows if r["method"] in PEBBLE)
    lams, iqms = [r["lam"] for r in paper], [r["iqm"] for r in paper]
    below = [r["iqm"] - r["iqm_ci"][0] for r in paper]
    above = [r["iqm_ci"][1] - r["iqm"] for r in paper]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.axhspan(*pebble["iqm_ci"], color="tab:orange", alpha=0.2, label=f"{pebble['method']}: IQM, 95% CI")
    ax.axhline(pebble["iqm"], color="tab:orange")
    ax.errorbar(lams, iqms, yerr=[below, above], fmt="o", capsize=4, label="REBEL, the paper's V: IQM, 95% CI")
    ax.set_xscale("symlog", linthresh=min((abs(lam) for lam in lams if lam), default=1.0))
    ax.set_xticks(lams)
    ax.set_xticklabels([f"{lam:g}" for lam in lams])
    ax.set_xlabel("lambda")
    surf = next((r for r in rows if r["method"] == SURF.get(r["task"])), None)
    if surf is not None:
        ax.axhline(surf["iqm"], color="tab:green", linestyle="--", label=f"{surf['method']}: IQM")
    _save_iqm_figure(fig, ax, path, title)
    return lams, iqms


def chosen_lambda(rows: list[dict], steps: int = 500_000) -> dict | None:
    """The rule of RESULTS.md, written before the 500k runs landed: among the REBEL rows of the paper's V
    (on-policy, lower bound, raw, tanh) that reach ``steps``, the one with the highest IQM; None if none does.
    """
    eligible = paper_rows(rows, steps)
    if not eligible:
        return None
    best = max(eligible, key=lambda r: r["iqm"])
    return {"task": best["task"], "lam": best["lam"], "iqm": best["iqm"], "among": [r["lam"] for r in eligible]}


def _differences(a: dict, b: dict) -> list[float]:
    """Per seed ``a``'s final return minus ``b``'s (rows whose seed i shares its key)."""
    return [round(float(x) - float(y), 2) for x, y in zip(a["final_returns"], b["final_returns"], strict=True)]


def _sign_tested(entries: list[dict]) -> list[dict]:
    """Each entry :func:`sign_counted`; then one entry pooling every pair (``lam`` "all"), if there is any entry."""
    out = [sign_counted(e) for e in entries]
    if out:
        out.append(sign_counted({"lam": "all", "differences": [d for e in out for d in e["differences"]]}))
    return out


def sign_pairs(rows: list[dict]) -> list[dict]:
    """+lambda against -lambda, seed by seed: for every REBEL row whose log (one ``--lam-grid`` program, whose
    lambdas share their seed keys) also holds -lambda, the per-seed final return at +lambda minus at -lambda,
    sign-tested (:func:`_sign_tested`)."""
    entries = []
    rebel = [r for r in rows if r["algo"] == "rebel"]
    for r in rebel:
        twin = [o for o in rebel if o["log"] == r["log"] and o["lam"] == -r["lam"]]
        if r["lam"] > 0 and twin:
            entries.append(
                {"task": r["task"], "lam": r["lam"], "log": r["log"], "differences": _differences(r, twin[0])}
            )
    return _sign_tested(entries)


def paper_pairs(rows: list[dict], estimator: str = "onpolicy", variant: str = PAPER_VARIANT) -> list[dict]:
    """The paper's term against one other setting of it, seed by seed: for every REBEL row of ``estimator`` and
    ``variant`` (at least one not the paper's), the row of the paper's term (on-policy V, ``PAPER_VARIANT``) at
    the same lambda, task, ``train_seed`` and seeds (seed i has the same key in both programs,
    ``train.seed_keys``): per seed the paper's final return minus the other's, sign-tested (:func:`_sign_tested`).
    """
    if (estimator, variant) == ("onpolicy", PAPER_VARIANT):
        raise ValueError("paper_pairs sets another setting against the paper's term; this one is the paper's")
    same = ("task", "lam", "teacher", "train_seed", "seeds")
    rebel = [r for r in rows if r["algo"] == "rebel"]
    paper = [r for r in rebel if r["estimator"] == "onpolicy" and r["variant"] == PAPER_VARIANT]
    entries = []
    for other in (r for r in rebel if r["estimator"] == estimator and r["variant"] == variant):
        twin = [p for p in paper if all(p[k] == other[k] for k in same)]
        if twin:
            entries.append(
                {
                    "task": other["task"],
                    "lam": other["lam"],
                    "log": [twin[0]["log"], other["log"]],
                    "differences": _differences(twin[0], other),
                }
            )
    return _sign_tested(entries)


def teacher_rows(rows: list[dict], lam: float) -> list[tuple[str, dict, dict]]:
    """``(teacher, PEBBLE's row, REBEL's row)`` per B-Pref teacher (``teachers.PRESETS`` order) under which both
    ran: REBEL of the paper's V at ``lam``, and the PEBBLE its ``efficiency_vs_pebble`` is against (the same
    teacher's; the oracle's PEBBLE for the oracle)."""
    by_method = {r["method"]: r for r in rows}
    out = []
    for teacher in PRESETS:
        rebel = [
            r
            for r in rows
            if r["algo"] == "rebel"
            and r["teacher"] == teacher
            and r["lam"] == lam
            and (r["estimator"], r["variant"]) == ("onpolicy", PAPER_VARIANT)
        ]
        if rebel and rebel[0]["pebble"] in by_method:
            out.append((teacher, by_method[rebel[0]["pebble"]], rebel[0]))
    return out


def teacher_pairs(rows: list[dict]) -> list[dict]:
    """REBEL against PEBBLE under each imperfect teacher, seed by seed: for every REBEL row (lambda != 0) of a
    teacher other than the oracle whose log (one ``--lam-grid 0 LAM`` program: its lambdas share their seed keys)
    also holds lambda 0 (PEBBLE bit for bit), the per-seed final return of REBEL minus PEBBLE's, sign-tested
    (:func:`_sign_tested`)."""
    rebel = [r for r in rows if r["algo"] == "rebel" and r["teacher"] not in (None, "oracle")]
    entries = []
    for r in (r for r in rebel if r["lam"] != 0):
        twin = [o for o in rebel if o["log"] == r["log"] and o["lam"] == 0 and o["teacher"] == r["teacher"]]
        if twin:
            entries.append(
                {
                    "task": r["task"],
                    "lam": r["lam"],
                    "teacher": r["teacher"],
                    "log": r["log"],
                    "differences": _differences(r, twin[0]),
                }
            )
    return _sign_tested(entries)


def oracle_labelled(run_dir: pathlib.Path) -> bool:
    """Whether every label of a teacher's run was the oracle's: its teacher answers as the oracle does (``beta``
    inf, ``gamma`` 1, no mistakes), and in every round with a session, every column's ``session_skipped`` and
    ``session_equal`` are 0. B-Pref's skip teacher on walker_walk did so (RESULTS.md): such a run repeats the
    oracle's protocol."""
    teacher = json.loads((run_dir / "config.json").read_text())["teacher"]
    if (teacher["beta"], teacher["gamma"], teacher["eps_mistake"]) != (math.inf, 1.0, 0.0):
        return False
    sessions = [r for r in _records(run_dir) if "session_skipped" in r]
    counts = [v for r in sessions for k in ("session_skipped", "session_equal") for v in r[k] if v is not None]
    return bool(sessions) and not any(counts)


def oracle_pooled(rows: list[dict], lam: float) -> dict | None:
    """PEBBLE and REBEL (the paper's V at ``lam``) over the oracle's rows and the imperfect teachers' rows of
    runs whose every label was the oracle's (:func:`oracle_labelled`); None without both oracle rows.

    A secondary analysis, chosen after the skip teacher turned out to skip nothing: more seeds of one protocol.
    Per method: the teachers pooled, ``seeds``, ``final_returns``, ``iqm`` and its 95% bootstrap ``iqm_ci``."""
    drawn = teacher_rows(rows, lam)
    if not drawn or drawn[0][0] != "oracle":
        return None
    pooled = [d for d in drawn if d[0] == "oracle" or all(oracle_labelled(_log_dir(log)) for log in d[2]["log"])]
    out: dict = {"lam": lam, "teachers": [teacher for teacher, _, _ in pooled]}
    for name, k in (("pebble", 1), ("rebel", 2)):
        scores = [v for d in pooled for v in d[k]["final_returns"]]
        out[name] = {
            "seeds": len(scores),
            "final_returns": scores,
            "iqm": _round(iqm(scores)),
            "iqm_ci": [_round(v) for v in bootstrap_ci(scores)],
            "log": sorted({log for d in pooled for log in d[k]["log"]}),
        }
    return out


def teacher_figure(rows: list[dict], lam: float, path: pathlib.Path, title: str) -> list[str]:
    """Writes ``path``: per teacher of :func:`teacher_rows` PEBBLE's and REBEL's IQM with the 95% interval, side
    by side. Returns the teachers drawn."""
    import matplotlib.pyplot as plt

    drawn = teacher_rows(rows, lam)
    fig, ax = plt.subplots(figsize=(7, 4))
    x = np.arange(len(drawn))
    for offset, which, name in ((-0.12, 1, "PEBBLE"), (0.12, 2, f"REBEL lambda {lam:g}")):
        picked = [entry[which] for entry in drawn]
        iqms = np.array([r["iqm"] for r in picked])
        low, high = (np.array([r["iqm_ci"][k] for r in picked], dtype=float) for k in (0, 1))
        ax.errorbar(x + offset, iqms, yerr=[iqms - low, high - iqms], fmt="o", capsize=4, label=f"{name}: IQM, 95% CI")
    ax.set_xticks(x)
    ax.set_xticklabels([teacher for teacher, _, _ in drawn])
    ax.set_xlabel("B-Pref teacher")
    _save_iqm_figure(fig, ax, path, title)
    return [teacher for teacher, _, _ in drawn]


def oracle_agreement(run_dir: pathlib.Path) -> dict[str, float]:
    """Per method of the run: ``session_oracle_agreement`` (the share of its labels equal to the oracle's answers)
    averaged over its columns' sessions; empty for a run that predates the metric."""
    records = [r for r in _records(run_dir) if "session_oracle_agreement" in r]
    out = {}
    for label, (_, info) in methods(run_dir).items():
        values = [v for r in records for v in np.asarray(r["session_oracle_agreement"], float)[info["columns"]]]
        values = [v for v in values if math.isfinite(v)]  # NaN (null) in rounds without a session
        if values:
            out[label] = round(float(np.mean(values)), 3)
    return out


def _agreement(row: dict) -> float | str:
    """A row's :func:`oracle_agreement`; "-" for a row of several runs or of a run that predates the metric."""
    return oracle_agreement(_log_dir(row["log"][0])).get(row["method"], "-") if len(row["log"]) == 1 else "-"


def on_policy_reward(task: str, run_dir: pathlib.Path) -> list[dict]:
    """Per method of the run: ``train.ROUND_REWARD_METRICS`` over rounds from ``ON_POLICY_FROM`` and seeds.

    Empty for a run that predates those metrics (or has no learned reward).
    """
    records = [r for r in _records(run_dir) if r["env_steps"] >= ON_POLICY_FROM and ROUND_REWARD_METRICS[0] in r]
    if not records:
        return []
    out = []
    for label, (_, info) in methods(run_dir).items():
        cols = info["columns"]
        means = {name: float(np.mean([np.asarray(r[name])[cols] for r in records])) for name in ROUND_REWARD_METRICS}
        out.append(
            {
                "task": task,
                "method": label,
                "lam": info["lam"],
                "seeds": len(cols),
                "rounds": len(records),
                "steps": [records[0]["env_steps"], records[-1]["env_steps"]],
                **{name: round(v, 3) for name, v in means.items()},
                "log": log_name(run_dir, RESULTS),
            }
        )
    return out


def main() -> None:
    table = [
        row
        for task, logs in RUNS.items()
        for row in rows(task, [RESULTS / "runs" / log for log in logs], RESULTS / f"rebel_{task}.png")
    ]
    logs = {task: RUNS[task] + STOPPED.get(task, []) for task in RUNS}
    reward = [row for task, dirs in logs.items() for d in dirs for row in on_policy_reward(task, RESULTS / "runs" / d)]
    walker = [r for r in table if r["task"] == "walker_walk"]
    chosen, signs = chosen_lambda(walker), sign_pairs(walker)
    lambda_figure(walker, RESULTS / "rebel_lambda_walker_walk.png", "walker_walk at 500k, 100 labels, oracle teacher")
    lam = chosen["lam"] if chosen else None
    if chosen is not None:  # the teachers' REBEL is the chosen lambda's
        teacher_figure(walker, lam, RESULTS / "rebel_teachers_walker_walk.png", "walker_walk at 500k, 100 labels")
    out = {
        "rows": table,
        "on_policy_reward": reward,
        "chosen_lambda": chosen,
        "sign_pairs": signs,
        "estimator_pairs": paper_pairs(walker, estimator="replay"),
        "output_pairs": paper_pairs(walker, variant=SIGMOID_VARIANT),
        "teacher_pairs": teacher_pairs(walker),
        "oracle_pooled": oracle_pooled(walker, lam) if chosen else None,
    }
    (RESULTS / "rebel.json").write_text(json.dumps(out, indent=1) + "\n")
    print(
        "| task | method | seeds | env steps | mean +- std | IQM [95% CI] | steps to threshold | vs PEBBLE [95% CI] "
        "| vs SURF [95% CI] |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for r in (r for r in table if r["teacher"] in (None, "oracle")):  # the imperfect teachers' table follows
        low, high = r["iqm_ci"]
        e_low, e_high = r["efficiency_ci"]
        print(
            f"| {r['task']} | {r['method']} | {r['seeds']} | {r['env_steps']:,} | {r['mean']:.1f} +- {r['std']:.1f} "
            f"| {r['iqm']:.1f} [{low}, {high}] | {r['steps_to_threshold']} ({r['threshold']:.0f}) "
            f"| {r['efficiency_vs_pebble']} [{e_low}, {e_high}] "
            f"| {r['efficiency_vs_surf']} [{r['efficiency_vs_surf_ci'][0]}, {r['efficiency_vs_surf_ci'][1]}] |"
        )
    if chosen is None:
        print("\nlambda by the rule of RESULTS.md: none yet (no REBEL run of the paper's V has reached 500k)")
    else:
        print(f"\nlambda by the rule of RESULTS.md: {chosen['lam']} (IQM {chosen['iqm']}; among {chosen['among']})")
    print(f"\nUnder B-Pref's teachers (walker_walk, REBEL at lambda {lam}; final returns, IQM [95% CI]):\n")
    print(
        "| teacher | PEBBLE | REBEL | REBEL minus PEBBLE, seed by seed: mean (positive of pairs, sign test p) "
        "| labels equal to the oracle's (PEBBLE, REBEL) | log |"
    )
    print("|---|---:|---:|---:|---:|---|")
    paired = {(e["teacher"], e["lam"]): e for e in out["teacher_pairs"] if "teacher" in e}
    for teacher, pebble, rebel in teacher_rows(walker, lam):
        e = paired.get((teacher, lam))
        pairs = (
            f"{np.mean(e['differences']):+.1f} ({e['positive']} of {e['pairs']}, p = {e['sign_test_p']})" if e else "-"
        )
        agreement = ", ".join(str(_agreement(r)) for r in (pebble, rebel))
        print(
            f"| {teacher} | {pebble['iqm']:.1f} [{pebble['iqm_ci'][0]}, {pebble['iqm_ci'][1]}] "
            f"| {rebel['iqm']:.1f} [{rebel['iqm_ci'][0]}, {rebel['iqm_ci'][1]}] | {pairs} | {agreement} "
            f"| {', '.join(f'`{log}`' for log in sorted({*pebble['log'], *rebel['log']}))} |"
        )
    pooled = out["oracle_pooled"]
    if pooled and len(pooled["teachers"]) > 1:
        print(
            f"\nThe oracle's labels pooled over the runs of teachers {pooled['teachers']} (every label the oracle's):\n"
        )
        for name in ("pebble", "rebel"):
            p = pooled[name]
            print(f"- {name}: IQM {p['iqm']} [{p['iqm_ci'][0]}, {p['iqm_ci'][1]}] over {p['seeds']} seeds")
    for title, entries in (
        ("+lambda against -lambda, seed by seed (walker_walk; final return at +lambda minus at -lambda)", signs),
        (
            "The paper's V against the replay V, seed by seed (final return on-policy minus replay)",
            out["estimator_pairs"],
        ),
        (
            "The paper's tanh reward against the sigmoid one, seed by seed (final return tanh minus sigmoid)",
            out["output_pairs"],
        ),
        ("REBEL against PEBBLE under each imperfect teacher, seed by seed (REBEL minus PEBBLE)", out["teacher_pairs"]),
    ):
        print(f"\n{title}:\n")
        for e in entries:
            which = f"{e['teacher']}, lambda {e['lam']}" if "teacher" in e else f"lambda {e['lam']}"
            print(f"- {which}: {e['positive']} of {e['pairs']} positive, sign test p = {e['sign_test_p']}")
    print(f"\nOn the policy's own transitions, rounds from {ON_POLICY_FROM:,} steps (means over rounds and seeds):\n")
    print("| task | method | steps | learned reward mean | saturated share | per-step corr. with true reward | log |")
    print("|---|---|---|---:|---:|---:|---|")
    for r in reward:
        print(
            f"| {r['task']} | {r['method']} | {r['steps'][0] // 1000}k-{r['steps'][1] // 1000}k "
            f"| {r['round_learned_mean']:.2f} | {r['round_learned_saturated']:.2f} "
            f"| {r['round_reward_correlation']:.2f} | `{r['log']}` |"
        )


if __name__ == "__main__":
    main()
