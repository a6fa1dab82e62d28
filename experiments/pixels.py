"""``results/pixels.json``: the pixel runs (DrQ-v2, and PEBBLE, SURF and REBEL on pixels).

Usage:
  python experiments/pixels.py

One row per (task, method, run length) of the run directories in ``RUNS``, split into methods and merged over
directories by ``compare.gather`` (the DrQ-v2 walker runs are one seed per program, so a method's seeds come
from several directories). ``frames`` are the agent steps of the
log times the task's action repeat (``PixelEnv.action_repeat``, 2): DrQ-v2 and SURF's pixel branch count
frames. Per row: ``labels`` (those the seeds got, read from the logs' ``labels_used``; the
budget asked is ``labels_asked``), ``final_returns`` (per seed the mean of its last 10 evaluations,
``analysis.final_returns``), ``mean``, ``std``, ``iqm`` with ``iqm_ci`` (95% percentile bootstrap over
seeds), ``device``, ``date``, ``command`` and ``log``; for a preference method also ``reward_accuracy_new`` and
``reward_correlation``, per seed the mean over its sessions (``REWARD_METRICS``). Also writes
``results/pixels_<task>.png``: each method's mean +- std evaluation return against frames. ``stopped`` lists the
runs stopped early, ``matched`` the preference methods at the agent steps all of their runs reached
(``MATCHED``), drawn in ``results/pixels_<task>_matched.png``; ``coupling`` whether a key's return difference between
two methods follows its learned reward's (:func:`coupling`); ``pooled`` a comparison over both tasks at once, in
units of each task's DrQ-v2 score (:func:`pooled`); ``results/pixels_paper.png`` draws the paper's pixel
panels (``PAPER_FIGURE``): PEBBLE, PEBBLE+SURF and REBEL at their longest whole runs beside DrQ-v2 on the true reward.
"""

from __future__ import annotations

import json
import math
import pathlib
import re
import warnings
from collections.abc import Iterator

import numpy as np
from analysis import (
    bootstrap_ci,
    curve_figure,
    detectable_difference,
    load_runs,
    log_name,
    rank_correlation,
    sign_test_p,
    signed_rank_p,
)
from compare import compare, gather, methods

from rebel_jax.envs import make_env
from rebel_jax.run.plots import per_seed, plot_curves, records

RESULTS = pathlib.Path(__file__).parents[1] / "results"
CHEETAH_PREFERENCE = [
    "pixels/rebel_cheetah_pixels_150000steps_seed2_seeds2_lams_0_0.001_bf16",
    "pixels/rebel_cheetah_pixels_150000steps_seed4_seeds2_lams_0_0.001_bf16",
    "pixels/surf_cheetah_pixels_80000steps_seed0_seeds3_bf16",
    "pixels/rebel_cheetah_pixels_150000steps_seed6_seeds2_lams_0_0.001_bf16",
    "pixels/surf_cheetah_pixels_150000steps_seed2_seeds2_bf16",
    "pixels/surf_cheetah_pixels_150000steps_seed4_seeds2_bf16",
    "pixels/surf_cheetah_pixels_80000steps_seed0_seeds2_bf16_surfadam",
    "pixels/rebel_cheetah_pixels_150000steps_seed8_seeds2_lams_0_0.001_bf16",
    "pixels/surf_cheetah_pixels_150000steps_seed6_seeds2_bf16",
]
"""The whole pixel preference runs on cheetah_run (PEBBLE and REBEL in lam-grid programs, and SURF)."""
WALKER_PREFERENCE = [
    *(f"pixels/rebel_walker_pixels_250000steps_seed{k}_lams_0_0.001_envs20_seedsteps10000_bf16" for k in range(6)),
    *(f"pixels/surf_walker_pixels_250000steps_seed{k}_envs20_seedsteps10000_bf16" for k in range(5)),
]
"""The whole pixel preference runs on walker_walk (PEBBLE and REBEL in lam-grid programs, and SURF), one key each."""
RUNS: dict[str, list[str]] = {
    "cheetah_run_pixels": ["pixels/drqv2_cheetah_500kframes_seed0_seeds5_bf16", *CHEETAH_PREFERENCE],
    "walker_walk_pixels": [
        "pixels/drqv2_walker_500kframes_seed0_bf16",
        "pixels/drqv2_walker_500kframes_seed20_seeds1_bf16_qf32",
        "pixels/drqv2_walker_500kframes_seed22_bf16_qf32",
        "pixels/drqv2_walker_500kframes_seed23_bf16_qf32",
        "pixels/drqv2_walker_500kframes_seed24_bf16_qf32",
        "pixels/drqv2_walker_500kframes_seed21_bf16_qf32",
        *WALKER_PREFERENCE,
    ],
}
"""Pixel task (``<task>_pixels``) -> its whole run directories under ``results/runs``; runs of one method that
ended at different lengths are rows apart (:func:`by_length`)."""
STOPPED: dict[str, list[str]] = {
    "cheetah_run_pixels": ["pixels/rebel_cheetah_pixels_150000steps_seed0_seeds2_lams_0_0.001_bf16_stopped82k"],
    "walker_walk_pixels": [
        "pixels/drqv2_walker_500kframes_seed0_bf16_stopped218k",
        "pixels/drqv2_walker_500kframes_seed1_seeds2_bf16_stopped245k",
    ],
}
"""Pixel runs stopped early: drawn in the task's figure and listed with every
evaluation under ``pixels.json``'s ``stopped``, but not rows (their last 10 evaluations are not a final score)."""
MATCHED: dict[str, tuple[int, list[str]]] = {
    "cheetah_run_pixels": (80_000, [*STOPPED["cheetah_run_pixels"], *CHEETAH_PREFERENCE]),
}
"""Pixel task -> (agent steps, run directories): the preference methods compared where all of the runs have
evaluated, each method's seeds pooled over the directories (:func:`matched`); ``pixels.json``'s ``matched`` and
``results/pixels_<task>_matched.png``."""


