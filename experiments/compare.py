"""The paper's comparison figure from finished runs: curves, IQM with bootstrap intervals, sample efficiency.

Usage:
  python experiments/compare.py RUN_DIR [RUN_DIR ...] --name NAME [--reference LABEL]
      [--methods LABEL ...] [--max-steps N] [--threshold R] [--caveat TEXT] [--out-dir DIR]

Each run directory (``python -m rebel_jax.train``) contributes one method per grid point: a
REBEL run with ``--lam-grid`` is split into its lambdas (``rebel lam=-0.1``; lambda 0 is
labelled ``pebble (rebel lam=0)``, which it equals bit for bit; a method composed with REBEL's term, such as
examples/rebel_on_qpa.py's, by its name: ``rebel_qpa lam=0``), a ``--teacher-grid`` run into
its teachers (``..., noisy``; a single ``--teacher`` other than the oracle is named the same way); other
runs are labelled by their algo, and budgets other than 100 labels are named (``pebble 1000 labels``), as are
a SURF ``reward_update`` other than 1000, a pixel reward stepped as SURF's (``pixel_reward.per_member_adam``),
one trained in another precision than tf32, and a pixel agent whose critics' output layer is float32
(``drqv2.critic_out_f32``).
A REBEL term other than the paper's (on-policy V, lower bound, raw) and a reward output other than tanh are named
in brackets (``rebel lam=0.01 (replay V, sigmoid output)``), so that variants never merge.
``--methods`` keeps a subset in a given order; ``--max-steps`` cuts every curve (to compare runs of
different lengths at equal steps).
Run directories of the same method (e.g. seeds split over several programs with different
``--seed``) are merged; they must share task, algo, preset, labels, teacher, lambda, num_envs and utd (``SHARED``).
Writes ``DIR/NAME.json`` (per method: final returns per seed, mean, std, IQM with its 95% percentile-bootstrap
interval, mean curve, and the sample-efficiency ratio against ``--reference``: env steps the other method needs to
reach a common return over the steps the reference needs; and what the numbers are: those shared settings, and
every merged run's device and date (sorted, each once), command and ``train_seed`` (per run)) and
``DIR/NAME.png`` (mean +- std curves and IQM bars), and prints a Markdown table for RESULTS.md.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from analysis import (  # noqa: E402
    bootstrap_ci,
    common_threshold,
    distinct_evaluations,
    final_returns,
    iqm,
    load_runs,
    merge_runs,
    plot_curves,
    plot_iqm,
    preset_name,
    sample_efficiency_ratio,
    sample_std,
)

from rebel_jax.config import AGENTS  # noqa: E402
from rebel_jax.preference import teachers  # noqa: E402

RESULTS = pathlib.Path(__file__).parents[1] / "results"


def _learns_from_preferences(cfg: dict) -> bool:
    """Every method but the agents on the true reward, registered here or not (a method of an example file)."""
    return cfg["algo"] not in AGENTS


def _teacher_name(knobs: dict) -> str:
    """The B-Pref preset a run's teacher settings equal, else the settings themselves."""
    named = [name for name, t in teachers.PRESETS.items() if dataclasses.asdict(t) == knobs]
    return named[0] if named else json.dumps(knobs)


def _info(run_dir: pathlib.Path, lam, teacher) -> dict:
    """What a method's numbers are: the run's settings, device, date and command."""
    cfg = json.loads((run_dir / "config.json").read_text())
    meta = json.loads((run_dir / "meta.json").read_text())
    preference = _learns_from_preferences(cfg)
    return {
        "task": cfg["env"]["task"],
        "algo": cfg["algo"],
        "preset": preset_name(meta["command"]),
        "labels": cfg["feedback"]["labels"] if preference else None,
        "teacher": (teacher or _teacher_name(cfg["teacher"])) if preference else None,
        "lam": lam,
        "num_envs": cfg["env"]["num_envs"],
        "utd": cfg["sac"]["utd"],
        "train_seed": cfg["train"]["seed"],  # seed i's key is fold_in(PRNGKey(train_seed), i) in every program
        "device": meta["devices"][0],
        "date": meta["started"][:10],
        "command": meta["command"],
    }


def _term_settings(cfg: dict) -> list[str]:
    """How a REBEL run's agent-preference term differs from the paper's (on-policy V, lower bound, raw).

    Runs from before ``rebel.source`` existed (no such key) used the replay window, as ``replay`` does now.
    """
    rebel = cfg["rebel"]
    out = []
    if rebel.get("source", "replay") == "replay":
        out.append("replay V" + (f", {rebel['estimator']} estimator" if rebel["estimator"] != "discounted" else ""))
    if rebel.get("form", "lower_bound") != "lower_bound":
        out.append(rebel["form"])
    if rebel.get("normalize"):
        out.append("normalized")
    return out


