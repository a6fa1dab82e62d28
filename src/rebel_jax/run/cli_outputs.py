"""What a command-line run leaves at its end: ``final.json``'s content, the summary table, the learning curve and
the evaluation clip."""

from __future__ import annotations

import functools
import pathlib
import sys

import jax
import jax.numpy as jnp
import numpy as np

from rebel_jax.run import plots, video
from rebel_jax.run.cli_args import Args, swept_knob
from rebel_jax.run.human import HumanError
from rebel_jax.train import Trainer, seed_keys


def sample_std(values: np.ndarray) -> float:
    """The sample standard deviation (``ddof=1``), as the results tables give it; NaN for one value."""
    return float(np.std(values, ddof=1)) if np.size(values) > 1 else float("nan")


def _final_result(
    final: np.ndarray,
    random: np.ndarray,
    ever_diverged: np.ndarray,
    names: list[str],
    success: np.ndarray | None = None,
) -> dict:
    """``final.json``'s content: the status, the policy's and random actions' returns per column and their means,
    and on a task that reports success (``success``: the policy's success rate per column) that rate and its mean."""
    result = {
        "status": "diverged" if ever_diverged.any() else "completed",
        "diverged": [names[i] for i in np.flatnonzero(ever_diverged)],
        "final_eval_return": final,
        "mean": float(final.mean()),  # NaN (written as null) if any seed's is: no silent nanmean
        "std": sample_std(final),  # ddof 1; null for one seed
        "random_return": random,
        "random_mean": float(random.mean()),
    }
    if success is not None:  # the fraction of each column's evaluation episodes that succeeded
        result["final_eval_success"] = success
        result["success_mean"] = float(success.mean())
    return result


SUMMARY_METRICS = ("labels_used", "reward_correlation", "reward_correlation_return")
"""Logged per-column metrics whose last finite value the summary table shows (preference methods)."""


def last_logged(run_dir: pathlib.Path, columns: int) -> dict[str, np.ndarray]:
    """Per column, the last finite value of each of :data:`SUMMARY_METRICS` in ``metrics.jsonl`` (NaN if none)."""
    last = {name: np.full(columns, np.nan) for name in SUMMARY_METRICS}
    for record in plots.records(run_dir):
        for name in SUMMARY_METRICS:
            if name in record:
                values = np.asarray(plots.per_seed(record[name]), float)
                last[name] = np.where(np.isfinite(values), values, last[name])
    return last


def method_metrics(run_dir: pathlib.Path, columns: int) -> dict[str, dict]:
    """The method's own metrics (``NAME/KEY``) for ``final.json``: per column the last finite value in
    ``metrics.jsonl`` (None if none) and their mean over the columns that have one."""
    last: dict[str, np.ndarray] = {}
    for record in plots.records(run_dir):
        for name, value in record.items():
            if "/" in name and not name.endswith("_mean"):
                values = np.asarray(plots.per_seed(value), float)
                last[name] = np.where(np.isfinite(values), values, last.get(name, np.full(columns, np.nan)))
    return {
        name: {
            "last": [None if np.isnan(v) else float(v) for v in values],
            "mean": float(np.nanmean(values)) if np.isfinite(values).any() else None,
        }
        for name, values in sorted(last.items())
    }


def summary_table(names: list[str], random: np.ndarray, final: np.ndarray, logged: dict[str, np.ndarray]) -> str:
    """The table printed at the end of a run: one row per column and their mean.

    Columns: the random policy's and the trained policy's evaluation return (the same initial
    states), the labels used, and the learned reward's Pearson correlation with the true one
    at the last feedback session, per step and over segment returns (``-`` for ``sac``).
    """
    header = ("", "random-policy return", "final return", "labels used", "reward corr. per step", "per segment")
    rows = [header]
    cells = [random, final, *(logged[k] for k in SUMMARY_METRICS)]
    formats = ("{:.1f}", "{:.1f}", "{:.0f}", "{:.2f}", "{:.2f}")

    def fmt(values, i):
        return [f.format(v[i]) if np.isfinite(v[i]) else "-" for f, v in zip(formats, values, strict=True)]

    rows += [(name, *fmt(cells, i)) for i, name in enumerate(names)]
    means = [np.array([np.mean(v)]) for v in cells]  # NaN where any column's is undefined
    rows.append(("mean", *fmt(means, 0)))
    widths = [max(len(row[j]) for row in rows) for j in range(len(header))]
    lines = [
        "  ".join(
            cell.ljust(w) if j == 0 else cell.rjust(w) for j, (cell, w) in enumerate(zip(row, widths, strict=True))
        )
        for row in rows
    ]
    return "\n".join(lines)


