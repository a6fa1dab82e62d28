"""Statistics and plots for comparing methods over seeds and tasks, with ``rliable``.

Follows Agarwal et al. 2021 through its library, ``rliable``: a method's per-run scores are
summarised by their interquartile mean (IQM, ``rliable.metrics.aggregate_iqm``) with a
percentile bootstrap confidence interval that, when several tasks are aggregated, resamples
the runs of each task independently (``rliable.library.get_interval_estimates``, its
stratified bootstrap); ``performance_profile`` gives rliable's score distributions. A "run"
is one seed: a run directory written by ``python -m rebel_jax.train --run-dir DIR`` holds all
seeds of one invocation, vmapped.

What rliable lacks is here: sample efficiency (the paper's "up to 70% better sample
efficiency") is the ratio of environment steps two methods need for their mean evaluation
curves to first reach a common return (``steps_to_reach``, ``sample_efficiency_ratio``,
``common_threshold``), on curves reduced to the rounds where a new evaluation finished
(``distinct_evaluations``); its interval (``sample_efficiency_ratio_ci``) resamples whole
seed curves with rliable's independent stratified bootstrap.

rliable's bootstraps draw from NumPy's global generator (``np.random.choice``); every
function here seeds it for the call and puts its state back afterwards, so an interval is a
function of its ``seed`` and leaves the caller's global stream alone.

Scores of different tasks are pooled only on a common scale: dm_control returns lie in
[0, 1000], so divide them by 1000 before ``aggregate_iqm_ci``.

References:
  Agarwal, Schwarzer, Castro, Courville, Bellemare. "Deep Reinforcement Learning at the Edge
  of the Statistical Precipice". NeurIPS 2021. https://github.com/google-research/rliable
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pathlib
from collections.abc import Callable, Iterable, Iterator, Mapping

import matplotlib

matplotlib.use("Agg")
import numpy as np  # noqa: E402
import scipy.optimize  # noqa: E402
import scipy.stats  # noqa: E402
from numpy.typing import ArrayLike  # noqa: E402
from rliable import library as rly  # noqa: E402
from rliable import metrics as rly_metrics  # noqa: E402

# Reading and plotting curves lives in the package (the CLI draws each run's curve); re-exported here.
from rebel_jax.run.plots import Curve, load_runs, plot_curves  # noqa: E402, F401
from rebel_jax.run.plots import nanmean_std as _nanmean_std  # noqa: E402
from rebel_jax.run.plots import per_seed as _per_seed  # noqa: E402, F401
from rebel_jax.run.plots import records as _records  # noqa: E402

Interval = tuple[float, float]
"""``(low, high)`` of a confidence interval; NaN where it is undefined."""


# -- statistics over runs ------------------------------------------------------------------
def sample_std(values: ArrayLike) -> float:
    """The sample standard deviation (``ddof=1``, as the papers' tables give it) of ``values``; NaN for fewer than
    two values. Every results table states a std over seeds this way."""
    x = np.asarray(values, dtype=float)
    return float(x.std(ddof=1)) if x.size > 1 else math.nan


@contextlib.contextmanager
def _global_seed(seed: int) -> Iterator[None]:
    """NumPy's global generator seeded with ``seed`` inside, its previous state restored after."""
    state = np.random.get_state()  # noqa: NPY002 - rliable draws from the legacy global generator.
    np.random.seed(seed)  # noqa: NPY002 - rliable draws from the legacy global generator.
    try:
        yield
    finally:
        np.random.set_state(state)  # noqa: NPY002 - rliable draws from the legacy global generator.


def iqm(scores: ArrayLike) -> float:
    """Interquartile mean of all scores pooled (rliable's ``aggregate_iqm``).

    ``scipy.stats.trim_mean(scores, 0.25)`` over every score: sort, drop ``floor(n / 4)`` at
    each end, average the rest (the middle 3 of 5, the middle 4 of 6).

    Args:
      scores: per-run scores, ``(runs,)`` or ``(runs, tasks)`` (all runs of all tasks pooled).

    Returns:
      The IQM.
    """
    return float(rly_metrics.aggregate_iqm(np.asarray(scores, dtype=float)))


def _interval(
    score_matrix: np.ndarray, statistic: Callable[[np.ndarray], float], reps: int, confidence: float, seed: int, method
) -> Interval:
    """rliable's stratified-bootstrap interval of ``statistic`` of a ``(runs, tasks)`` matrix."""
    if score_matrix.shape[0] < 2:
        return math.nan, math.nan
    with _global_seed(seed):
        _, intervals = rly.get_interval_estimates(
            {"scores": score_matrix},
            lambda x: np.array([statistic(x)]),
            method=method.lower(),
            reps=reps,
            confidence_interval_size=confidence,
        )
    low, high = np.asarray(intervals["scores"], dtype=float).reshape(2)
    return float(low), float(high)


def bootstrap_ci(
    scores: ArrayLike,
    statistic: Callable[[np.ndarray], float] = iqm,
    reps: int = 2000,
    confidence: float = 0.95,
    seed: int = 0,
    method: str = "percentile",
) -> Interval:
    """Bootstrap confidence interval of a statistic of the runs of one task (rliable's).

    Resamples the runs with replacement ``reps`` times. The default ``method="percentile"`` is
    rliable's: the ``(1 - confidence) / 2`` and ``(1 + confidence) / 2`` quantiles (linear
    interpolation) of the statistic over the resamples; ``"bca"`` (bias-corrected and
    accelerated), ``"bc"`` and ``"basic"`` are ``arch``'s alternatives.

    Args:
      scores: ``(runs,)`` one finite score per run.
      statistic: ``statistic(x)`` of an ``(runs, 1)`` array (``iqm``, ``np.mean``, ``np.median``).
      reps: bootstrap resamples.
      confidence: the interval's coverage, in (0, 1).
      seed: seed of the resampling (the interval is a function of it).
      method: ``"percentile"``, ``"bca"``, ``"bc"`` or ``"basic"`` (case-insensitive).

    Returns:
      ``(low, high)``; NaN for fewer than two runs, where no spread can be estimated.
    """
    x = np.asarray(scores, dtype=float).reshape(-1, 1)
    return _interval(x, statistic, reps, confidence, seed, method)


def aggregate_iqm_ci(
    score_matrix: ArrayLike, reps: int = 2000, confidence: float = 0.95, seed: int = 0, method: str = "percentile"
) -> tuple[float, Interval]:
    """IQM over all runs and tasks with rliable's stratified bootstrap confidence interval.

    Every resample draws, for each task independently, as many runs as it has with
    replacement, then takes the IQM of all drawn scores pooled. With one task this is
    ``bootstrap_ci(scores, iqm)`` (the same draws for the same seed).

    Args:
      score_matrix: ``(runs, tasks)`` normalised scores (or ``(runs,)`` for one task).
      reps: bootstrap resamples.
      confidence: the interval's coverage, in (0, 1).
      seed: seed of the resampling.
      method: ``"percentile"`` (rliable's) or ``"bca"``, ``"bc"``, ``"basic"``.

    Returns:
      ``(iqm, (low, high))``; the interval is NaN for fewer than two runs.
    """
    m = np.asarray(score_matrix, dtype=float)
    m = m[:, None] if m.ndim == 1 else m
    return iqm(m), _interval(m, iqm, reps, confidence, seed, method)


def performance_profile(
    scores: Mapping[str, ArrayLike], taus: ArrayLike, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """rliable's performance profiles (score distributions) with stratified-bootstrap bands.

    The profile of a method at ``tau`` is the fraction of its runs (of all tasks) whose score
    exceeds ``tau`` (``rliable.library.create_performance_profile``, run-score distribution).

    Args:
      scores: ``{label: (runs,) or (runs, tasks) normalised scores}``.
      taus: ``(K,)`` thresholds.
      reps: bootstrap resamples of each band.
      confidence: the bands' coverage.
      seed: seed of the resampling.

    Returns:
      ``{label: (profile (K,), band (2, K) low and high)}``.
    """
    matrices = {}
    for label, s in scores.items():
        m = np.asarray(s, dtype=float)
        matrices[label] = m[:, None] if m.ndim == 1 else m
    with _global_seed(seed):
        profiles, bands = rly.create_performance_profile(
            matrices, np.asarray(taus, dtype=float), reps=reps, confidence_interval_size=confidence
        )
    return {label: (np.asarray(profiles[label]), np.asarray(bands[label])) for label in matrices}


# -- curves ------------------------------------------------------------------------------
def mean_curve(curve: Curve) -> Curve:
    """``(steps, mean over seeds)`` of a curve; a 1-D curve is returned as floats unchanged."""
    steps, values = np.asarray(curve[0], dtype=float), np.asarray(curve[1], dtype=float)
    return steps, (_nanmean_std(values, axis=1)[0] if values.ndim == 2 else values)


def sign_test_p(positive: int, pairs: int) -> float:
    """Two-sided sign-test p-value of ``positive`` of ``pairs`` non-zero differences (either sign with
    probability 1/2): twice the binomial tail of the rarer sign, at most 1."""
    rare = min(positive, pairs - positive)
    return min(1.0, 2 * sum(math.comb(pairs, k) for k in range(rare + 1)) / 2**pairs)


def sign_counted(entry: dict) -> dict:
    """``entry`` with how many of its non-zero ``differences`` are positive (``positive`` of ``pairs``) and
    :func:`sign_test_p` (null without a non-zero difference)."""
    nonzero = [d for d in entry["differences"] if d != 0]
    positive = int(sum(d > 0 for d in nonzero))
    p = round(sign_test_p(positive, len(nonzero)), 4) if nonzero else None
    return entry | {"positive": positive, "pairs": len(nonzero), "sign_test_p": p}


def signed_rank_p(differences: ArrayLike) -> float | None:
    """Two-sided Wilcoxon signed-rank p-value of non-zero paired ``differences``: the share of the sign patterns
    of their ranks (ties at mid-ranks) whose signed-rank sum lies as far from its mean as the observed one.

    Exact (every one of the 2**n patterns, scipy's permutation version) up to 16 differences, a fixed-seed sample
    of 2**16 patterns beyond; None for none. Unlike the sign test it weighs each difference by its size's rank.
    """
    d = np.asarray(differences, dtype=float)
    if d.size < 2:  # one difference: both of its sign patterns lie as far from the mean (scipy wants two)
        return 1.0 if d.size else None
    method = scipy.stats.PermutationMethod(n_resamples=2**16, rng=0)
    return float(scipy.stats.wilcoxon(d, zero_method="wilcox", method=method).pvalue)


def rank_correlation(x: ArrayLike, y: ArrayLike) -> tuple[float, float] | None:
    """Spearman's rank correlation of paired ``x`` and ``y`` (ties at mid-ranks) and its two-sided permutation
    p-value over the pairings of x with y, all of them up to 8 pairs (scipy's exact version), a fixed-seed sample of
    2**16 beyond: twice the share of the smaller tail (pairings whose correlation is at most, or at least, the
    observed one), at most 1. None below 3 pairs or where either does not vary."""
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.size < 3 or np.ptp(x) == 0 or np.ptp(y) == 0:
        return None

    rx = scipy.stats.rankdata(x)
    rx -= rx.mean()

    def rho(b: np.ndarray, axis: int = -1) -> np.ndarray:  # Pearson's correlation of the ranks, x's held fixed
        rb = scipy.stats.rankdata(b, axis=axis)
        rb -= rb.mean(axis=axis, keepdims=True)
        return (rx * rb).sum(axis=axis) / np.sqrt((rx**2).sum() * (rb**2).sum(axis=axis))

    # One sample: "pairings" reorders y alone, so each resample is one pairing of x with y (n! in all).
    resamples = math.inf if x.size <= 8 else 2**16
    test = scipy.stats.permutation_test(
        (y,), rho, permutation_type="pairings", vectorized=True, n_resamples=resamples, rng=0
    )
    return float(test.statistic), float(test.pvalue)


def detectable_difference(
    differences: ArrayLike, keys: int | None = None, power: float = 0.8, alpha: float = 0.05
) -> float | None:
    """The smallest true mean difference that a two-sided paired t-test at level ``alpha`` over ``keys`` keys
    (default: as many as ``differences``) finds with probability ``power``, were the per-key differences normal
    with the standard deviation of ``differences``: what a comparison of that many keys can resolve.

    Exact under those assumptions: the test statistic is non-central t with ``keys - 1`` degrees of freedom and
    non-centrality ``delta * sqrt(keys) / sd``, solved for ``delta``. None below two differences or keys, or
    where the differences do not vary. The rank tests beside it need about 5% more keys for normal differences
    (the signed-rank test's efficiency 3/pi against the t-test's).
    """
    d = np.asarray(differences, dtype=float)
    keys = d.size if keys is None else keys
    sd = float(d.std(ddof=1)) if d.size > 1 else 0.0
    if keys < 2 or sd == 0.0:
        return None
    df, critical = keys - 1, float(scipy.stats.t.ppf(1 - alpha / 2, keys - 1))

    def short(nc: float) -> float:  # power at non-centrality nc, less the target; either tail rejects
        return float(scipy.stats.nct.sf(critical, df, nc) + scipy.stats.nct.sf(critical, df, -nc)) - power

    nc = scipy.optimize.brentq(short, 0.0, 100.0)
    return nc * sd / math.sqrt(keys)


def final_returns(returns: ArrayLike, last: int = 10) -> np.ndarray:
    """Per seed, the mean of its last ``last`` finite evaluations.

    Args:
      returns: ``(evals, seeds)`` evaluation returns, NaN where a seed has none.
      last: how many of the last evaluations to average.

    Returns:
      ``(seeds,)``; NaN for a seed without any evaluation.
    """
    r = np.asarray(returns, dtype=float)
    out = np.full(r.shape[1], np.nan)
    for j in range(r.shape[1]):
        seed_evals = r[np.isfinite(r[:, j]), j]
        if seed_evals.size:
            out[j] = seed_evals[-last:].mean()
    return out


def steps_to_reach(steps: ArrayLike, values: ArrayLike, threshold: float) -> float:
    """The first environment step at which a curve reaches ``threshold``.

    Interpolates linearly between the last evaluation below the threshold and the first at or
    above it; non-finite evaluations are skipped. If the first evaluation already reaches it,
    its step is returned (an upper bound: nothing is known before it).

    Args:
      steps: ``(evals,)`` increasing environment steps of the evaluations.
      values: ``(evals,)`` the (mean) return at each.
      threshold: the return to reach.

    Returns:
      The step as a float, or NaN if the curve never reaches the threshold.
    """
    s, v = np.asarray(steps, dtype=float), np.asarray(values, dtype=float)
    keep = np.isfinite(v)
    s, v = s[keep], v[keep]
    reached = np.flatnonzero(v >= threshold)
    if reached.size == 0:
        return math.nan
    i = reached[0]
    if i == 0:
        return float(s[0])
    return float(s[i - 1] + (threshold - v[i - 1]) / (v[i] - v[i - 1]) * (s[i] - s[i - 1]))


def common_threshold(final_means: Iterable[float], fraction: float = 0.8) -> float:
    """A return every compared method reaches: ``fraction`` of the lowest final mean return.

    Pass each method's final mean return, the ``mean`` of its ``summary`` (per seed the mean
    of the last 10 logged rounds, then the mean over seeds). For ``0 < fraction <= 1`` and
    non-negative returns every mean curve reaches the threshold (the maximum of its last
    rounds is at least their mean), so the sample-efficiency ratio is defined; the default
    0.8 measures the climb rather than the plateau, where the noise of a flat curve would
    decide the crossing.

    Args:
      final_means: one final mean return per compared method.
      fraction: the fraction of the lowest of them.

    Returns:
      The threshold.
    """
    return fraction * min(final_means)


def _steps_ratio(steps_a: float, steps_b: float) -> float:
    """``steps_b / steps_a`` with "never reached" (NaN) as infinitely many steps."""
    a = math.inf if math.isnan(steps_a) else steps_a
    b = math.inf if math.isnan(steps_b) else steps_b
    if math.isinf(a) and math.isinf(b):
        return math.nan
    if math.isinf(b) or a == 0:
        return math.inf
    return b / a


def sample_efficiency_ratio(curve_a: Curve, curve_b: Curve, threshold: float) -> float:
    """How many times more environment steps method b needs than a to reach ``threshold``.

    ``steps_b / steps_a`` of ``steps_to_reach`` on the mean curves. A ratio of 1.7 reads "a is
    70% more sample-efficient than b" (b needs 1.7x the steps of a; equivalently a needs
    ``1 - 1 / 1.7 = 41%`` fewer steps). Choose the threshold with ``common_threshold`` and
    pass curves reduced by ``distinct_evaluations``.

    Args:
      curve_a: method a's curve (2-D curves are averaged over seeds).
      curve_b: method b's curve.
      threshold: the common return.

    Returns:
      The ratio; ``inf`` if only a reaches the threshold, 0 if only b does, NaN if neither.
    """
    steps_a = steps_to_reach(*mean_curve(curve_a), threshold)
    return _steps_ratio(steps_a, steps_to_reach(*mean_curve(curve_b), threshold))


def sample_efficiency_ratio_ci(
    run_a: Curve, run_b: Curve, threshold: float, reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> Interval:
    """Percentile bootstrap interval of ``sample_efficiency_ratio`` over the seeds.

    Each resample draws the seeds of a and of b independently with replacement (rliable's
    ``StratifiedIndependentBootstrap`` over the seed indices, so whole seed curves are drawn),
    averages the drawn curves and takes the ratio. A resample in which a method never reaches
    the threshold counts as an infinite number of its steps (see ``sample_efficiency_ratio``);
    resamples where neither does are left out. The interval is rliable's percentile interval
    (linear interpolation between resamples) of the others' ratios; where some ratio is
    infinite it takes the quantiles as they are (``inverted_cdf``, no interpolation across
    ``inf``).

    Args:
      run_a: ``(steps, returns (evals, seeds))`` of method a.
      run_b: the same for method b.
      threshold: the common return.
      reps: bootstrap resamples.
      confidence: the interval's coverage, in (0, 1).
      seed: seed of the resampling.

    Returns:
      ``(low, high)``; NaN if no resample has a defined ratio.
    """
    (steps_a, returns_a), (steps_b, returns_b) = (
        (np.asarray(steps, dtype=float), np.asarray(returns, dtype=float)) for steps, returns in (run_a, run_b)
    )

    def ratio(seeds_a: np.ndarray, seeds_b: np.ndarray) -> np.ndarray:
        mean_a = _nanmean_std(returns_a[:, seeds_a[:, 0]], axis=1)[0]
        mean_b = _nanmean_std(returns_b[:, seeds_b[:, 0]], axis=1)[0]
        reach = (steps_to_reach(steps_a, mean_a, threshold), steps_to_reach(steps_b, mean_b, threshold))
        return np.array([_steps_ratio(*reach)])

    index_a, index_b = (np.arange(r.shape[1])[:, None] for r in (returns_a, returns_b))
    with _global_seed(seed):
        ratios = rly.StratifiedIndependentBootstrap(index_a, index_b).apply(ratio, reps)[:, 0]
    ratios = ratios[~np.isnan(ratios)]
    if ratios.size == 0:
        return math.nan, math.nan
    alpha = (1 - confidence) / 2
    method = "linear" if np.all(np.isfinite(ratios)) else "inverted_cdf"
    low, high = np.percentile(ratios, [100 * alpha, 100 * (1 - alpha)], method=method)
    return float(low), float(high)


# -- run directories -----------------------------------------------------------------------
def log_name(run_dir: str | os.PathLike, results: pathlib.Path) -> str:
    """A run directory as the results tables name it: ``results/<its path under results>``, else as given (a
    directory outside ``results``, e.g. a test's)."""
    path, results = pathlib.Path(run_dir).resolve(), results.resolve()
    return f"results/{path.relative_to(results)}" if path.is_relative_to(results) else str(run_dir)


def distinct_evaluations(curve: Curve) -> Curve:
    """Only the rounds in which a new evaluation finished.

    The trainer logs, every round, the return of the *last finished* evaluation episodes, so
    a round that ends inside an episode repeats the previous value (a new evaluation finishes
    every ``episode_length * num_envs`` environment steps: 40k for walker at 40 envs, four
    10k rounds). A row is kept when any seed's return differs from the row before. Use the
    result for ``steps_to_reach`` so that it interpolates between true evaluations rather than
    across a repeated plateau; ``summary`` keeps every round (the RESULTS.md convention).

    Args:
      curve: ``(steps (evals,), returns (evals, seeds))``, e.g. from ``load_runs``.

    Returns:
      The same curve without the repeated rows.
    """
    steps, returns = np.asarray(curve[0]), np.asarray(curve[1], dtype=float)
    same = (returns[1:] == returns[:-1]) | (np.isnan(returns[1:]) & np.isnan(returns[:-1]))
    keep = np.concatenate([[True], ~same.all(axis=1)])[: len(steps)]
    return steps[keep], returns[keep]


def merge_runs(*runs: Curve) -> Curve:
    """The seeds of several run directories of one method side by side, on their common steps.

    Args:
      *runs: ``load_runs`` results, ``(steps, returns (evals, seeds))``.

    Returns:
      ``(steps, returns (common evals, total seeds))``.
    """
    common = runs[0][0]
    for steps, _ in runs[1:]:
        common = np.intersect1d(common, steps)
    columns = [returns[np.searchsorted(steps, common)] for steps, returns in runs]
    return common, np.concatenate(columns, axis=1)


def preset_name(command: str) -> str:
    """The ``--preset`` of a recorded command line; the CLI's default ``paper`` without one."""
    tokens = command.split()
    for i, token in enumerate(tokens):
        if token == "--preset" and i + 1 < len(tokens):
            return tokens[i + 1]
        if token.startswith("--preset="):
            return token.split("=", 1)[1]
    return "paper"


def _json_float(x: float) -> float | None:
    """A float for JSON: ``None`` for NaN or infinity (strict JSON has neither)."""
    return float(x) if math.isfinite(x) else None


def summary(run_dir: str | os.PathLike, *, last: int = 10, **extra) -> dict:
    """The JSON summary of one run directory (the schema of RESULTS.md) plus ``extra``.

    Keys: task, algo, preset, seeds, env_steps (of the last round), num_envs, utd,
    final_returns (per seed the mean of its last ``last`` evaluations), mean, std (population)
    and iqm with iqm_ci (95% percentile bootstrap over seeds, ``bootstrap_ci``) of the
    final returns, curve {env_steps, mean, std} over seeds, evaluation, device, date, command,
    then ``extra`` (e.g. labels, teacher, lam), which may override any of them. Non-finite
    numbers are written as ``None``.

    Args:
      run_dir: a directory written by ``python -m rebel_jax.train``.
      last: evaluations averaged into a seed's final return.
      **extra: further keys.

    Returns:
      A JSON-serialisable dict.
    """
    run_dir = pathlib.Path(run_dir)
    cfg = json.loads((run_dir / "config.json").read_text())
    meta = json.loads((run_dir / "meta.json").read_text())
    records = _records(run_dir)
    steps, returns = load_runs(run_dir)
    final = final_returns(returns, last)
    scores = final[np.isfinite(final)]
    low, high = bootstrap_ci(scores, iqm)
    curve_mean, curve_std = _nanmean_std(returns, axis=1)
    train = cfg.get("train", {})
    return {
        "task": cfg["env"]["task"],
        "algo": cfg["algo"],
        "preset": preset_name(meta["command"]),
        "seeds": meta["seeds"],
        "env_steps": records[-1]["env_steps"] if records else 0,
        "num_envs": cfg["env"].get("num_envs"),
        "utd": cfg.get("sac", {}).get("utd"),
        "final_returns": [_json_float(x) for x in final],
        "mean": _json_float(scores.mean()) if scores.size else None,
        "std": _json_float(sample_std(scores)) if scores.size else None,
        "iqm": _json_float(iqm(scores)) if scores.size else None,
        "iqm_ci": [_json_float(low), _json_float(high)],
        "curve": {
            "env_steps": steps.tolist(),
            "mean": [_json_float(x) for x in curve_mean],
            "std": [_json_float(x) for x in curve_std],
        },
        "evaluation": (
            f"in-batch deterministic episodes (see rebel_jax.train), {train.get('eval_episodes', '?')} per seed "
            f"per {cfg['env'].get('episode_length', '?')}-step episode; final return = per seed the mean of the "
            f"last {last} evaluations"
        ),
        "device": meta["devices"][0],
        "date": meta["started"][:10],
        "command": meta["command"],
        **extra,
    }


# -- plots -------------------------------------------------------------------------------
def curve_figure(
    curves: Mapping[str, Curve],
    path: pathlib.Path,
    title: str,
    xlabel: str | None = None,
    seeds: bool = False,
    ylabel: str = "evaluation return (true reward)",
) -> None:
    """Writes ``path``: each label's mean +- std curve over seeds (``plot_curves``, with each seed's curve
    if ``seeds``) of what ``ylabel`` names, titled, on one axes."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4.5))
    plot_curves(ax, curves, seeds=seeds, ylabel=ylabel)
    ax.legend(fontsize=8)
    if xlabel is not None:
        ax.set_xlabel(xlabel)
    ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def plot_iqm(
    ax, scores: Mapping[str, ArrayLike], reps: int = 2000, confidence: float = 0.95, seed: int = 0
) -> dict[str, tuple[float, Interval]]:
    """Horizontal IQM bars with bootstrap confidence-interval whiskers, one per label.

    Whiskers are drawn from the interval's ends (a percentile interval need not contain the
    point estimate, so they are not symmetric error bars). The first label is on top.

    Args:
      ax: a matplotlib ``Axes``.
      scores: ``{label: (runs,) or (runs, tasks) scores}``; several tasks are aggregated with
        the stratified bootstrap of ``aggregate_iqm_ci``.
      reps: bootstrap resamples.
      confidence: the intervals' coverage.
      seed: seed of the resampling generator.

    Returns:
      ``{label: (iqm, (low, high))}``, the plotted numbers.
    """
    stats = {label: aggregate_iqm_ci(s, reps, confidence, seed) for label, s in scores.items()}
    y = np.arange(len(stats))
    points = np.array([p for p, _ in stats.values()])
    lows, highs = (np.array([ci[k] for _, ci in stats.values()]) for k in (0, 1))
    ax.barh(y, points, height=0.6, alpha=0.7)
    ax.hlines(y, lows, highs, color="black", linewidth=1.5)
    ax.vlines(np.concatenate([lows, highs]), np.tile(y, 2) - 0.15, np.tile(y, 2) + 0.15, color="black", linewidth=1.5)
    ax.set_yticks(y, list(stats))
    ax.set_ylim(len(stats) - 0.5, -0.5)
    ax.set_xlabel(f"IQM ({confidence:.0%} bootstrap CI)")
    return stats


# -- runs compared by key ----------------------------------------------------------------
def keyed_run(run_dir: str | os.PathLike, last: int = 10) -> dict:
    """One run's final return per seed by both measures, with each seed's PRNG key ``(train.seed, seed index)``.

    Keys: ``keys``, ``end_of_run`` (``final.json``'s frozen-policy evaluation at the last step), ``last10`` (per seed
    the mean of its last ``last`` evaluations, :func:`final_returns`), and the run's ``device``, ``date``, ``jax``,
    ``commit`` and ``command`` from its ``meta.json``."""
    run_dir = pathlib.Path(run_dir)
    cfg = json.loads((run_dir / "config.json").read_text())
    meta = json.loads((run_dir / "meta.json").read_text())
    _, returns = load_runs(run_dir)
    end = json.loads((run_dir / "final.json").read_text())["final_eval_return"]
    return {
        "keys": [[cfg["train"]["seed"], i] for i in range(len(end))],
        "end_of_run": [round(float(v), 2) for v in end],
        "last10": [round(float(v), 2) for v in final_returns(returns, last)],
        "device": ", ".join(meta["devices"]),
        "date": meta["started"][:10],
        "jax": meta["jax"],
        "commit": meta.get("git_commit"),
        "command": meta["command"],
    }


def measured(values: ArrayLike) -> dict:
    """Mean, sample std and IQM with its 95% bootstrap interval of per-seed scores (``std`` null for one seed)."""
    x = np.asarray(values, dtype=float)
    low, high = bootstrap_ci(x, iqm)
    std = sample_std(x) if x.size > 1 else math.nan
    return {
        "seeds": int(x.size),
        "mean": round(float(x.mean()), 2),
        "std": _json_float(round(std, 2)),
        "iqm": round(float(iqm(x)), 2),
        "iqm_ci": [_json_float(round(low, 2)), _json_float(round(high, 2))],
    }


def paired_difference(a: dict, b: dict, measure: str) -> dict:
    """``a`` minus ``b`` (two :func:`keyed_run` results) over the keys both have, by ``measure`` (``end_of_run``
    or ``last10``): the differences, their mean with its 95% percentile-bootstrap interval, how many are positive
    with the sign test's p, and the signed-rank test's p."""
    va = {tuple(k): v for k, v in zip(a["keys"], a[measure], strict=True)}
    vb = {tuple(k): v for k, v in zip(b["keys"], b[measure], strict=True)}
    keys = sorted(va.keys() & vb.keys())
    d = np.asarray([va[k] - vb[k] for k in keys], dtype=float)
    low, high = bootstrap_ci(d, np.mean)
    entry = {
        "measure": measure,
        "keys": [list(k) for k in keys],
        "differences": [round(float(v), 2) for v in d],
        "mean": round(float(d.mean()), 2),
        "mean_ci": [_json_float(round(low, 2)), _json_float(round(high, 2))],
    }
    nonzero = d[d != 0]
    signed_rank = _json_float(round(signed_rank_p(nonzero), 4)) if nonzero.size else None
    return sign_counted(entry) | {"signed_rank_p": signed_rank}