def methods(run_dir: pathlib.Path) -> dict[str, tuple[tuple[np.ndarray, np.ndarray], dict]]:
    """The run's curves per method label: ``{label: ((steps, returns (evals, seeds)), info)}``.

    A grid run (``--lam-grid``, ``--teacher-grid``) is split into one label per grid point; ``info["columns"]``
    are the label's columns of the run's per-seed metrics.
    """
    cfg = json.loads((run_dir / "config.json").read_text())
    meta = json.loads((run_dir / "meta.json").read_text())
    steps, returns = load_runs(run_dir)
    columns = returns.shape[1]
    lams = meta.get("lams") or [None] * columns
    # Outside a --teacher-grid the run's own teacher names the method unless it is the oracle, so that runs
    # of one method under different teachers never merge.
    own = _teacher_name(cfg["teacher"]) if _learns_from_preferences(cfg) else None
    teachers = meta.get("teachers") or [None if own == "oracle" else own] * columns
    out: dict[str, tuple[list[int], dict]] = {}
    for i, (lam, teacher) in enumerate(zip(lams, teachers, strict=True)):
        if lam is None:
            label = cfg["algo"]
        elif cfg["algo"] == "rebel":
            label = "pebble (rebel lam=0)" if lam == 0 else f"rebel lam={lam:g}"
        else:  # a method composed with REBEL's term (examples/rebel_on_qpa.py): its lambdas, 0 included
            label = f"{cfg['algo']} lam={lam:g}"
        settings = _term_settings(cfg) if lam else []
        if _learns_from_preferences(cfg) and cfg["reward"].get("output", "tanh") != "tanh":
            settings.append(f"{cfg['reward']['output']} output")
        label += f" ({', '.join(settings)})" if settings else ""
        if _learns_from_preferences(cfg) and cfg["feedback"]["labels"] != 100:
            label += f" {cfg['feedback']['labels']} labels"
        if cfg["algo"] == "surf" and cfg.get("surf", {}).get("reward_update", 1000) != 1000:  # SURF's walker value
            label += f" (reward_update {cfg['surf']['reward_update']})"
        pixel_reward = cfg.get("pixel_reward", {})  # absent: an earlier run, the defaults below
        if pixel_reward.get("per_member_adam"):
            label += " (SURF's reward Adam)"
        if pixel_reward.get("precision", "tf32") != "tf32":
            label += f" ({pixel_reward['precision']} reward)"
        if cfg.get("drqv2", {}).get("critic_out_f32"):  # the pixel agent's critics' output layer in float32
            label += " (float32 critic output)"
        label += f", {teacher}" if teacher else ""
        out.setdefault(label, ([], _info(run_dir, lam, teacher)))[0].append(i)
    return {label: ((steps, returns[:, idx]), info | {"columns": idx}) for label, (idx, info) in out.items()}


SHARED = ("task", "algo", "preset", "labels", "teacher", "lam", "num_envs", "utd")
"""Settings that every run of one method label must share for ``gather`` to pool their seeds."""


def pooled_info(infos: list[dict], run_dirs: list[pathlib.Path]) -> dict:
    """One method's info from the infos of its runs (in ``run_dirs`` order): the :data:`SHARED` settings, which
    must agree, and the provenance of every run: ``device`` and ``date`` (sorted, each once), ``command`` and
    ``train_seed`` (per run, in the order of ``run_dirs``), and ``run_dirs``."""
    for key in SHARED:
        values = {json.dumps(info[key]) for info in infos}
        if len(values) > 1:
            runs = [str(d) for d in run_dirs]
            raise ValueError(f"cannot pool {runs} as one method: their {key} values differ ({sorted(values)})")
    first = {key: value for key, value in infos[0].items() if key != "columns"}  # columns: one run's own
    return first | {
        "device": sorted({info["device"] for info in infos}),
        "date": sorted({info["date"] for info in infos}),
        "command": [info["command"] for info in infos],
        "train_seed": [info["train_seed"] for info in infos],
        "run_dirs": list(run_dirs),
    }