PEBBLE, REBEL = "pebble (rebel lam=0) 1000 labels", "rebel lam=0.001 1000 labels"
SURF = "surf 1000 labels (reward_update 20)"
PAIRED: dict[str, list[tuple[str, str]]] = {
    "cheetah_run_pixels": [(PEBBLE, REBEL), (PEBBLE, SURF), (SURF, f"{SURF} (SURF's reward Adam)")],
    "walker_walk_pixels": [
        ("pebble (rebel lam=0) 200 labels", "rebel lam=0.001 200 labels"),
        ("pebble (rebel lam=0) 200 labels", "surf 200 labels (reward_update 20)"),
    ],
}
"""Pixel task -> (method a, method b): b against a key by key (:func:`paired`), in the rows and the matched
entries wherever both methods have seeds of the same keys at the same frames, by their returns and by their
learned rewards' measures (:data:`REWARD_METRICS`); ``pixels.json``'s ``paired``."""
POOLED: dict[str, dict[str, tuple[str, str]]] = {
    "REBEL minus PEBBLE": {task: PAIRED[task][0] for task in PAIRED},
    "SURF minus PEBBLE": {task: PAIRED[task][1] for task in PAIRED},
}
"""Comparison -> pixel task -> its :data:`PAIRED` methods: the comparisons :func:`pooled` reads over both tasks;
``pixels.json``'s ``pooled``."""
REFERENCE = {"cheetah_run_pixels": "drqv2", "walker_walk_pixels": "drqv2 (float32 critic output)"}
"""Pixel task -> the row whose mean scales its differences in :func:`pooled`: DrQ-v2 on the true reward, 5 seeds
at 500k frames (the float32 critic output on walker, the arm that met the target of 700)."""


def _std(std: float | None) -> str:
    """A table's std cell: one decimal, "-" where one seed has none."""
    return "-" if std is None else f"{std:.1f}"


def action_repeat(task: str) -> int:
    """Frames per agent step of a pixel task."""
    return make_env(task).action_repeat


def _described(task: str, label: str, info: dict) -> dict:
    """What a pixels.json entry is and where it comes from: its task, method and run provenance.

    A method's seeds may come from runs on different devices and days, so ``device`` and ``date`` list every one
    of its runs' values (sorted, each once) and ``command`` each run's command, in the order of ``log``, as
    ``experiments/baselines.py`` does; all read from the runs' ``meta.json`` (``compare.pooled_info``).
    """
    return {
        "task": task.removesuffix("_pixels"),
        "algo": info["algo"],
        "method": label,
        "obs": "pixels",
        "device": info["device"],
        "date": info["date"],
        "command": info["command"],
        "log": [log_name(d, RESULTS) for d in info["run_dirs"]],
    }