def _eval_clip(args: Args, trainer: Trainer, policy, run_dir: pathlib.Path) -> pathlib.Path | None:
    """Writes ``eval.gif``: ``args.video_steps`` steps of the first column's deterministic policy; its path.

    ``policy``: ``trainer.policy_params`` of every column, on the host. A pixel run's policy sees its own 84x84
    frame stacks; the clip is drawn by a camera of its own, as a state run's.
    """
    if args.time_limit:
        # Runs split over time-limited calls have no time budgeted for compiling the clip.
        print(f"eval.gif skipped under --time-limit; render it with: python -m rebel_jax.run.video {run_dir}")
        return None
    try:
        import imageio  # noqa: F401
    except ImportError:
        print(f"eval.gif skipped: imageio is not installed; later: python -m rebel_jax.run.video {run_dir}")
        return None
    params = jax.tree.map(lambda x: jnp.asarray(x[0]), policy)
    key = seed_keys(args.config.train.seed, 1)[0]  # any seed (PRNGKey keeps 32 bits)
    path = run_dir / "eval.gif"
    try:
        act = functools.partial(trainer.mean_action, params)
        video.policy_video(trainer.env, act, key, path, args.video_steps, 120)
    except HumanError as err:  # the quadruped's clip needs MuJoCo's renderer, which found no OpenGL context
        print(f"eval.gif skipped: {err}")
        return None
    return path


def _learning_curve(args: Args, run_dir: pathlib.Path, random: np.ndarray) -> pathlib.Path | None:
    """Writes ``learning_curve.png``: the evaluation return of each group of seeds (lambda, teacher), and random's.

    A failure here is a warning, not the run's: it comes after ``final.json``, and the figure can be drawn again
    from ``metrics.jsonl`` (``python experiments/curves.py RUN_DIR --name NAME``).
    """
    try:
        return _draw_learning_curve(args, run_dir, random)
    except Exception as error:  # Any plotting failure: the run's results are already on disk.
        print(
            f"warning: learning_curve.png not written ({type(error).__name__}: {error}); final.json and "
            f"metrics.jsonl are (experiments/curves.py {run_dir} --name NAME draws it)",
            file=sys.stderr,
        )
        return None


def _draw_learning_curve(args: Args, run_dir: pathlib.Path, random: np.ndarray) -> pathlib.Path:
    """:func:`_learning_curve`'s figure: the success rate on a task that reports success (as the papers show
    Meta-World's), else the return with the random policy's."""
    cfg = args.config
    success = any(r.get("eval_success") is not None for r in plots.records(run_dir))
    steps, returns = plots.load_runs(run_dir, "eval_success" if success else "eval_return")
    runs = {}
    for i in range(0, args.columns, args.seeds):
        lam, teacher = args.grid()[i]
        which = ([f"lambda {lam:g}"] if args.lam_grid else []) + ([f"teacher {teacher}"] if teacher else [])
        runs[", ".join(which) or cfg.algo] = (steps, returns[:, i : i + args.seeds])
    labels = f", {cfg.feedback.labels} labels" if cfg.preference and not args.host_teacher else ""
    title = f"{cfg.algo} on {cfg.env.task} ({cfg.env.episode_length}-step episodes{labels})"
    if success:
        return plots.write_learning_curve(run_dir / "learning_curve.png", runs, title, ylabel="evaluation success rate")
    return plots.write_learning_curve(run_dir / "learning_curve.png", runs, title, float(np.mean(random)))


def report(args: Args, run_dir: pathlib.Path, result: dict, files: list, final: np.ndarray, random: np.ndarray) -> None:
    """What a finished run prints: the summary table per column, the files written, each group's final return
    (mean +- sample std over its seeds; on a task that reports success, its success rate too) and the seeds that
    diverged."""
    cfg = args.config
    success = result.get("final_eval_success")
    success = None if success is None else np.asarray(success, float)
    names, grid = args.column_names(), args.grid()
    print(
        f"\n{cfg.algo} on {cfg.env.task}: evaluation returns ({cfg.train.eval_episodes} episodes of "
        f"{cfg.env.episode_length} steps per seed, the same initial states for the random policy)"
    )
    print(summary_table(names, random, final, last_logged(run_dir, args.columns)))
    for path in files:
        if path is not None:
            print(f"wrote {path}")
    for i in range(0, args.columns, args.seeds):
        part = final[i : i + args.seeds]
        lam, teacher = grid[i]
        which = ([f"lambda {lam:g}"] if swept_knob(cfg) else []) + ([f"teacher {teacher}"] if teacher else [])
        which = f" ({', '.join(which)})" if which else ""
        spread = f" +- {sample_std(part):.1f} (sample std)" if part.size > 1 else ""
        rate = ""
        if success is not None:  # a task that reports success: the rate, as the return
            rates = success[i : i + args.seeds]
            rate = f", success rate {rates.mean():.2f}"
            rate += f" +- {sample_std(rates):.2f} (sample std)" if rates.size > 1 else ""
        print(f"final evaluation return over {args.seeds} seed(s){which}: {part.mean():.1f}{spread}{rate}")
    if result["diverged"]:
        print(f"warning: diverged during the run: {', '.join(result['diverged'])}", file=sys.stderr)
    print(f"run directory: {run_dir}")
