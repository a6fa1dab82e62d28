"""Learning curves of run directories: read from ``metrics.jsonl`` and plotted with matplotlib.

The one place for plotting curves: the CLI writes ``learning_curve.png`` at the end of a run with
:func:`write_learning_curve`, and ``experiments/analysis.py`` (hence ``curves.py`` and
``compare.py``) re-exports :func:`load_runs` and :func:`plot_curves`. matplotlib is imported
only when a figure is drawn, with its non-interactive Agg backend.
"""

from __future__ import annotations

import json
import math
import os
import pathlib
from collections.abc import Mapping

import numpy as np

Curve = tuple[np.ndarray, np.ndarray]
"""``(env_steps (evals,), returns (evals,) or (evals, seeds))``; a 2-D curve is averaged over seeds."""


def nanmean_std(x: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and (population) standard deviation over the finite entries; NaN where none are."""
    finite = np.isfinite(x)
    count = finite.sum(axis=axis)
    safe = np.maximum(count, 1)
    mean = np.where(finite, x, 0.0).sum(axis=axis) / safe
    dev = np.where(finite, x - np.expand_dims(mean, axis), 0.0)
    std = np.sqrt((dev**2).sum(axis=axis) / safe)
    empty = count == 0
    return np.where(empty, np.nan, mean), np.where(empty, np.nan, std)


def records(run_dir: pathlib.Path) -> list[dict]:
    """The rounds of ``metrics.jsonl`` in step order, one per ``env_steps``.

    A resumed run appends the rounds after its last checkpoint again; the last record of a
    step wins, as it is the one the finished run continued from.
    """
    by_step = {}
    for line in (pathlib.Path(run_dir) / "metrics.jsonl").read_text().splitlines():
        if line.strip():
            record = json.loads(line)
            by_step[record["env_steps"]] = record
    return [by_step[s] for s in sorted(by_step)]


def per_seed(value) -> list[float]:
    """A logged per-seed list (or a scalar, for one seed) with ``None`` as NaN."""
    values = value if isinstance(value, list) else [value]
    return [math.nan if v is None else float(v) for v in values]


def load_runs(run_dir: str | os.PathLike, metric: str = "eval_return") -> Curve:
    """The per-seed evaluation curves of one run directory.

    Args:
      run_dir: a directory written by ``python -m rebel_jax.train`` (``metrics.jsonl``).
      metric: the logged evaluation measure: ``eval_return``, or ``eval_success`` on a task that reports success.

    Returns:
      ``(steps (evals,) int, returns (evals, seeds) float)``: one row per round with an
      evaluation return for at least one seed, NaN for the seeds without one (``null``).
      Rounds repeat the last finished evaluation (see ``analysis.distinct_evaluations``).
    """
    rounds = records(pathlib.Path(run_dir))
    rows = [(r["env_steps"], per_seed(r.get(metric))) for r in rounds]
    rows = [(s, v) for s, v in rows if any(math.isfinite(x) for x in v)]
    # The seed count comes from the rounds that log ``eval_return`` (a list, of nulls before the first
    # evaluation): a pixel run's first rounds log none at all, which read as one seed.
    logged = [per_seed(r[metric]) for r in rounds if r.get(metric) is not None]
    seeds = max((len(v) for v in logged), default=0)
    steps = np.array([s for s, _ in rows], dtype=np.int64)
    returns = np.array([v for _, v in rows], dtype=float).reshape(len(rows), seeds)
    return steps, returns


def plot_curves(
    ax, runs: Mapping[str, Curve], seeds: bool = False, ylabel: str = "evaluation return (true reward)"
) -> None:
    """Mean +- std over seeds of the evaluation return of each run, one line and band per label.

    Args:
      ax: a matplotlib ``Axes``.
      runs: ``{label: (steps (evals,), returns (evals, seeds))}``, e.g. from ``load_runs``.
      seeds: also draw each seed's curve, thin, in its label's colour (a band over few seeds hides a
        seed that failed, as DrQ-v2's walker seeds sometimes do).
      ylabel: what the curves measure.
    """
    for label, (steps, returns) in runs.items():
        r = np.asarray(returns, dtype=float)
        r = r[:, None] if r.ndim == 1 else r
        mean, std = nanmean_std(r, axis=1)
        n = r.shape[1]
        (line,) = ax.plot(steps, mean, label=f"{label} ({n} seed{'' if n == 1 else 's'})")
        ax.fill_between(steps, mean - std, mean + std, color=line.get_color(), alpha=0.25, linewidth=0)
        if seeds and n > 1:
            kept = np.isfinite(r)
            for j in range(n):
                ax.plot(np.asarray(steps)[kept[:, j]], r[kept[:, j], j], color=line.get_color(), lw=0.7, alpha=0.6)
    ax.set_xlabel("environment steps")
    ax.set_ylabel(ylabel)
    ax.legend()


def write_learning_curve(
    path: str | os.PathLike,
    runs: Mapping[str, Curve],
    title: str,
    random_return: float | None = None,
    ylabel: str = "evaluation return (true reward)",
) -> pathlib.Path:
    """Draws evaluation curves (mean +- std over seeds, :func:`plot_curves`) to the image ``path`` (PNG).

    Args:
      path: the image file.
      runs: ``{label: (steps (evals,), returns (evals, seeds))}``, e.g. the column groups of one run.
      title: the figure's title.
      random_return: drawn as a dashed horizontal line (the random policy's return), if given and finite.
      ylabel: what the curves measure.

    Returns:
      ``path``.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    try:
        plot_curves(ax, runs, ylabel=ylabel)
        if random_return is not None and math.isfinite(random_return):
            ax.axhline(random_return, color="gray", linestyle="--", label=f"random policy ({random_return:.1f})")
            ax.legend()
        ax.set_title(title)
        fig.tight_layout()
        fig.savefig(path, dpi=100)
    finally:
        plt.close(fig)
    return pathlib.Path(path)