def _columns(run_dirs: list[pathlib.Path], label: str) -> Iterator[tuple[pathlib.Path, list[int]]]:
    """Each run directory that holds method ``label``, with the label's columns of its per-seed metrics, in the
    order ``gather`` pools their seeds."""
    for run_dir in run_dirs:
        found = methods(run_dir).get(label)
        if found is not None:
            yield run_dir, found[1]["columns"]


def labels_used(run_dirs: list[pathlib.Path], label: str, max_steps: int) -> list[int]:
    """Per seed of method ``label`` (in ``gather``'s order), the labels it had used at its run's last round up to
    ``max_steps`` agent steps that logs ``labels_used``: what it got, which may fall short of ``--labels`` (SURF's
    walker schedule asks 170 of 200 in 500k frames, notes/surf_pixel_audit.md, decision 3). A run that stopped
    before its first feedback session logged none: its seeds are left out."""
    out = []
    for run_dir, columns in _columns(run_dirs, label):
        logged = [r for r in records(run_dir) if r.get("labels_used") is not None and r["env_steps"] <= max_steps]
        if logged:  # none: stopped before its first feedback session
            out += [int(logged[-1]["labels_used"][c]) for c in columns]
    return out


REWARD_METRICS = ("reward_accuracy_new", "reward_correlation")
"""The pixel sessions' measures of the learned reward, averaged per seed over its sessions (:func:`session_means`):
the ensemble's accuracy on each session's new (not equal) pairs before it trains on them, its generalisation
(0.5 is chance), and the Pearson correlation of the relabelled and the true reward over the replay
(``reward_correlation_replay`` of :data:`rebel_jax.preference.pixel_feedback.PIXEL_SESSION_METRICS`; logs written
before that
name call it ``reward_correlation``, the name kept here)."""

LOGGED_AS = {"reward_correlation": ("reward_correlation_replay", "reward_correlation")}
"""A measure's names in the logs, newest first."""


def session_means(run_dirs: list[pathlib.Path], label: str, max_steps: int, name: str) -> list[float]:
    """Per seed of method ``label`` (in ``gather``'s order) the mean of the per-round metric ``name`` over its
    sessions up to ``max_steps`` agent steps (the rounds that log it; NaN in the others). A run that logs none,
    a DrQ-v2 run or one from before the metric, adds no seeds."""
    out = []
    for run_dir, columns in _columns(run_dirs, label):
        rounds = [r for r in records(run_dir) if r["env_steps"] <= max_steps]
        logged_as = next((n for n in LOGGED_AS.get(name, (name,)) if any(n in r for r in rounds)), name)
        logged = [per_seed(r[logged_as]) for r in rounds if r.get(logged_as) is not None]
        if logged:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # a seed without a session: NaN, None in the JSON
                means = np.nanmean(np.asarray(logged, dtype=float), axis=0)
            out += [round(float(means[c]), 3) if np.isfinite(means[c]) else None for c in columns]
    return out


def seed_keys(run_dirs: list[pathlib.Path], label: str) -> list[list[int]]:
    """Per seed of method ``label`` (in ``gather``'s order) its key as ``[train.seed, i]``: every program gives
    its column c the key ``fold_in(PRNGKey(train.seed), c % seeds)`` (``cli.column_keys``), so a grid's lambdas,
    and runs of other methods started from the same ``--seed``, share their seeds' keys."""
    out = []
    for run_dir, columns in _columns(run_dirs, label):
        seed = json.loads((run_dir / "config.json").read_text())["train"]["seed"]
        seeds = json.loads((run_dir / "meta.json").read_text())["seeds"]
        out += [[seed, c % seeds] for c in columns]
    return out


PLANNED_KEYS = (5, 10, 20)
"""Key counts at which :func:`paired` gives the detectable difference beside the entry's own."""