def gather(run_dirs: list[pathlib.Path], max_steps: int | None = None):
    """Every method's curve (seeds of run directories with the same label merged) and its run info.

    Returns ``(curves, infos)``, both keyed by label; curves stop at ``max_steps`` if given. A label's info is
    :func:`pooled_info` of its runs: the settings they share, and every run's device, date, command and seed.
    """
    parts: dict[str, list] = {}
    found: dict[str, list[tuple[pathlib.Path, dict]]] = {}
    for run_dir in run_dirs:
        for label, (curve, info) in methods(run_dir).items():
            parts.setdefault(label, []).append(curve)
            found.setdefault(label, []).append((run_dir, info))
    infos = {label: pooled_info([i for _, i in runs], [d for d, _ in runs]) for label, runs in found.items()}
    curves = {label: merge_runs(*runs) for label, runs in parts.items()}
    if max_steps is not None:
        curves = {label: (steps[steps <= max_steps], r[steps <= max_steps]) for label, (steps, r) in curves.items()}
    return curves, infos


def compare(
    curves: dict[str, tuple[np.ndarray, np.ndarray]], reference: str | None, threshold: float | None = None
) -> dict:
    """Per-method statistics (see the module docstring) of ``gather``'s curves.

    ``threshold`` is the return the sample-efficiency ratios count steps to (default:
    ``common_threshold`` of the final means, one every method reaches); a method whose mean
    curve never reaches it gets a NaN ratio.
    """
    finals = {label: final_returns(returns) for label, (_, returns) in curves.items()}
    if threshold is None:
        threshold = common_threshold(np.nanmean(f) for f in finals.values())
    reference = reference or next(iter(curves))
    out = {"threshold": threshold, "reference": reference, "methods": {}}
    for label, (steps, returns) in curves.items():
        scores = finals[label][np.isfinite(finals[label])]
        mean_curve, std_curve = np.nanmean(returns, axis=1), np.nanstd(returns, axis=1)
        ref_steps, ref_returns = curves[reference]
        ratio = sample_efficiency_ratio(
            distinct_evaluations((ref_steps, np.nanmean(ref_returns, axis=1)[:, None])),
            distinct_evaluations((steps, mean_curve[:, None])),
            threshold,
        )
        out["methods"][label] = {
            "seeds": int(returns.shape[1]),
            "env_steps": int(steps[-1]),
            "final_returns": scores.tolist(),
            "mean": float(scores.mean()),
            "std": sample_std(scores),
            "iqm": float(iqm(scores)),
            "iqm_ci": list(bootstrap_ci(scores, iqm)),
            "steps_ratio_vs_reference": ratio,
            "curve": {"env_steps": steps.tolist(), "mean": mean_curve.tolist(), "std": std_curve.tolist()},
        }
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("run_dirs", nargs="+", type=pathlib.Path)
    p.add_argument("--name", required=True)
    p.add_argument("--reference", help="method label the sample-efficiency ratios are relative to (default: first)")
    p.add_argument("--out-dir", type=pathlib.Path, default=RESULTS)
    p.add_argument("--methods", nargs="+", help="keep only these method labels, in this order (default: all)")
    p.add_argument("--max-steps", type=int, help="cut every curve at this many env steps")
    p.add_argument("--threshold", type=float, help="return for the sample-efficiency ratios (default: common)")
    p.add_argument("--caveat", help="a warning stored with the numbers (e.g. a bug the runs had)")
    args = p.parse_args()
    curves, infos = gather(args.run_dirs, args.max_steps)
    if args.methods:
        missing = [m for m in args.methods if m not in curves]
        if missing:
            raise SystemExit(f"error: --methods {missing} not among {list(curves)}")
        curves = {m: curves[m] for m in args.methods}
    result = compare(curves, args.reference, args.threshold)
    if args.caveat:
        result = {"caveat": args.caveat, **result}
    for label, entry in result["methods"].items():  # What the numbers are (not gather's bookkeeping).
        entry.update({k: v for k, v in infos[label].items() if k != "run_dirs"})
    args.out_dir.mkdir(parents=True, exist_ok=True)
    (args.out_dir / f"{args.name}.json").write_text(json.dumps(result, indent=1))
    fig, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    plot_curves(left, curves)
    plot_iqm(right, {label: m["final_returns"] for label, m in result["methods"].items()})
    left.set_title(args.name)
    fig.tight_layout()
    fig.savefig(args.out_dir / f"{args.name}.png", dpi=120)
    ratio = f"steps to {result['threshold']:.0f} / those of {result['reference']}"
    print(f"| method | seeds | env steps | final mean +- std | IQM [95% CI] | {ratio} |")
    print("|---|---:|---:|---:|---:|---:|")
    for label, m in result["methods"].items():
        low, high = m["iqm_ci"]
        print(
            f"| {label} | {m['seeds']} | {m['env_steps']:,} | {m['mean']:.1f} +- {m['std']:.1f} "
            f"| {m['iqm']:.1f} [{low:.1f}, {high:.1f}] | {m['steps_ratio_vs_reference']:.2f} |"
        )


if __name__ == "__main__":
    main()