def paired(entries: list[dict], a: str, b: str, scores: str) -> list[dict]:
    """Method ``b`` against ``a`` key by key: for each frames at which ``entries`` (rows or matched entries) hold
    both, over the seed keys both have (:func:`seed_keys`), the per-key ``scores`` of b minus a's and their
    statistics (:func:`differences`; ``detectable`` is for planning how many keys a comparison needs). No entry
    where the two share no key."""
    out = []
    for x in (e for e in entries if e["method"] == a):
        for y in (e for e in entries if e["method"] == b and e["frames"] == x["frames"]):
            mine = {tuple(k): v for k, v in zip(x["keys"], x[scores], strict=True) if v is not None}
            theirs = {tuple(k): v for k, v in zip(y["keys"], y[scores], strict=True) if v is not None}
            keys = [k for k in mine if k in theirs]
            if not keys:
                continue
            diffs = np.array([theirs[k] - mine[k] for k in keys])
            digits = 3 if scores in REWARD_METRICS else 2  # returns, or the rewards' accuracies and correlations
            described = {"task": x["task"], "frames": x["frames"], "scores": scores, "a": a, "b": b}
            out.append(described | {"keys": [list(k) for k in keys]} | differences(diffs, digits))
    return out


def differences(diffs: np.ndarray, digits: int) -> dict:
    """Paired differences (b minus a, one per key) and what they say, each rounded to ``digits``: the mean, its
    standard error and 95% percentile bootstrap interval (at a few keys narrower than its 95%), how many are
    positive with the two-sided sign test's p-value and the Wilcoxon signed-rank test's
    (:func:`analysis.signed_rank_p`), zeros being no pair of either; ``detectable``: at these keys and at
    :data:`PLANNED_KEYS`, the smallest mean difference a paired t-test would find with 80% power at the observed
    spread (:func:`analysis.detectable_difference`)."""
    nonzero = diffs[diffs != 0]
    positive = int(np.sum(nonzero > 0))
    low, high = bootstrap_ci(diffs, np.mean)
    sem = float(diffs.std(ddof=1) / np.sqrt(len(diffs))) if len(diffs) > 1 else math.nan
    return {
        "differences": [round(float(d), digits) for d in diffs],
        "mean": round(float(diffs.mean()), digits),
        "sem": round(sem, digits) if math.isfinite(sem) else None,
        "mean_ci": [round(v, digits) if math.isfinite(v) else None for v in (low, high)],
        "positive": positive,
        "pairs": len(nonzero),
        "sign_test_p": round(sign_test_p(positive, len(nonzero)), 4),
        "signed_rank_p": None if nonzero.size == 0 else round(signed_rank_p(nonzero), 4),
        "detectable": {
            str(n): None if (v := detectable_difference(diffs, n)) is None else round(v, digits)
            for n in sorted({len(diffs), *PLANNED_KEYS})
        },
    }


def pooled(pairs: list[dict], table: list[dict]) -> list[dict]:
    """Each comparison of :data:`POOLED` over both pixel tasks: per task its :func:`paired` entry of final returns
    at the longest frames, each key's difference divided by the mean of the task's reference row
    (:data:`REFERENCE`, DrQ-v2 on the true reward at 500k frames), the tasks' keys together (:func:`differences`,
    in units of that mean). ``tasks`` says which entry and reference each task gave. No entry where fewer than two
    tasks have one. Chosen after the per-task entries were seen, to read both panels at
    once with more keys than either; RESULTS.md says so."""
    out = []
    for name, by_task in POOLED.items():
        parts, diffs = [], []
        for task, (a, b) in by_task.items():
            short = task.removesuffix("_pixels")
            found = [e for e in pairs if (e["task"], e["scores"], e["a"], e["b"]) == (short, "final_returns", a, b)]
            if not found:
                continue
            entry = max(found, key=lambda e: e["frames"])
            refs = [r for r in table if r["task"] == short and r["method"] == REFERENCE[task]]
            if len(refs) != 1:
                raise ValueError(f"{task}: {len(refs)} rows of the reference {REFERENCE[task]!r}, not one")
            ref = refs[0]
            diffs += [d / ref["mean"] for d in entry["differences"]]
            parts.append(
                {"task": short, "frames": entry["frames"], "a": a, "b": b, "keys": len(entry["keys"]),
                 "reference": ref["method"], "reference_frames": ref["frames"], "reference_mean": ref["mean"]}
            )  # fmt: skip
        if len(parts) > 1:
            out.append({"comparison": name, "tasks": parts} | differences(np.array(diffs), 3))
    return out


def coupling(pairs: list[dict], measure: str = "reward_correlation") -> list[dict]:
    """Whether a key's return difference follows its learned reward's: for each :func:`paired` entry of
    ``final_returns``, Spearman's correlation over the keys of its differences with those of the entry of
    ``measure`` for the same task, frames and methods, and its permutation p (:func:`analysis.rank_correlation`).
    No entry below 3 shared keys. The reward measures are taken over each seed's own replay, which its policy
    fills, so a correlation here does not say which way the effect runs."""
    same, out = ("task", "frames", "a", "b"), []
    for e in (e for e in pairs if e["scores"] == "final_returns"):
        found = next((m for m in pairs if m["scores"] == measure and all(m[k] == e[k] for k in same)), None)
        if found is None:
            continue
        by_key = {tuple(k): d for k, d in zip(found["keys"], found["differences"], strict=True)}
        shared = [(d, by_key[tuple(k)]) for k, d in zip(e["keys"], e["differences"], strict=True) if tuple(k) in by_key]
        tested = rank_correlation(*zip(*shared, strict=True)) if shared else None
        if tested is not None:
            rho, p = tested
            entry = {"measure": measure, "keys": len(shared), "spearman": round(rho, 3), "permutation_p": round(p, 4)}
            out.append({k: e[k] for k in same} | entry)
    return out


def _statistics(label: str, m: dict, info: dict, repeat: int, scores: str = "final_returns") -> dict:
    """A method's numbers from ``compare``'s entry ``m``: the labels its seeds got by its last evaluation (one
    number if they all got the same) and the budget they asked, seeds, frames, per-seed scores (under the key
    ``scores``) and their mean, std and IQM with its 95% bootstrap interval; a preference method's learned reward
    measures per seed (:data:`REWARD_METRICS`, :func:`session_means`)."""
    asked = info["labels"]
    used = labels_used(info["run_dirs"], label, m["env_steps"]) if asked is not None else []
    steps = m["env_steps"]
    quality = {name: session_means(info["run_dirs"], label, steps, name) for name in REWARD_METRICS} if asked else {}
    return {
        "labels": (used[0] if len(set(used)) == 1 else used) if used else None,
        "labels_asked": asked,
        "seeds": m["seeds"],
        "keys": seed_keys(info["run_dirs"], label),
        "frames": m["env_steps"] * repeat,
        scores: [round(v, 2) for v in m["final_returns"]],
        "mean": round(m["mean"], 2),
        "std": round(m["std"], 2) if math.isfinite(m["std"]) else None,  # one seed: no sample std
        "iqm": round(m["iqm"], 2),
        # One seed has no interval: null, not NaN, which strict JSON readers refuse.
        "iqm_ci": [round(v, 2) if np.isfinite(v) else None for v in m["iqm_ci"]],
        **quality,
    }


def by_length(run_dirs: list[pathlib.Path]) -> dict[int, list[pathlib.Path]]:
    """The run directories grouped by the agent steps of their last evaluation, in the given order within each
    group: ``merge_runs`` keeps only the evaluations all of its runs share, so seeds of a 160k-frame and a
    300k-frame run of one method would silently merge at 160k."""
    out: dict[int, list[pathlib.Path]] = {}
    for run_dir in run_dirs:
        out.setdefault(int(load_runs(run_dir)[0][-1]), []).append(run_dir)
    return dict(sorted(out.items()))


def rows(task: str, run_dirs: list[pathlib.Path]) -> tuple[list[dict], dict]:
    """The task's rows, one per method and run length (:func:`by_length`), and its curves against frames
    (``{label: (frames, returns)}``; a method of several lengths is labelled "<method> (to <frames>k)")."""
    repeat = action_repeat(task)
    groups = [gather(dirs) for dirs in by_length(run_dirs).values()]
    repeated = {label for label in set().union(*(c for c, _ in groups)) if sum(label in c for c, _ in groups) > 1}
    out, frames = [], {}
    for curves, infos in groups:
        stats = compare(curves, None)["methods"]
        out += [
            {**_described(task, label, infos[label]), **_statistics(label, m, infos[label], repeat)}
            for label, m in stats.items()
        ]
        for label, (steps, returns) in curves.items():
            name = f"{label} (to {int(steps[-1]) * repeat // 1000}k)" if label in repeated else label
            frames[name] = (steps * repeat, returns)
    return out, frames


def figure(task: str, curves: dict, path: pathlib.Path, note: str = "") -> None:
    """Each method's mean +- std evaluation return against frames, as DrQ-v2 and SURF draw them, and each
    seed's curve (thin): DrQ-v2 fails on some walker seeds, its own curves included (RESULTS.md). ``note`` ends
    the title."""
    title = f"{task.removesuffix('_pixels')}, pixels{note}"
    curve_figure(curves, path, title, xlabel="frames (agent steps x action repeat)", seeds=True)


def _entries(task: str, curves: dict, infos: dict, scores: str) -> list[dict]:
    """Per method of ``gather``'s ``curves`` its pixels.json entry: described as a row, its statistics with the
    per-seed scores under the key ``scores`` (per seed the mean of its last 10 evaluations, all of them in a run of
    fewer), ``evaluations`` (each as ``[frames, seed-mean return]``) and ``last_evaluation`` (per seed its return
    at the last of them)."""
    repeat = action_repeat(task)
    stats = compare(curves, None)["methods"]
    out = []
    for label, (steps, returns) in curves.items():
        means = np.nanmean(returns, axis=1)
        kept = np.isfinite(means)
        evaluations = zip(steps[kept] * repeat, means[kept], strict=True)
        out.append(
            {
                **_described(task, label, infos[label]),
                **_statistics(label, stats[label], infos[label], repeat, scores=scores),
                "evaluations": [[int(f), round(float(r), 2)] for f, r in evaluations],
                # A seed without that evaluation: null, not NaN, which strict JSON readers refuse.
                "last_evaluation": [round(float(r), 2) if np.isfinite(r) else None for r in returns[-1]],
            }
        )
    return out


def stopped(task: str, run_dirs: list[pathlib.Path]) -> tuple[list[dict], dict]:
    """The stopped runs' entries and curves, one per run directory (each stopped at its own length, often
    on other code): per method ``evaluations`` (each as ``[frames, seed-mean return]``), ``frames`` (those
    of its last evaluation), ``last10_returns`` (per seed the mean of its last 10 evaluations, as
    ``final_returns``, but of a run that did not reach its end) with their mean, std and IQM interval, and the
    labels as the rows. The methods of one directory stopped together, so they compare at equal frames. Curves
    are labelled "(stopped; last evaluation at <frames>)"."""
    repeat = action_repeat(task)
    out, frames = [], {}
    for run_dir in run_dirs:
        curves, infos = gather([run_dir])
        for label, (steps, returns) in curves.items():
            frames[f"{label} (stopped; last evaluation at {int(steps[-1]) * repeat // 1000}k)"] = (
                steps * repeat,
                returns,
            )
        out += _entries(task, curves, infos, "last10_returns")
    return out, frames


def matched(task: str, agent_steps: int, run_dirs: list[pathlib.Path]) -> tuple[list[dict], dict]:
    """The methods of ``run_dirs`` compared at ``agent_steps``, a length every one of the runs reached, finished or
    stopped: each method's seeds pooled over the directories and its evaluations cut there (``gather``'s
    ``max_steps``). Per method ``matched_returns`` (per seed the mean of its evaluations to there, its last 10 if
    it has more) and ``last_evaluation`` (per seed the evaluation at ``agent_steps``), with the entries' other keys
    as :func:`stopped`'s, and the curves against frames."""
    curves, infos = gather(run_dirs, agent_steps)
    if any(int(steps[-1]) != agent_steps for steps, _ in curves.values()):
        raise ValueError(f"not every run of {task} has an evaluation at {agent_steps} agent steps")
    repeat = action_repeat(task)
    return _entries(task, curves, infos, "matched_returns"), {
        label: (steps * repeat, returns) for label, (steps, returns) in curves.items()
    }


PAPER_FIGURE: dict[str, tuple[str, dict[str, str]]] = {
    "walker_walk_pixels": (
        "Visual Walker (walker_walk)",
        {
            "drqv2 (float32 critic output)": "DrQ-v2, true reward",
            "pebble (rebel lam=0) 200 labels": "PEBBLE",
            "surf 200 labels (reward_update 20)": "PEBBLE+SURF",
            "rebel lam=0.001 200 labels": "REBEL, lambda 0.001",
        },
    ),
    "cheetah_run_pixels": (
        "Visual Cheetah (cheetah_run)",
        {
            "drqv2": "DrQ-v2, true reward",
            "pebble (rebel lam=0) 1000 labels": "PEBBLE",
            "surf 1000 labels (reward_update 20) (to 300k)": "PEBBLE+SURF",
            "rebel lam=0.001 1000 labels": "REBEL, lambda 0.001",
        },
    ),
}
"""Pixel task -> (panel title, {curve label of :func:`rows`: legend name}): the paper's pixel panels, each method
at its longest whole runs, beside DrQ-v2 on the true reward (:func:`paper_figure`)."""


def paper_figure(curves: dict[str, dict], table: list[dict], path: pathlib.Path) -> None:
    """Writes ``path``: one panel per task of :data:`PAPER_FIGURE`, each method's mean +- std evaluation return
    over its seeds against frames (``curves[task]``, as :func:`rows` names them), the preference methods' legend
    naming the labels their seeds got (the ``table`` row of that method and length). A curve missing is an
    error."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(PAPER_FIGURE), figsize=(6 * len(PAPER_FIGURE), 4.2))
    for ax, (task, (title, names)) in zip(np.atleast_1d(axes), PAPER_FIGURE.items(), strict=True):
        missing = [label for label in names if label not in curves.get(task, {})]
        if missing:
            raise ValueError(f"{task}: no curves {missing} among {sorted(curves.get(task, {}))}")
        for label, name in names.items():
            frames, returns = curves[task][label]
            method = re.sub(r" \(to \d+k\)$", "", label)
            same = (task.removesuffix("_pixels"), method, int(frames[-1]))
            (row,) = (r for r in table if (r["task"], r["method"], r["frames"]) == same)
            name += f", {row['labels']} labels" if row["labels"] is not None else ""
            plot_curves(ax, {name: (frames, returns)})
        ax.set_xlabel("frames (agent steps x action repeat)")
        ax.set_title(title)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    table, early, same, pairs = [], [], [], []
    whole: dict[str, dict] = {}  # task -> the whole runs' curves, for the paper's figure
    for task in sorted(set(RUNS) | set(STOPPED)):
        task_rows, curves = rows(task, [RESULTS / "runs" / log for log in RUNS[task]]) if task in RUNS else ([], {})
        whole[task] = curves
        task_stopped, stopped_curves = stopped(task, [RESULTS / "runs" / log for log in STOPPED.get(task, [])])
        short = task.removesuffix("_pixels")
        figure(task, curves | stopped_curves, RESULTS / f"pixels_{short}.png")
        table += task_rows
        early += task_stopped
        task_matched = []
        if task in MATCHED:
            agent_steps, logs = MATCHED[task]
            task_matched, matched_curves = matched(task, agent_steps, [RESULTS / "runs" / log for log in logs])
            note = f", equal frames (runs pooled to {action_repeat(task) * agent_steps // 1000}k)"
            figure(task, matched_curves, RESULTS / f"pixels_{short}_matched.png", note)
            same += task_matched
        for a, b in PAIRED.get(task, []):
            pairs += paired(task_rows, a, b, "final_returns") + paired(task_matched, a, b, "matched_returns")
            for name in REWARD_METRICS:  # Whether b's learned reward is better than a's on the same keys.
                pairs += paired(task_rows, a, b, name) + paired(task_matched, a, b, name)
    paper_figure(whole, table, RESULTS / "pixels_paper.png")
    coupled, both = coupling(pairs), pooled(pairs, table)
    out = {"rows": table, "stopped": early, "matched": same, "paired": pairs, "coupling": coupled, "pooled": both}
    (RESULTS / "pixels.json").write_text(json.dumps(out, indent=1) + "\n")
    print("| task | method | seeds | frames | mean +- std | IQM [95% CI] |")
    print("|---|---|---:|---:|---:|---:|")
    for r in table:
        low, high = r["iqm_ci"]
        print(
            f"| {r['task']} | {r['method']} | {r['seeds']} | {r['frames']:,} | {r['mean']:.1f} +- {_std(r['std'])} "
            f"| {r['iqm']:.1f} [{low}, {high}] |"
        )
    for r in early:
        shown = ", ".join(f"{f // 1000}k: {v:.0f}" for f, v in r["evaluations"])
        last10 = ", ".join(f"{v:.1f}" for v in r["last10_returns"])
        got = f", {r['labels']} labels" if r["labels"] is not None else ""
        print(f"\n{r['task']} {r['method']} ({r['seeds']} seed(s){got}, stopped at {r['frames']:,} frames): {shown}")
        low, high = r["iqm_ci"]
        print(f"  per seed, the mean of its last 10 evaluations: {last10}; IQM {r['iqm']:.1f} [{low}, {high}]")
    if same:
        print("\n| task | method | seeds | frames | per seed: mean evaluation | mean +- std | IQM [95% CI] |", end="")
        print(" per seed: last |")
        print("|---|---|---:|---:|---|---:|---:|---|")
    for r in same:
        low, high = r["iqm_ci"]
        scores = ", ".join(f"{v:.1f}" for v in r["matched_returns"])
        last = ", ".join("-" if v is None else f"{v:.1f}" for v in r["last_evaluation"])
        print(
            f"| {r['task']} | {r['method']} | {r['seeds']} | {r['frames']:,} | {scores} | {r['mean']:.1f} +- "
            f"{_std(r['std'])} | {r['iqm']:.1f} [{low}, {high}] | {last} |"
        )
    _quality_table(table + same)
    _paired_table(pairs)
    print("\n| task | frames | b minus a | keys | Spearman: return against reward-correlation differences | p |")
    print("|---|---:|---|---:|---:|---:|")
    for c in coupled:
        print(f"| {c['task']} | {c['frames']:,} | {c['b']} minus {c['a']} | {c['keys']} | {c['spearman']} "
              f"| {c['permutation_p']} |")  # fmt: skip
    _pooled_table(both)


def _quality_table(entries: list[dict]) -> None:
    """Per preference method its learned reward's session measures (:data:`REWARD_METRICS`), seed means."""
    print("\n| task | method | seeds | frames | accuracy on new pairs | correlation with the true reward |")
    print("|---|---|---:|---:|---:|---:|")
    for r in entries:
        if "reward_accuracy_new" in r:
            cells = [np.mean([v for v in r[name] if v is not None]) for name in REWARD_METRICS]
            print(f"| {r['task']} | {r['method']} | {r['seeds']} | {r['frames']:,} | {cells[0]:.3f} | {cells[1]:.3f} |")


def _paired_table(entries: list[dict]) -> None:
    """Each :func:`paired` entry: method b minus method a, key by key."""
    print(
        "\n| task | frames | scores | b minus a | keys | per key | mean +- s.e. [95% CI] | positive | sign test p "
        "| signed-rank p | detectable at 80% power (keys: difference) |"
    )
    print("|---|---:|---|---|---:|---|---:|---:|---:|---:|---|")
    for e in entries:
        low, high = e["mean_ci"]
        digits = 3 if e["scores"] in REWARD_METRICS else 1
        diffs = ", ".join(f"{d:+.{digits}f}" for d in e["differences"])
        detectable = ", ".join(f"{n}: {v}" for n, v in e["detectable"].items())
        print(
            f"| {e['task']} | {e['frames']:,} | {e['scores']} | {e['b']} minus {e['a']} | {len(e['keys'])} | {diffs} "
            f"| {e['mean']:+.{digits}f} +- {e['sem']} [{low}, {high}] | {e['positive']} of {e['pairs']} "
            f"| {e['sign_test_p']} | {e['signed_rank_p']} | {detectable} |"
        )


def _pooled_table(entries: list[dict]) -> None:
    """Each :func:`pooled` entry: the tasks' keys together, in units of each task's DrQ-v2 mean."""
    print("\n| comparison | tasks: frames, keys, divided by | per key | mean +- s.e. [95% CI] | positive ", end="")
    print("| sign test p | signed-rank p | detectable at 80% power (keys: difference) |")
    print("|---|---|---|---:|---:|---:|---:|---|")
    for e in entries:
        tasks = "; ".join(
            f"{t['task']} {t['frames'] // 1000}k, {t['keys']}, {t['reference_mean']:.1f}" for t in e["tasks"]
        )
        low, high = e["mean_ci"]
        detectable = ", ".join(f"{n}: {v}" for n, v in e["detectable"].items())
        print(
            f"| {e['comparison']} | {tasks} | {', '.join(f'{d:+.3f}' for d in e['differences'])} | {e['mean']:+.3f} +- "
            f"{e['sem']} [{low}, {high}] | {e['positive']} of {e['pairs']} | {e['sign_test_p']} | {e['signed_rank_p']} "
            f"| {detectable} |"
        )


if __name__ == "__main__":
    main()
