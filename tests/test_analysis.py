"""Statistics, curve readers and plots of ``experiments/analysis.py`` on hand-checked data."""

from __future__ import annotations

import dataclasses
import importlib.util
import itertools
import json
import math
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402
import scipy.stats  # noqa: E402

_PATH = pathlib.Path(__file__).parents[1] / "experiments" / "analysis.py"
_SPEC = importlib.util.spec_from_file_location("analysis", _PATH)
analysis = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(analysis)
from rliable import library as rly  # noqa: E402

from rebel_jax.preference.teachers import PRESETS as TEACHERS  # noqa: E402
from rebel_jax.preference.teachers import TeacherConfig  # noqa: E402
from rebel_jax.run import plots  # noqa: E402

ORACLE = dataclasses.asdict(TeacherConfig())
"""The oracle's knobs as a run's ``config.json`` records them."""


def trimmed_mean_reference(scores: list[float]) -> float:
    """scipy's ``trim_mean(x, 0.25)`` in plain Python: drop int(n / 4) sorted scores per end."""
    ordered = sorted(scores)
    cut = len(ordered) // 4
    kept = ordered[cut : len(ordered) - cut]
    return sum(kept) / len(kept)


# -- IQM ---------------------------------------------------------------------------------
def test_iqm_by_hand():
    # n = 8: drop the 2 lowest and the 2 highest.
    assert analysis.iqm([7.0, -50.0, 3.0, 1.0, 90.0, 5.0, 2.0, 1000.0]) == pytest.approx((2 + 3 + 5 + 7) / 4)
    # n = 5: floor(5 / 4) = 1 per end, the middle 3 (not a fractional weighting of 2.5 scores).
    assert analysis.iqm([10.0, 1.0, 7.0, 3.0, 100.0]) == pytest.approx((3 + 7 + 10) / 3)
    # n = 6: still 1 per end, the middle 4.
    assert analysis.iqm([1.0, 2.0, 3.0, 4.0, 5.0, 600.0]) == pytest.approx(3.5)


@pytest.mark.parametrize("n", [4, 5, 6, 7, 9, 10, 13, 50])
def test_iqm_matches_plain_python_trimmed_mean(n):
    scores = np.random.default_rng(n).lognormal(size=n)
    assert analysis.iqm(scores) == pytest.approx(trimmed_mean_reference(scores.tolist()), rel=1e-12)


def test_iqm_pools_all_runs_of_all_tasks():
    matrix = np.random.default_rng(0).normal(size=(7, 3)) + np.arange(3)
    assert analysis.iqm(matrix) == pytest.approx(trimmed_mean_reference(matrix.ravel().tolist()))


# -- bootstrap ---------------------------------------------------------------------------
def test_bootstrap_ci_contains_the_iqm_and_narrows_with_more_runs():
    rng = np.random.default_rng(1)
    widths = []
    for runs in (5, 50):
        scores = rng.normal(500.0, 100.0, size=runs)
        low, high = analysis.bootstrap_ci(scores)
        assert low <= analysis.iqm(scores) <= high
        assert low < high
        widths.append(high - low)
    assert widths[1] < 0.6 * widths[0]


def test_bootstrap_ci_is_a_function_of_its_seed_and_bca_agrees_on_a_large_sample():
    scores = np.random.default_rng(2).normal(size=60)
    assert analysis.bootstrap_ci(scores, seed=3) == analysis.bootstrap_ci(scores, seed=3)
    assert analysis.bootstrap_ci(scores, seed=3) != analysis.bootstrap_ci(scores, seed=4)
    percentile = analysis.bootstrap_ci(scores)
    bca = analysis.bootstrap_ci(scores, method="BCa")
    assert bca[0] <= analysis.iqm(scores) <= bca[1]
    assert np.allclose(bca, percentile, atol=0.25 * (percentile[1] - percentile[0]))


def test_bootstrap_ci_of_the_mean_matches_the_normal_interval():
    scores = np.random.default_rng(5).normal(10.0, 2.0, size=400)
    low, high = analysis.bootstrap_ci(scores, np.mean, reps=4000)
    half = 1.96 * scores.std() / math.sqrt(scores.size)
    assert low == pytest.approx(scores.mean() - half, abs=0.1 * half)
    assert high == pytest.approx(scores.mean() + half, abs=0.1 * half)


def test_bootstrap_ci_leaves_numpys_global_generator_as_it_was():
    np.random.seed(123)  # noqa: NPY002 - rliable draws from the legacy global generator.
    expected = np.random.random_sample(3)  # noqa: NPY002 - rliable draws from the legacy global generator.
    np.random.seed(123)  # noqa: NPY002 - rliable draws from the legacy global generator.
    analysis.bootstrap_ci(np.random.default_rng(0).normal(size=20), seed=5)  # rliable draws with np.random.choice.
    analysis.sample_efficiency_ratio_ci((np.arange(3), np.ones((3, 2))), (np.arange(3), np.ones((3, 2))), 0.5, reps=10)
    np.testing.assert_array_equal(np.random.random_sample(3), expected)  # noqa: NPY002 - rliable draws from the legacy global generator.


def test_bootstrap_ci_is_undefined_for_one_run():
    assert all(math.isnan(x) for x in analysis.bootstrap_ci([3.0]))


def test_stratified_bootstrap_keeps_every_task_in_each_resample():
    # Tasks on very different levels with little spread inside each: resampling runs within
    # each task barely moves the pooled IQM, resampling the pooled runs changes the task mix.
    rng = np.random.default_rng(6)
    matrix = np.array([0.0, 0.5, 1.0]) + rng.normal(0.0, 0.01, size=(10, 3))
    point, (low, high) = analysis.aggregate_iqm_ci(matrix)
    assert point == pytest.approx(analysis.iqm(matrix))
    assert low <= point <= high
    pooled_low, pooled_high = analysis.bootstrap_ci(matrix.ravel())
    assert high - low < 0.2 * (pooled_high - pooled_low)


def test_aggregate_iqm_ci_of_one_task_is_the_plain_bootstrap():
    scores = np.random.default_rng(7).normal(size=12)
    point, ci = analysis.aggregate_iqm_ci(scores)
    assert point == pytest.approx(analysis.iqm(scores))
    assert ci == pytest.approx(analysis.bootstrap_ci(scores))


# -- steps to reach and sample efficiency ------------------------------------------------
def test_steps_to_reach_interpolates_between_evaluations():
    steps, values = [0, 10, 20, 30], [0.0, 2.0, 6.0, 10.0]
    assert analysis.steps_to_reach(steps, values, 5.0) == pytest.approx(10 + (5 - 2) / (6 - 2) * 10)  # 17.5
    assert analysis.steps_to_reach(steps, values, 6.0) == pytest.approx(20.0)
    assert analysis.steps_to_reach(steps, values, -1.0) == pytest.approx(0.0)  # the first evaluation
    # The first crossing counts, even if the curve drops below again.
    assert analysis.steps_to_reach(steps, [0.0, 6.0, 2.0, 8.0], 5.0) == pytest.approx(5 / 6 * 10)
    # A missing evaluation is skipped: interpolate across it.
    assert analysis.steps_to_reach([0, 10, 20], [0.0, math.nan, 6.0], 3.0) == pytest.approx(10.0)


def test_steps_to_reach_never():
    assert math.isnan(analysis.steps_to_reach([0, 10, 20], [0.0, 4.0, 9.9], 10.0))
    assert math.isnan(analysis.steps_to_reach([0, 10], [math.nan, math.nan], 0.0))


def test_sample_efficiency_ratio_of_a_curve_twice_as_slow():
    steps, values = np.array([0, 10, 20, 30]), np.array([0.0, 2.0, 6.0, 10.0])
    fast, slow = (steps, values), (2 * steps, values)
    assert analysis.sample_efficiency_ratio(fast, slow, 5.0) == pytest.approx(2.0)
    assert analysis.sample_efficiency_ratio(slow, fast, 5.0) == pytest.approx(0.5)
    # Per-seed curves are averaged first: seeds 4 and 8 at step 20 make the mean 6.
    seeds = np.stack([values, values], axis=1)
    seeds[2] = [4.0, 8.0]
    assert analysis.sample_efficiency_ratio((steps, seeds), slow, 5.0) == pytest.approx(2.0)
    assert math.isnan(analysis.sample_efficiency_ratio(fast, slow, 20.0))  # neither reaches 20
    assert analysis.sample_efficiency_ratio(fast, (steps, values / 10), 5.0) == math.inf
    assert analysis.sample_efficiency_ratio((steps, values / 10), fast, 5.0) == 0.0


def test_common_threshold_is_reached_by_every_mean_curve():
    rng = np.random.default_rng(9)
    steps = np.arange(0, 200, 10)
    runs = [(steps, np.linspace(0, top, 20)[:, None] + rng.normal(0, 5, (20, 5))) for top in (900.0, 300.0)]
    finals = [analysis.final_returns(returns).mean() for _, returns in runs]
    threshold = analysis.common_threshold(finals)
    assert threshold == pytest.approx(0.8 * min(finals))
    for run in runs:
        assert math.isfinite(analysis.steps_to_reach(*analysis.mean_curve(run), threshold))
    assert analysis.common_threshold([100.0, 50.0], fraction=0.5) == pytest.approx(25.0)


def test_sample_efficiency_ratio_ci():
    steps = np.arange(0, 100, 10)
    clean = np.repeat(np.arange(10.0)[:, None] * 10, 5, axis=1)
    # Identical seeds: every resample has the same curves, the ratio is exactly 2.
    assert analysis.sample_efficiency_ratio_ci((steps, clean), (2 * steps, clean), 45.0) == pytest.approx((2.0, 2.0))
    noisy = clean + np.random.default_rng(8).normal(0.0, 3.0, size=clean.shape)
    ratio = analysis.sample_efficiency_ratio((steps, noisy), (2 * steps, clean), 45.0)
    low, high = analysis.sample_efficiency_ratio_ci((steps, noisy), (2 * steps, clean), 45.0)
    assert low <= ratio <= high and low < high


# -- run directories ---------------------------------------------------------------------
def write_run(run_dir: pathlib.Path, eval_returns: list, steps_per_round: int = 10) -> pathlib.Path:
    """A synthetic ``python -m rebel_jax.train`` run directory with the given per-round returns."""
    run_dir.mkdir()
    config = {
        "algo": "rebel",
        "env": {"task": "walker_walk", "num_envs": 4, "episode_length": 1000},
        "sac": {"utd": 0.25},
        "train": {"eval_episodes": 10},
    }
    meta = {
        "jax": "0.10.2",
        "devices": ["TFRT_CPU_0"],
        "git_commit": "HEAD",
        "command": "train.py --preset tiny --algo rebel --seeds 3",
        "seeds": 3,
        "started": "2026-11-23T10:00:00",
    }
    (run_dir / "config.json").write_text(json.dumps(config))
    (run_dir / "meta.json").write_text(json.dumps(meta))
    lines = []
    for i, ret in enumerate(eval_returns):
        record = {"env_steps": (i + 1) * steps_per_round, "round": i, "eval_return": ret, "train_return": ret}
        lines.append(json.dumps(record))
    (run_dir / "metrics.jsonl").write_text("\n".join(lines) + "\n\n")
    return run_dir


RETURNS = [
    [None, None, None],  # before any evaluation: dropped
    [1.0, None, 3.0],  # one seed without an evaluation yet: NaN
    [2.0, 4.0, 6.0],
    [4.0, 8.0, 12.0],
    [5.0, 10.0, 15.0],
]


def test_load_runs_with_nulls(tmp_path):
    steps, returns = analysis.load_runs(write_run(tmp_path / "run", RETURNS))
    assert steps.tolist() == [20, 30, 40, 50]
    assert returns.shape == (4, 3)
    np.testing.assert_array_equal(returns[1:], np.array(RETURNS[2:], dtype=float))
    assert returns[0, 0] == 1.0 and math.isnan(returns[0, 1]) and returns[0, 2] == 3.0


def test_load_runs_counts_seeds_when_the_first_rounds_log_no_evaluation(tmp_path):
    # A DrQ-v2 run's seed-step rounds have no "eval_return" key at all; 5 seeds read as 1 before (the
    # 5-seed cheetah run of 2026-11-25 stopped in its learning-curve plot on this).
    run_dir = write_run(tmp_path / "run", RETURNS)
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line]
    del records[0]["eval_return"]
    (run_dir / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in records) + "\n")
    steps, returns = analysis.load_runs(run_dir)
    assert steps.tolist() == [20, 30, 40, 50] and returns.shape == (4, 3)
    np.testing.assert_array_equal(returns[1:], np.array(RETURNS[2:], dtype=float))


def test_load_runs_reads_the_success_rate_of_a_task_that_reports_it(tmp_path):
    run_dir = write_run(tmp_path / "run", RETURNS)
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines() if line]
    success = [[None if v is None else v / 20 for v in r["eval_return"]] for r in records]
    for record, rate in zip(records, success, strict=True):
        record["eval_success"] = rate
    (run_dir / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in records) + "\n")
    steps, rates = plots.load_runs(run_dir, "eval_success")
    assert steps.tolist() == [20, 30, 40, 50]
    np.testing.assert_array_equal(rates[1:], np.array(success[2:], dtype=float))


def test_load_runs_keeps_the_last_record_of_a_resumed_round(tmp_path):
    run_dir = write_run(tmp_path / "run", RETURNS)
    with open(run_dir / "metrics.jsonl", "a") as f:  # a resume re-logging the round at step 40
        f.write(json.dumps({"env_steps": 40, "round": 3, "eval_return": [7.0, 7.0, 7.0]}) + "\n")
    steps, returns = analysis.load_runs(run_dir)
    assert steps.tolist() == [20, 30, 40, 50]
    assert returns[2].tolist() == [7.0, 7.0, 7.0]


def test_distinct_evaluations_drops_repeated_rounds():
    steps = np.array([10, 20, 30, 40, 50])
    returns = np.array([[1.0, math.nan], [1.0, math.nan], [1.0, 2.0], [1.0, 2.0], [3.0, 2.0]])
    kept_steps, kept = analysis.distinct_evaluations((steps, returns))
    assert kept_steps.tolist() == [10, 30, 50]
    np.testing.assert_array_equal(kept, returns[[0, 2, 4]])


def test_final_returns_average_each_seeds_last_finite_evaluations():
    returns = np.array([[1.0, math.nan], [2.0, 5.0], [3.0, math.nan], [4.0, 7.0]])
    np.testing.assert_allclose(analysis.final_returns(returns, last=2), [3.5, 6.0])
    np.testing.assert_allclose(analysis.final_returns(returns, last=10), [2.5, 6.0])


def test_merge_runs_on_common_steps():
    a = (np.array([10, 20, 30]), np.array([[1.0], [2.0], [3.0]]))
    b = (np.array([20, 30, 40]), np.array([[5.0, 6.0], [7.0, 8.0], [9.0, 9.0]]))
    steps, returns = analysis.merge_runs(a, b)
    assert steps.tolist() == [20, 30]
    np.testing.assert_array_equal(returns, [[2.0, 5.0, 6.0], [3.0, 7.0, 8.0]])


def test_summary_schema_and_numbers(tmp_path):
    s = analysis.summary(write_run(tmp_path / "run", RETURNS), last=2, labels=100, lam=0.1)
    json.dumps(s, allow_nan=False)  # strict JSON
    for key in ("task", "algo", "preset", "seeds", "env_steps", "final_returns", "mean", "std", "curve", "device"):
        assert key in s
    assert (s["task"], s["algo"], s["preset"], s["seeds"]) == ("walker_walk", "rebel", "tiny", 3)
    assert (s["env_steps"], s["date"], s["device"]) == (50, "2026-11-23", "TFRT_CPU_0")
    assert (s["labels"], s["lam"]) == (100, 0.1)
    assert s["final_returns"] == pytest.approx([4.5, 9.0, 13.5])
    assert s["mean"] == pytest.approx(9.0)
    assert s["std"] == pytest.approx(np.std([4.5, 9.0, 13.5], ddof=1))  # the sample std
    assert s["iqm"] == pytest.approx(9.0)  # the middle of 3
    assert s["iqm_ci"][0] <= s["iqm"] <= s["iqm_ci"][1]
    assert s["curve"]["env_steps"] == [20, 30, 40, 50]
    assert s["curve"]["mean"] == pytest.approx([2.0, 4.0, 8.0, 10.0])
    assert s["curve"]["std"][0] == pytest.approx(1.0)


# -- plots -------------------------------------------------------------------------------
def test_plot_curves_and_iqm(tmp_path):
    run = analysis.load_runs(write_run(tmp_path / "run", RETURNS))
    fig, (ax_curves, ax_iqm) = plt.subplots(1, 2)
    analysis.plot_curves(ax_curves, {"REBEL": run, "SAC": (run[0], 2 * run[1])})
    assert [t.get_text() for t in ax_curves.get_legend().get_texts()] == ["REBEL (3 seeds)", "SAC (3 seeds)"]
    np.testing.assert_allclose(ax_curves.get_lines()[1].get_ydata(), [4.0, 8.0, 16.0, 20.0])
    _, ax_seeds = plt.subplots()
    analysis.plot_curves(ax_seeds, {"REBEL": run}, seeds=True)  # the mean, then each seed's own curve
    lines = ax_seeds.get_lines()
    assert len(lines) == 1 + run[1].shape[1] and len({line.get_color() for line in lines}) == 1
    for j, line in enumerate(lines[1:]):  # a seed's curve skips its missing evaluations
        kept = np.isfinite(run[1][:, j])
        np.testing.assert_array_equal(line.get_xdata(), run[0][kept])
        np.testing.assert_array_equal(line.get_ydata(), run[1][kept, j])
    assert len(lines[2].get_ydata()) == len(run[0]) - 1
    scores = {"REBEL": [0.9, 0.8, 0.85, 0.7, 0.95], "PEBBLE": np.full((5, 2), 0.5)}
    stats = analysis.plot_iqm(ax_iqm, scores)
    assert [t.get_text() for t in ax_iqm.get_yticklabels()] == ["REBEL", "PEBBLE"]
    assert [bar.get_width() for bar in ax_iqm.patches] == pytest.approx([0.85, 0.5])
    assert stats["PEBBLE"][0] == pytest.approx(0.5) and stats["PEBBLE"][1] == pytest.approx((0.5, 0.5))
    fig.savefig(tmp_path / "plot.png")
    plt.close(fig)
    assert (tmp_path / "plot.png").stat().st_size > 0


def test_sample_efficiency_ratio_ci_equals_rliables_interval_of_the_ratio_of_mean_slopes():
    # Seed curves through the origin, returns_s(t) = slope_s * t: a mean curve reaches the threshold T
    # at T / mean(slope) (interpolation between evaluations is exact on a line), so the ratio of
    # steps b / a of a resample is mean(slopes_a) / mean(slopes_b) of the same seed draws. rliable's
    # independent stratified bootstrap of that statistic must give the same interval.
    rng = np.random.default_rng(11)
    steps = np.arange(0, 110, 10)
    slopes_a, slopes_b = rng.uniform(1.0, 2.0, 6), rng.uniform(0.5, 1.5, 4)
    threshold = 0.4 * min(slopes_a.min(), slopes_b.min()) * steps[-1]  # Every resample's mean curve reaches it.
    curve_a, curve_b = (steps, steps[:, None] * slopes_a), (steps, steps[:, None] * slopes_b)
    for seed, confidence in ((0, 0.95), (3, 0.8)):
        interval = analysis.sample_efficiency_ratio_ci(curve_a, curve_b, threshold, 500, confidence, seed)
        np.random.seed(seed)  # noqa: NPY002 - rliable draws from the legacy global generator.
        _, reference = rly.get_interval_estimates(
            {"ratio": [slopes_a[:, None], slopes_b[:, None]]},
            lambda a, b: np.array([a.mean() / b.mean()]),
            reps=500,
            confidence_interval_size=confidence,
        )
        np.testing.assert_allclose(interval, np.asarray(reference["ratio"]).reshape(2), rtol=1e-9)
    assert interval[0] < slopes_a.mean() / slopes_b.mean() < interval[1]


# -- performance profiles ----------------------------------------------------------------
def test_performance_profile_is_the_fraction_of_runs_above_each_threshold():
    rng = np.random.default_rng(12)
    scores = {"a": rng.uniform(size=(9, 2)), "b": rng.uniform(size=7), "flat": np.full(5, 0.5)}
    taus = np.linspace(0.0, 1.0, 11)
    result = analysis.performance_profile(scores, taus, reps=200)
    assert list(result) == ["a", "b", "flat"]
    for label, s in scores.items():
        profile, band = result[label]
        expected = [np.mean(np.asarray(s) > tau) for tau in taus]
        np.testing.assert_allclose(profile, expected)
        assert band.shape == (2, taus.size) and np.all(band[0] <= band[1])
        assert np.all((band >= 0) & (band <= 1))
    np.testing.assert_allclose(result["flat"][1], np.stack([result["flat"][0]] * 2))  # No spread, no band.


def test_sign_test_p_equals_scipys_two_sided_binomial_test():
    for pairs in range(1, 13):
        for positive in range(pairs + 1):
            expected = scipy.stats.binomtest(positive, pairs, 0.5, alternative="two-sided").pvalue
            assert analysis.sign_test_p(positive, pairs) == pytest.approx(expected, rel=1e-12)


def test_signed_rank_p_equals_an_enumeration_of_every_sign_pattern():
    rng = np.random.default_rng(0)
    for n in range(1, 9):
        d = np.round(rng.normal(size=n), 0) + rng.choice([0.0, 0.5], size=n)  # rounded: ties among the sizes
        d = d[d != 0]
        ranks = scipy.stats.rankdata(np.abs(d))  # ties at mid-ranks
        centre, observed = ranks.sum() / 2, ranks[d > 0].sum()
        sums = [np.dot(ranks, signs) for signs in itertools.product([0, 1], repeat=d.size)]
        expected = np.mean([abs(w - centre) >= abs(observed - centre) - 1e-9 for w in sums])
        assert analysis.signed_rank_p(d) == pytest.approx(expected, rel=1e-9), d
    assert analysis.signed_rank_p([]) is None


def test_rank_correlation_equals_spearman_and_an_enumeration_of_every_pairing():
    rng = np.random.default_rng(2)
    for n in (3, 5, 7):
        x = np.round(rng.normal(size=n), 0)  # rounded: ties at mid-ranks
        y = x + rng.normal(size=n)
        rho, p = analysis.rank_correlation(x, y)
        assert rho == pytest.approx(scipy.stats.spearmanr(x, y).statistic, abs=1e-12)
        others = [scipy.stats.spearmanr(x, y[list(order)]).statistic for order in itertools.permutations(range(n))]
        tails = np.mean(np.array(others) <= rho + 1e-12), np.mean(np.array(others) >= rho - 1e-12)
        assert p == pytest.approx(min(1.0, 2 * min(tails)), rel=1e-9), (x, y)
    assert analysis.rank_correlation([1.0, 2.0], [2.0, 1.0]) is None  # below 3 pairs
    assert analysis.rank_correlation([1.0, 1.0, 1.0], [1.0, 2.0, 3.0]) is None  # x does not vary


def test_a_t_test_on_the_detectable_difference_rejects_at_the_asked_power():
    """Monte Carlo: normal per-key differences whose mean is the detectable difference, at the spread of the given
    differences, are found by scipy's paired (one-sample) t-test in 80% (90%) of 100,000 draws (standard error
    0.0013; the tolerance catches a non-central t with one degree of freedom too many at 3 keys, 0.794)."""
    rng = np.random.default_rng(1)
    observed = [-3.0, -82.0, 8.5, 121.0, 27.0, -127.0]  # the spread only matters
    sd = np.std(observed, ddof=1)
    for keys, power in ((3, 0.8), (6, 0.8), (10, 0.9)):
        delta = analysis.detectable_difference(observed, keys, power=power)
        draws = rng.normal(delta, sd, size=(100_000, keys))
        rejected = scipy.stats.ttest_1samp(draws, 0.0, axis=1).pvalue < 0.05
        assert rejected.mean() == pytest.approx(power, abs=0.004), (keys, power)
        assert analysis.detectable_difference(observed, keys, power=power - 0.2) < delta  # less power, less needed
    assert analysis.detectable_difference(observed, 20) < analysis.detectable_difference(observed)  # more keys
    assert analysis.detectable_difference([5.0]) is None and analysis.detectable_difference([2.0, 2.0]) is None
    assert analysis.detectable_difference(observed, keys=1) is None


def _experiment(monkeypatch, name: str):
    """``experiments/<name>.py``, importable with its siblings."""
    monkeypatch.syspath_prepend(str(_PATH.parent))
    spec = importlib.util.spec_from_file_location(name, _PATH.parent / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _fake_run(root: pathlib.Path, name: str, returns: list[float], changes: dict | None = None) -> dict:
    """A run directory's ``config.json`` (only the settings ``pooled`` reads) and its table row."""
    cfg = {"algo": "pebble", "sac": {"precision": "tf32", "utd": 1.0}, "train": {"seed": 0},
           "feedback": {"labels": 100}, "rebel": {"lam": 0.0}}  # fmt: skip
    for (group, key), value in (changes or {}).items():
        cfg[group][key] = value
    run = root / "runs" / "baselines" / name
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps(cfg))
    x = np.asarray(returns)
    return {"log": f"results/runs/baselines/{name}", "complete": True, "final_returns": returns,
            "returns_at": {"500000": float(x.mean())}, "seeds": len(x), "precision": cfg["sac"]["precision"],
            "seed": cfg["train"]["seed"], "device": "d", "date": "t", "jax": "j", "command": "c"}  # fmt: skip


def test_baselines_pool_only_runs_that_differ_in_precision_and_seed(tmp_path, monkeypatch):
    baselines = _experiment(monkeypatch, "baselines")
    monkeypatch.setattr(baselines, "RESULTS", tmp_path)
    a = _fake_run(tmp_path, "a", [100.0, 300.0])
    b = _fake_run(tmp_path, "b", [500.0, 700.0, 900.0], {("sac", "precision"): "bf16", ("train", "seed"): 1})
    row = baselines.pooled("pooled", [a, b])
    x = np.asarray([100.0, 300.0, 500.0, 700.0, 900.0])
    assert row["seeds"] == 5 and row["final_returns"] == x.tolist()
    assert row["mean"] == pytest.approx(x.mean(), abs=0.01) and row["std"] == pytest.approx(x.std(ddof=1), abs=0.01)
    assert row["returns_at"]["500000"] == pytest.approx(x.mean())  # seed-weighted, not the mean of means
    assert row["precision"] == ["bf16", "tf32"] and row["seed"] == [0, 1]
    c = _fake_run(tmp_path, "c", [1.0, 2.0], {("feedback", "labels"): 1000})
    with pytest.raises(ValueError, match="feedback.*labels"):
        baselines.pooled("pooled", [a, c])
    with pytest.raises(ValueError, match="total_steps"):
        baselines.pooled("pooled", [a, b | {"complete": False}])


def test_baselines_diagnostics_against_a_hand_computation(tmp_path, monkeypatch):
    baselines = _experiment(monkeypatch, "baselines")
    rng = np.random.default_rng(0)
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"sac": {"gamma": 0.9}}))
    logged = []
    for i in range(14):  # 14 rounds of 3 seeds; the per-round reward metrics only in the last 4.
        record = {k: rng.uniform(0.1, 2.0, 3).tolist() for k in ("q", "alpha", "entropy", "critic_loss")}
        record |= {"env_steps": 1000 * (i + 1), "eval_return": rng.uniform(0, 900, 3).tolist()}
        if i >= 10:
            record |= {"round_learned_mean": rng.uniform(-1, 1, 3).tolist()}
        logged.append(record)
    (run / "metrics.jsonl").write_text("".join(json.dumps(r) + "\n" for r in logged))
    out = baselines.diagnostics(run, [0, 2])  # The columns of one method.
    last = logged[-10:]
    col = lambda key, rows: np.array([[r[key][c] for c in (0, 2)] for r in rows])  # noqa: E731
    implied = col("q", last) * 0.1 - 0.9 * col("alpha", last) * col("entropy", last)
    assert out["implied_reward_last10"] == round(float(implied.mean()), 3)
    assert out["q_last10"] == round(float(col("q", last).mean()), 3)
    assert out["round_learned_mean_last10"] == round(float(col("round_learned_mean", logged[10:]).mean()), 3)
    assert out["round_learned_saturated_last10"] is None  # not logged
    best = max(range(14), key=lambda i: col("eval_return", [logged[i]]).mean())
    assert out["best_eval_step"] == logged[best]["env_steps"]


def _fake_curve_run(
    run: pathlib.Path,
    algo: str,
    slope: float | list[float],
    seeds: int,
    lams: list | None = None,
    task: str = "walker_walk",
    teacher: str = "oracle",
    train_seed: int = 0,
) -> None:
    """A run directory whose every column's evaluation return is ``slope * env_steps / 1000`` (a slope per
    column, or one for all), under a B-Pref ``teacher`` given by ``--teacher``, from ``--seed train_seed``;
    ``seeds`` counts the columns (a grid's seeds are the columns over the lambdas, as ``meta.json`` says)."""
    run.mkdir(parents=True)
    rebel = {"source": "onpolicy", "form": "lower_bound", "normalize": False, "estimator": "discounted"}
    cfg = {"algo": algo, "env": {"task": task, "num_envs": 10}, "feedback": {"labels": 100},
           "teacher": dataclasses.asdict(TEACHERS[teacher]), "sac": {"utd": 1.0}, "rebel": rebel,
           "reward": {"output": "tanh"}, "train": {"seed": train_seed}}  # fmt: skip
    meta = {"devices": ["d"], "started": "2026-11-24T00:00:00", "command": f"train --algo {algo}", "lams": lams,
            "seeds": seeds // len(set(lams)) if lams else seeds}  # fmt: skip
    (run / "config.json").write_text(json.dumps(cfg))
    (run / "meta.json").write_text(json.dumps(meta | {"columns": seeds}))
    steps = range(10_000, 200_001, 10_000)
    slopes = np.broadcast_to(slope, seeds)
    lines = [json.dumps({"env_steps": s, "eval_return": (slopes * s / 1000).tolist()}) for s in steps]
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")


def test_rebel_rows_against_a_hand_computation(tmp_path, monkeypatch):
    rebel = _experiment(monkeypatch, "rebel")
    monkeypatch.setattr(rebel, "RESULTS", tmp_path)
    _fake_curve_run(tmp_path / "runs" / "pebble", "pebble", 1.0, 3)
    _fake_curve_run(tmp_path / "runs" / "grid", "rebel", 2.0, 3, lams=[0.1] * 3)  # twice as fast
    run_dirs = [tmp_path / "runs" / n for n in ("pebble", "grid")]
    rows = {r["method"]: r for r in rebel.rows("walker_walk", run_dirs, tmp_path / "rebel_walker_walk.png")}
    assert set(rows) == {"pebble", "rebel lam=0.1"}
    assert (tmp_path / "rebel_walker_walk.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # Final returns: the mean of the last 10 evaluations (110k..200k): 155 and 310; threshold 0.8 * 155 = 124.
    pebble, grid = rows["pebble"], rows["rebel lam=0.1"]
    assert pebble["final_returns"] == [155.0] * 3 and grid["final_returns"] == [310.0] * 3
    assert pebble["threshold"] == grid["threshold"] == 124.0
    assert (pebble["steps_to_threshold"], grid["steps_to_threshold"]) == (124_000, 62_000)
    assert grid["efficiency_vs_pebble"] == 2.0 and grid["efficiency_ci"] == [2.0, 2.0]
    assert pebble["efficiency_vs_pebble"] == 1.0
    assert grid["efficiency_vs_surf"] is None and grid["efficiency_vs_surf_ci"] == [None, None]  # no SURF run
    _fake_curve_run(tmp_path / "runs" / "surf", "surf", 4.0, 3)  # four times PEBBLE's slope
    with_surf = {r["method"]: r for r in rebel.rows("walker_walk", [*run_dirs, tmp_path / "runs" / "surf"])}
    # The threshold is still 124 (PEBBLE's final mean is the lowest): SURF reaches it at 31k, REBEL at 62k.
    assert with_surf["rebel lam=0.1"]["efficiency_vs_surf"] == 0.5 and with_surf["pebble"]["efficiency_vs_surf"] == 0.25
    assert with_surf["rebel lam=0.1"]["efficiency_vs_surf_ci"] == [0.5, 0.5]
    # A REBEL run below every baseline does not move the threshold (only the baselines set it): one at a
    # quarter of PEBBLE's slope ends at 38.75 (80%: 31) and never reaches 124 (no steps, ratio 0).
    _fake_curve_run(tmp_path / "runs" / "slow", "rebel", 0.25, 3, lams=[0.01] * 3)
    with_slow = {r["method"]: r for r in rebel.rows("walker_walk", [*run_dirs, tmp_path / "runs" / "slow"])}
    assert {r["threshold"] for r in with_slow.values()} == {124.0}
    assert with_slow["rebel lam=0.01"]["steps_to_threshold"] is None
    assert with_slow["rebel lam=0.01"]["efficiency_vs_pebble"] == 0.0
    assert with_slow["rebel lam=0.1"]["efficiency_vs_pebble"] == 2.0
    assert (grid["lam"], grid["estimator"], grid["variant"]) == (0.1, "onpolicy", "lower_bound, raw, tanh output")
    assert (pebble["estimator"], pebble["variant"]) == (None, None)
    assert grid["log"] == ["results/runs/grid"] and grid["seeds"] == 3
    with pytest.raises(ValueError, match="no PEBBLE run"):
        rebel.rows("walker_walk", [tmp_path / "runs" / "grid"])


def test_rebel_rows_under_a_teacher_are_against_that_teachers_pebble_and_pair_seeds(tmp_path, monkeypatch):
    rebel = _experiment(monkeypatch, "rebel")
    monkeypatch.setattr(rebel, "RESULTS", tmp_path)
    _fake_curve_run(tmp_path / "runs" / "pebble", "pebble", 1.0, 3)
    _fake_curve_run(tmp_path / "runs" / "oracle", "rebel", 2.0, 3, lams=[0.1] * 3)
    # One --lam-grid 0 0.1 --teacher mistake program: PEBBLE's columns at slope 2, REBEL's at 4, 6 and 1.
    slopes, lams = [2, 2, 2, 4, 6, 1], [0] * 3 + [0.1] * 3
    _fake_curve_run(tmp_path / "runs" / "mistake", "rebel", slopes, 6, lams, teacher="mistake")
    run_dirs = [tmp_path / "runs" / n for n in ("pebble", "oracle", "mistake")]
    rows = rebel.rows("walker_walk", run_dirs, tmp_path / "rebel_walker_walk.png")
    by = {r["method"]: r for r in rows}
    assert set(by) == {"pebble", "rebel lam=0.1", "pebble (rebel lam=0), mistake", "rebel lam=0.1, mistake"}
    mistake, pebble_mistake = by["rebel lam=0.1, mistake"], by["pebble (rebel lam=0), mistake"]
    assert (mistake["teacher"], mistake["pebble"], by["rebel lam=0.1"]["pebble"]) == (
        "mistake",
        "pebble (rebel lam=0), mistake",
        "pebble",
    )
    # Only the oracle's PEBBLE sets the threshold: 0.8 * 155 = 124 (not the mistake teacher's lambda-0 columns).
    assert {r["threshold"] for r in rows} == {124.0}
    # REBEL's mean curve has slope 11/3: against PEBBLE under the same teacher (slope 2) the ratio is 11/6; against
    # the oracle's PEBBLE (slope 1) it would be 11/3.
    assert mistake["efficiency_vs_pebble"] == round(11 / 6, 2) and pebble_mistake["efficiency_vs_pebble"] == 1.0
    assert by["rebel lam=0.1"]["efficiency_vs_pebble"] == 2.0
    assert rebel.chosen_lambda(rows, steps=200_000)["among"] == [0.1]  # the oracle's REBEL only
    assert rebel.teacher_rows(rows, 0.1) == [("oracle", by["pebble"], by["rebel lam=0.1"]),
                                             ("mistake", pebble_mistake, mistake)]  # fmt: skip
    # Final returns (means of the last 10 evaluations): 155 per unit of slope. REBEL minus PEBBLE per seed.
    (entry, pooled) = rebel.teacher_pairs(rows)
    assert (entry["teacher"], entry["lam"], entry["differences"]) == ("mistake", 0.1, [310.0, 620.0, -155.0])
    assert (entry["positive"], entry["pairs"], pooled["lam"]) == (2, 3, "all")
    assert rebel.teacher_figure(rows, 0.1, tmp_path / "t.png", "t") == ["oracle", "mistake"]
    assert (tmp_path / "t.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _log_sessions(run: pathlib.Path, skipped: list[float], equal: list[float], agreement: list | None = None) -> None:
    """Adds per-column session metrics to a fake run's rounds: a session every other round, NaN (null) between."""
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    for k, row in enumerate(rows):
        none = [None] * len(skipped)
        row.update(session_skipped=skipped if k % 2 else none, session_equal=equal if k % 2 else none)
        if agreement is not None:
            row["session_oracle_agreement"] = agreement if k % 2 else none
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")


def test_rebel_pools_the_oracle_with_teacher_runs_whose_every_label_was_the_oracles(tmp_path, monkeypatch):
    rebel = _experiment(monkeypatch, "rebel")
    monkeypatch.setattr(rebel, "RESULTS", tmp_path)
    runs = tmp_path / "runs"
    _fake_curve_run(runs / "pebble", "pebble", 1.0, 3)
    _fake_curve_run(runs / "oracle", "rebel", 2.0, 3, lams=[0.1] * 3)
    grid = dict(seeds=6, lams=[0] * 3 + [0.1] * 3)
    _fake_curve_run(runs / "skip", "rebel", [2, 3, 2, 4, 6, 1], teacher="skip", **grid)
    _log_sessions(runs / "skip", [0.0] * 6, [0.0] * 6)  # skipped nothing: every label the oracle's
    _fake_curve_run(runs / "mistake", "rebel", [1, 1, 1, 5, 5, 5], teacher="mistake", **grid)
    # Its flips are not counted: never the oracle's labels, whatever its agreement.
    _log_sessions(runs / "mistake", [0.0] * 6, [0.0] * 6, [1.0, 0.9, 0.8, 0.7, 0.6, 0.8])
    rows = rebel.rows("walker_walk", [runs / n for n in ("pebble", "oracle", "skip", "mistake")])
    by = {r["method"]: r for r in rows}
    assert rebel.oracle_labelled(runs / "skip") and not rebel.oracle_labelled(runs / "mistake")
    # The labels' agreement with the oracle, per method over its columns' sessions; none logged by the skip run.
    agreement = {"pebble (rebel lam=0), mistake": 0.9, "rebel lam=0.1, mistake": 0.7}
    assert rebel.oracle_agreement(runs / "mistake") == agreement and rebel.oracle_agreement(runs / "skip") == {}
    assert [rebel._agreement(by[m]) for m in agreement] == [0.9, 0.7] and rebel._agreement(by["pebble"]) == "-"
    pooled = rebel.oracle_pooled(rows, 0.1)
    assert pooled["teachers"] == ["oracle", "skip"]
    for name, labels in (
        ("pebble", ("pebble", "pebble (rebel lam=0), skip")),
        ("rebel", ("rebel lam=0.1", "rebel lam=0.1, skip")),
    ):
        scores = [v for label in labels for v in by[label]["final_returns"]]
        assert pooled[name]["final_returns"] == scores and pooled[name]["seeds"] == 6
        assert pooled[name]["iqm"] == pytest.approx(scipy.stats.trim_mean(scores, 0.25), abs=0.01)
        low, high = pooled[name]["iqm_ci"]
        assert min(scores) <= low <= pooled[name]["iqm"] <= high <= max(scores)
    _log_sessions(runs / "skip", [0.0, 0.0, 1.0, 0.0, 0.0, 0.0], [0.0] * 6)  # one query skipped: not pooled
    assert not rebel.oracle_labelled(runs / "skip") and rebel.oracle_pooled(rows, 0.1)["teachers"] == ["oracle"]
    _log_sessions(runs / "skip", [0.0] * 6, [0.0] * 5 + [2.0])  # two equal answers: not pooled either
    assert not rebel.oracle_labelled(runs / "skip")


def test_rebel_on_policy_reward_averages_each_lambdas_columns_over_rounds_and_seeds(tmp_path, monkeypatch):
    rebel = _experiment(monkeypatch, "rebel")
    monkeypatch.setattr(rebel, "RESULTS", tmp_path)
    run = tmp_path / "runs" / "grid"
    _fake_curve_run(run, "rebel", 1.0, 4, lams=[0.1, 0.1, -0.1, -0.1])
    rng = np.random.default_rng(0)
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    for row in rows:  # per-round metrics per column, from 30k on (earlier rounds predate them)
        if row["env_steps"] >= 30_000:
            row.update({name: rng.normal(size=4).tolist() for name in rebel.ROUND_REWARD_METRICS})
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = {r["method"]: r for r in rebel.on_policy_reward("walker_walk", run)}
    used = [r for r in rows if r["env_steps"] >= rebel.ON_POLICY_FROM]
    for label, cols in (("rebel lam=0.1", [0, 1]), ("rebel lam=-0.1", [2, 3])):
        for name in rebel.ROUND_REWARD_METRICS:
            expected = sum(r[name][c] for r in used for c in cols) / (2 * len(used))
            assert out[label][name] == round(expected, 3)
        assert out[label]["steps"] == [40_000, 200_000] and out[label]["rounds"] == 17 and out[label]["seeds"] == 2
    _fake_curve_run(tmp_path / "runs" / "old", "pebble", 1.0, 3)
    assert rebel.on_policy_reward("walker_walk", tmp_path / "runs" / "old") == []  # predates the metrics


def test_pixel_rows_merge_one_seed_jobs_and_count_frames(tmp_path, monkeypatch):
    pixels = _experiment(monkeypatch, "pixels")
    monkeypatch.setattr(pixels, "RESULTS", tmp_path)
    runs = [tmp_path / "runs" / f"drqv2_seed{k}" for k in range(3)]
    for k, run in enumerate(runs):  # one seed per job, as the drqv2_seed set runs them
        _fake_curve_run(run, "drqv2", 1.0 + k, 1, task="walker_walk_pixels")
    meta = json.loads((runs[2] / "meta.json").read_text())  # the last job ran on another device, a day later
    meta |= {"devices": ["e"], "started": "2026-11-25T09:00:00", "command": "train --algo drqv2 --seed 2"}
    (runs[2] / "meta.json").write_text(json.dumps(meta))
    rows, curves = pixels.rows("walker_walk_pixels", runs)
    assert len(rows) == 1
    row = rows[0]
    # Per seed the mean of the last 10 evaluations (110k..200k agent steps): 155 times the slope.
    assert row["final_returns"] == [155.0, 310.0, 465.0] and row["mean"] == 310.0 and row["seeds"] == 3
    assert row["frames"] == 2 * 200_000 and pixels.action_repeat("walker_walk_pixels") == 2
    assert (row["task"], row["algo"], row["obs"]) == ("walker_walk", "drqv2", "pixels")
    assert row["log"] == [f"results/runs/drqv2_seed{k}" for k in range(3)]
    assert row["device"] == ["d", "e"] and row["date"] == ["2026-11-24", "2026-11-25"]
    assert row["command"] == ["train --algo drqv2"] * 2 + ["train --algo drqv2 --seed 2"]
    low, high = row["iqm_ci"]
    assert low <= row["iqm"] <= high
    frames, returns = curves["drqv2"]
    assert frames[-1] == 400_000 and returns.shape == (20, 3)
    pixels.figure("walker_walk_pixels", curves, tmp_path / "pixels_walker_walk.png")
    assert (tmp_path / "pixels_walker_walk.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_pixel_rows_report_the_labels_each_seed_got(tmp_path, monkeypatch):
    pixels = _experiment(monkeypatch, "pixels")
    monkeypatch.setattr(pixels, "RESULTS", tmp_path)
    grid = tmp_path / "runs" / "rebel_grid"  # PEBBLE (lambda 0) and REBEL in one program, 2 seeds each
    _fake_curve_run(grid, "rebel", 1.0, 4, lams=[0, 0.001, 0, 0.001], task="walker_walk_pixels")
    alone = tmp_path / "runs" / "rebel_more"  # one more REBEL seed from another job
    _fake_curve_run(alone, "rebel", 1.0, 1, lams=[0.001], task="walker_walk_pixels")
    for run, used in ((grid, [170, 170, 160, 170]), (alone, [170])):
        rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        rows[-3]["labels_used"] = [u - 10 for u in used]  # an earlier round's count
        rows[-2]["labels_used"] = used  # the last count logged
        rows[-1]["labels_used"] = None  # the last round logs none
        (run / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = {r["method"]: r for r in pixels.rows("walker_walk_pixels", [grid, alone])[0]}
    assert out["pebble (rebel lam=0)"]["labels"] == [170, 160] and out["rebel lam=0.001"]["labels"] == 170
    assert out["rebel lam=0.001"]["seeds"] == 3 and out["rebel lam=0.001"]["labels_asked"] == 100
    drqv2 = tmp_path / "runs" / "drqv2"
    _fake_curve_run(drqv2, "drqv2", 1.0, 1, task="walker_walk_pixels")
    (row,) = pixels.rows("walker_walk_pixels", [drqv2])[0]
    assert row["labels"] is None and row["labels_asked"] is None


def test_pixel_rows_keep_runs_of_different_lengths_apart_and_average_the_sessions_reward_measures(
    tmp_path, monkeypatch
):
    pixels = _experiment(monkeypatch, "pixels")
    monkeypatch.setattr(pixels, "RESULTS", tmp_path)
    task = "cheetah_run_pixels"
    long, short = tmp_path / "runs" / "surf_long", tmp_path / "runs" / "surf_short"
    _fake_curve_run(long, "surf", 1.0, 2, task=task)  # to 200k agent steps
    _fake_curve_run(short, "surf", 2.0, 3, task=task)
    rng = np.random.default_rng(0)
    logged = {}
    for run, seeds, end in ((long, 2, 200_000), (short, 3, 100_000)):
        rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
        rows = [r for r in rows if r["env_steps"] <= end]
        for i, r in enumerate(rows):  # a session every other round; NaN in the others, as the pixel round logs
            for name in pixels.REWARD_METRICS:
                r[name] = rng.uniform(size=seeds).tolist() if i % 2 == 0 else [float("nan")] * seeds
        (run / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
        logged[run.name] = rows
    out, curves = pixels.rows(task, [long, short])
    # Two rows of one method, not its 5 seeds merged at the shorter run's 100k steps.
    assert [(r["method"], r["seeds"], r["frames"]) for r in out] == [("surf", 3, 200_000), ("surf", 2, 400_000)]
    assert out[0]["final_returns"] == [2.0 * 55] * 3 and out[1]["final_returns"] == [155.0] * 2
    assert set(curves) == {"surf (to 200k)", "surf (to 400k)"} and curves["surf (to 400k)"][0][-1] == 400_000
    for row, run in zip(out, ("surf_short", "surf_long"), strict=True):
        for name in pixels.REWARD_METRICS:
            sessions = [r[name] for i, r in enumerate(logged[run]) if i % 2 == 0]
            expected = [sum(s[c] for s in sessions) / len(sessions) for c in range(row["seeds"])]
            assert row[name] == pytest.approx(expected, abs=1e-3)
    # Up to a step: the matched entries average only the sessions before it.
    (entry,) = [e for e in pixels.matched(task, 60_000, [long])[0]]
    early = [
        r["reward_accuracy_new"] for i, r in enumerate(logged["surf_long"]) if i % 2 == 0 and r["env_steps"] <= 60_000
    ]
    assert entry["reward_accuracy_new"] == pytest.approx([sum(s[c] for s in early) / 3 for c in range(2)], abs=1e-3)
    drqv2 = tmp_path / "runs" / "drqv2"
    _fake_curve_run(drqv2, "drqv2", 1.0, 1, task=task)
    (row,) = pixels.rows(task, [drqv2])[0]
    assert "reward_accuracy_new" not in row  # no learned reward


def test_pixel_stopped_runs_list_every_evaluation_against_frames(tmp_path, monkeypatch):
    pixels = _experiment(monkeypatch, "pixels")
    monkeypatch.setattr(pixels, "RESULTS", tmp_path)
    run = tmp_path / "runs" / "drqv2_stopped"
    _fake_curve_run(run, "drqv2", 2.0, 1, task="walker_walk_pixels")
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    rows.insert(1, {"env_steps": 15_000, "eval_return": None})  # a round without an evaluation
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    shorter = tmp_path / "runs" / "drqv2_stopped_earlier"  # two seeds, stopped at 100k agent steps
    _fake_curve_run(shorter, "drqv2", 1.0, 2, task="walker_walk_pixels")
    rows = [json.loads(line) for line in (shorter / "metrics.jsonl").read_text().splitlines()]
    (shorter / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows if r["env_steps"] <= 100_000) + "\n")
    entries, curves = pixels.stopped("walker_walk_pixels", [run, shorter])
    entry, earlier = entries
    # Every evaluation (10k..200k agent steps, return 2 per thousand steps) at twice the steps in frames.
    assert entry["evaluations"] == [[2 * s, 2.0 * s / 1000] for s in range(10_000, 200_001, 10_000)]
    assert entry["frames"] == 400_000 and entry["seeds"] == 1 and entry["log"] == ["results/runs/drqv2_stopped"]
    assert entry["last10_returns"] == [2.0 * 155]  # the mean of 110k..200k steps' returns
    # Each directory is its own entry and curve (their lengths differ), not seeds merged into one.
    assert earlier["frames"] == 200_000 and earlier["seeds"] == 2 and earlier["last10_returns"] == [55.0, 55.0]
    assert set(curves) == {"drqv2 (stopped; last evaluation at 400k)", "drqv2 (stopped; last evaluation at 200k)"}
    assert curves["drqv2 (stopped; last evaluation at 400k)"][0][-1] == 400_000
    assert (entry["mean"], entry["labels"], entry["labels_asked"]) == (310.0, None, None)
    assert entry["iqm_ci"] == [None, None]  # one seed has no interval
    json.dumps(entries, allow_nan=False)  # strict JSON: no NaN
    # A stopped PEBBLE-and-REBEL program: per method its labels got, and the statistics of its last-10 scores.
    grid = tmp_path / "runs" / "rebel_grid_stopped"
    _fake_curve_run(grid, "rebel", 1.0, 4, lams=[0, 0.001, 0, 0.001], task="cheetah_run_pixels")
    rows = [json.loads(line) for line in (grid / "metrics.jsonl").read_text().splitlines()]
    rows[-1]["labels_used"] = [200, 175, 200, 175]
    (grid / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = {e["method"]: e for e in pixels.stopped("cheetah_run_pixels", [grid])[0]}
    pebble, rebel = out["pebble (rebel lam=0)"], out["rebel lam=0.001"]
    assert (pebble["labels"], rebel["labels"], rebel["labels_asked"]) == (200, 175, 100)
    assert pebble["last10_returns"] == [155.0, 155.0] and pebble["mean"] == 155.0 and pebble["std"] == 0.0
    low, high = rebel["iqm_ci"]
    assert low <= rebel["iqm"] <= high and rebel["seeds"] == 2


def test_pixel_matched_pools_each_methods_seeds_at_the_steps_every_run_reached(tmp_path, monkeypatch):
    pixels = _experiment(monkeypatch, "pixels")
    monkeypatch.setattr(pixels, "RESULTS", tmp_path)
    runs = tmp_path / "runs"
    task = "cheetah_run_pixels"
    # A stopped PEBBLE-and-REBEL program (to 80k agent steps), a finished one on other seeds, and a SURF run.
    _fake_curve_run(runs / "grid_stopped", "rebel", [1.0, 2.0, 3.0, 4.0], 4, lams=[0, 0, 0.001, 0.001], task=task)
    rows = [json.loads(line) for line in (runs / "grid_stopped" / "metrics.jsonl").read_text().splitlines()]
    (runs / "grid_stopped" / "metrics.jsonl").write_text(
        "\n".join(json.dumps(r) for r in rows if r["env_steps"] <= 80_000) + "\n"
    )
    _fake_curve_run(runs / "grid", "rebel", [5.0, 6.0, 7.0, 8.0], 4, lams=[0, 0, 0.001, 0.001], task=task)
    _fake_curve_run(runs / "surf", "surf", 0.5, 3, task=task)
    for name in ("grid_stopped", "grid", "surf"):  # 25 labels per column every 10k agent steps
        rows = [json.loads(line) for line in (runs / name / "metrics.jsonl").read_text().splitlines()]
        columns = len(rows[0]["eval_return"])
        for r in rows:
            r["labels_used"] = [25 * (r["env_steps"] // 10_000)] * columns
        (runs / name / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    dirs = [runs / n for n in ("grid_stopped", "grid", "surf")]
    entries, curves = pixels.matched(task, 80_000, dirs)
    out = {e["method"]: e for e in entries}
    assert set(out) == {"pebble (rebel lam=0)", "rebel lam=0.001", "surf"}
    # Per seed the mean of its 8 evaluations (10k..80k agent steps: 45 times the slope) and the one at 80k.
    pebble = out["pebble (rebel lam=0)"]
    assert pebble["matched_returns"] == [45.0, 90.0, 225.0, 270.0] and pebble["seeds"] == 4
    assert pebble["last_evaluation"] == [80.0, 160.0, 400.0, 480.0] and pebble["frames"] == 160_000
    assert out["rebel lam=0.001"]["matched_returns"] == [135.0, 180.0, 315.0, 360.0]
    assert out["surf"]["matched_returns"] == [22.5] * 3 and out["surf"]["log"] == ["results/runs/surf"]
    # The labels every seed had by 80k agent steps, not by its run's end (200k for two of the three runs).
    assert [out[m]["labels"] for m in sorted(out)] == [200, 200, 200] and pebble["labels_asked"] == 100
    assert pebble["log"] == ["results/runs/grid_stopped", "results/runs/grid"]
    assert pebble["evaluations"][-1] == [160_000, (80 + 160 + 400 + 480) / 4]
    frames, returns = curves["surf"]
    assert frames[-1] == 160_000 and returns.shape == (8, 3)
    json.dumps(entries, allow_nan=False)
    with pytest.raises(ValueError, match="90000 agent steps"):  # the stopped program has no evaluation there
        pixels.matched(task, 90_000, dirs)


def test_pixel_paired_compares_two_methods_on_the_seed_keys_they_share(tmp_path, monkeypatch):
    pixels = _experiment(monkeypatch, "pixels")
    monkeypatch.setattr(pixels, "RESULTS", tmp_path)
    runs, task = tmp_path / "runs", "cheetah_run_pixels"
    # PEBBLE (lambda 0) and REBEL from --seed 0 and --seed 2 (2 seeds each, lambda-major as cli.column_keys tiles
    # them), and SURF from --seed 0 with 3 seeds: SURF shares keys (0, 0) and (0, 1) with PEBBLE.
    grid = [0, 0, 0.001, 0.001]
    _fake_curve_run(runs / "grid0", "rebel", [1.0, 2.0, 1.5, 1.0], 4, lams=grid, task=task)
    _fake_curve_run(runs / "grid2", "rebel", [3.0, 1.0, 4.0, 3.0], 4, lams=grid, task=task, train_seed=2)
    _fake_curve_run(runs / "surf", "surf", [2.0, 2.0, 5.0], 3, task=task)
    entries = pixels.rows(task, [runs / n for n in ("grid0", "grid2", "surf")])[0]
    by = {e["method"]: e for e in entries}
    assert by["pebble (rebel lam=0)"]["keys"] == [[0, 0], [0, 1], [2, 0], [2, 1]]
    assert by["surf"]["keys"] == [[0, 0], [0, 1], [0, 2]]
    (rebel,) = pixels.paired(entries, "pebble (rebel lam=0)", "rebel lam=0.001", "final_returns")
    # Final return = 155 x slope (the last 10 evaluations, 110k-200k agent steps); REBEL minus PEBBLE per key.
    expected = [155 * (1.5 - 1.0), 155 * (1.0 - 2.0), 155 * (4.0 - 3.0), 155 * (3.0 - 1.0)]
    assert rebel["keys"] == [[0, 0], [0, 1], [2, 0], [2, 1]] and rebel["differences"] == pytest.approx(expected)
    assert rebel["mean"] == pytest.approx(np.mean(expected), abs=0.01) and rebel["frames"] == 400_000
    assert rebel["sem"] == pytest.approx(np.std(expected, ddof=1) / 2, abs=0.01)
    assert (rebel["positive"], rebel["pairs"], rebel["sign_test_p"]) == (3, 4, 0.625)
    # Ranks of |77.5|, |-155|, |155|, |310|: 1, 2.5, 2.5, 4; 8 of the 16 sign patterns lie as far from 5 as 7.5.
    assert rebel["signed_rank_p"] == 0.5
    # What 4 keys, and the planned 5, 10 and 20, can resolve at this spread, fewer keys needing a larger difference.
    detectable = {str(n): analysis.detectable_difference(expected, n) for n in (4, 5, 10, 20)}
    assert rebel["detectable"] == pytest.approx(detectable, abs=0.01)
    assert rebel["detectable"]["4"] > rebel["detectable"]["5"] > rebel["detectable"]["10"] > rebel["detectable"]["20"]
    low, high = rebel["mean_ci"]
    assert min(expected) <= low <= rebel["mean"] <= high <= max(expected)
    (surf,) = pixels.paired(entries, "pebble (rebel lam=0)", "surf", "final_returns")
    assert surf["keys"] == [[0, 0], [0, 1]] and surf["differences"] == pytest.approx([155.0, 0.0])
    assert (surf["positive"], surf["pairs"]) == (1, 1)  # a zero difference is no pair of the sign test
    assert surf["detectable"]["2"] is not None and surf["detectable"]["5"] < surf["detectable"]["2"]
    assert pixels.paired(entries, "surf", "drqv2", "final_returns") == []  # no such method: no entry
    json.dumps(rebel, allow_nan=False)
    # A learned-reward measure that a seed lacks (null) leaves that key out; such measures keep 3 decimals.
    by["pebble (rebel lam=0)"]["reward_correlation"] = [0.1, None, 0.2, 0.3]
    by["rebel lam=0.001"]["reward_correlation"] = [0.1234, 0.5, 0.25, None]
    (correlation,) = pixels.paired(entries, "pebble (rebel lam=0)", "rebel lam=0.001", "reward_correlation")
    assert correlation["keys"] == [[0, 0], [2, 0]] and correlation["differences"] == [0.023, 0.05]


def test_pixel_coupling_ranks_return_differences_against_reward_differences_on_shared_keys(monkeypatch):
    pixels = _experiment(monkeypatch, "pixels")
    base = {"task": "cheetah_run", "frames": 300_000, "a": "pebble", "b": "rebel"}
    keys = [[0, 0], [0, 1], [2, 0], [2, 1], [4, 0]]
    returns = base | {"scores": "final_returns", "keys": keys, "differences": [-3.0, -82.0, 8.5, 121.0, 27.0]}
    # The learned-reward entry lacks key (4, 0) (a seed without the measure), and lists its keys in another order.
    reward = base | {"scores": "reward_correlation", "keys": [keys[i] for i in (3, 0, 2, 1)]}
    reward["differences"] = [0.03, -0.04, 0.07, -0.1]
    other = base | {"frames": 160_000, "scores": "final_returns", "keys": keys[:2], "differences": [1.0, 2.0]}
    (entry,) = pixels.coupling([returns, reward, other])  # 160k has no reward entry: none
    rho, p = analysis.rank_correlation([-3.0, -82.0, 8.5, 121.0], [-0.04, -0.1, 0.07, 0.03])
    assert entry == base | {"measure": "reward_correlation", "keys": 4, "spearman": round(rho, 3),
                            "permutation_p": round(p, 4)}  # fmt: skip
    assert rho == 0.8  # ranks 2, 1, 3, 4 against 2, 1, 4, 3
    few = reward | {"keys": keys[:2], "differences": [0.1, 0.2]}
    assert pixels.coupling([returns, few]) == []  # 2 shared keys: no rank correlation


def test_pixel_pooled_scales_each_tasks_key_differences_by_its_reference_and_pools_the_keys(monkeypatch):
    pixels = _experiment(monkeypatch, "pixels")
    monkeypatch.setattr(
        pixels, "POOLED", {"b minus a": {"cheetah_run_pixels": ("a", "b"), "walker_walk_pixels": ("p", "q")}}
    )
    monkeypatch.setattr(pixels, "REFERENCE", {"cheetah_run_pixels": "drqv2", "walker_walk_pixels": "drqv2 f32"})
    table = [
        {"task": "cheetah_run", "method": "drqv2", "frames": 1_000_000, "mean": 500.0},
        {"task": "walker_walk", "method": "drqv2", "frames": 1_000_000, "mean": 1.0},  # not walker's reference
        {"task": "walker_walk", "method": "drqv2 f32", "frames": 1_000_000, "mean": 800.0},
    ]
    entry = {"scores": "final_returns", "keys": [[0, 0], [1, 0]]}
    pairs = [
        entry | {"task": "cheetah_run", "frames": 300_000, "a": "a", "b": "b", "differences": [100.0, -50.0]},
        entry | {"task": "cheetah_run", "frames": 160_000, "a": "a", "b": "b", "differences": [9.0, 9.0]},  # shorter
        entry | {"task": "cheetah_run", "frames": 300_000, "a": "b", "b": "a", "differences": [-100.0, 50.0]},
        entry | {"task": "cheetah_run", "frames": 300_000, "scores": "reward_correlation", "a": "a", "b": "b",
                 "differences": [0.5, 0.5]},
        entry | {"task": "walker_walk", "frames": 500_000, "a": "p", "b": "q", "keys": [[0, 0], [1, 0], [2, 0]],
                 "differences": [400.0, 0.0, -80.0]},
    ]  # fmt: skip
    (out,) = pixels.pooled(pairs, table)
    expected = np.array([100 / 500, -50 / 500, 400 / 800, 0.0, -80 / 800])
    assert out["comparison"] == "b minus a" and out["differences"] == pytest.approx(expected)
    assert out["mean"] == pytest.approx(expected.mean(), abs=1e-3)
    assert out["sem"] == pytest.approx(expected.std(ddof=1) / np.sqrt(5), abs=1e-3)
    assert (out["positive"], out["pairs"]) == (2, 4)  # the zero is no pair
    assert out["detectable"] == pytest.approx(
        {str(n): analysis.detectable_difference(expected, n) for n in (5, 10, 20)}, abs=1e-3
    )
    assert out["tasks"] == [
        {"task": "cheetah_run", "frames": 300_000, "a": "a", "b": "b", "keys": 2, "reference": "drqv2",
         "reference_frames": 1_000_000, "reference_mean": 500.0},
        {"task": "walker_walk", "frames": 500_000, "a": "p", "b": "q", "keys": 3, "reference": "drqv2 f32",
         "reference_frames": 1_000_000, "reference_mean": 800.0},
    ]  # fmt: skip
    json.dumps(out, allow_nan=False)
    assert pixels.pooled(pairs[:4], table) == []  # one task alone is no pooled entry
    with pytest.raises(ValueError, match="walker_walk_pixels: 0 rows of the reference 'drqv2 f32', not one"):
        pixels.pooled(pairs, table[:2])


def test_the_pixel_paper_figure_draws_its_panels_methods_and_refuses_a_missing_one(tmp_path, monkeypatch):
    pixels = _experiment(monkeypatch, "pixels")
    monkeypatch.setattr(pixels, "RESULTS", tmp_path)
    task = "cheetah_run_pixels"
    _fake_curve_run(tmp_path / "runs" / "grid", "rebel", [1.0, 2.0], 2, lams=[0, 0.001], task=task)
    table, curves = pixels.rows(task, [tmp_path / "runs" / "grid"])
    names = {"pebble (rebel lam=0)": "PEBBLE", "rebel lam=0.001": "REBEL"}
    monkeypatch.setattr(pixels, "PAPER_FIGURE", {task: ("Visual Cheetah", names)})
    drawn = []
    monkeypatch.setattr(pixels, "plot_curves", lambda ax, runs: drawn.append(runs) or analysis.plot_curves(ax, runs))
    pixels.paper_figure({task: curves}, table, tmp_path / "paper.png")
    assert (tmp_path / "paper.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert [list(runs) for runs in drawn] == [["PEBBLE"], ["REBEL"]]  # the fakes log no labels_used: none named
    for runs, label in zip(drawn, names, strict=True):
        frames, returns = next(iter(runs.values()))
        np.testing.assert_array_equal(frames, curves[label][0])
        np.testing.assert_array_equal(returns, curves[label][1])
    monkeypatch.setattr(pixels, "PAPER_FIGURE", {task: ("Visual Cheetah", {"surf": "PEBBLE+SURF"})})
    with pytest.raises(ValueError, match=r"no curves \['surf'\]"):
        pixels.paper_figure({task: curves}, table, tmp_path / "paper.png")


def test_rebel_chosen_lambda_is_the_highest_iqm_of_the_papers_v_at_500k(monkeypatch):
    rebel = _experiment(monkeypatch, "rebel")
    paper = {"algo": "rebel", "estimator": "onpolicy", "variant": rebel.PAPER_VARIANT, "task": "walker_walk"}
    paper |= {"teacher": "oracle"}
    rows = [
        {**paper, "lam": 0.01, "iqm": 300.0, "env_steps": 500_000},
        {**paper, "lam": 0.001, "iqm": 990.0, "env_steps": 500_000, "teacher": "noisy"},  # another teacher
        {**paper, "lam": 0.0, "iqm": 990.0, "env_steps": 500_000},  # lambda 0 is PEBBLE, not a lambda to choose
        {**paper, "lam": -0.01, "iqm": 200.0, "env_steps": 500_000},
        {**paper, "lam": 0.1, "iqm": 900.0, "env_steps": 140_000},  # stopped early: not eligible
        {**paper, "lam": 0.001, "iqm": 800.0, "env_steps": 500_000, "estimator": "replay"},  # another V
        {**paper, "lam": -0.001, "iqm": 700.0, "env_steps": 500_000, "variant": "penalty, raw, tanh output"},
        {"algo": "pebble", "estimator": None, "variant": None, "lam": None, "iqm": 999.0, "env_steps": 500_000},
    ]
    assert rebel.chosen_lambda(rows) == {"task": "walker_walk", "lam": 0.01, "iqm": 300.0, "among": [-0.01, 0.01]}
    assert rebel.chosen_lambda(rows[4:]) is None


def test_rebel_sign_pairs_pair_seeds_within_one_program_and_sign_test_them(monkeypatch):
    rebel = _experiment(monkeypatch, "rebel")
    row = lambda lam, finals, log: {
        "algo": "rebel",
        "task": "walker_walk",
        "lam": lam,
        "final_returns": finals,
        "log": log,
    }
    rows = [
        row(0.01, [5.0, 3.0, 1.0], ["a"]),
        row(-0.01, [1.0, 4.0, 1.0], ["a"]),  # differences 4, -1, 0 (a tie: not a pair)
        row(0.001, [9.0, 9.0, 9.0], ["b"]),
        row(-0.001, [1.0, 2.0, 3.0], ["b"]),  # 8, 7, 6
        row(0.1, [9.0, 9.0, 9.0], ["c"]),  # its -0.1 ran in another program: seeds do not pair
        row(-0.1, [1.0, 1.0, 1.0], ["d"]),
        {"algo": "pebble", "task": "walker_walk", "lam": None, "final_returns": [0.0] * 3, "log": ["e"]},
    ]
    out = rebel.sign_pairs(rows)
    assert [(e["lam"], e["differences"], e["positive"], e["pairs"]) for e in out] == [
        (0.01, [4.0, -1.0, 0.0], 1, 2),
        (0.001, [8.0, 7.0, 6.0], 3, 3),
        ("all", [4.0, -1.0, 0.0, 8.0, 7.0, 6.0], 4, 5),
    ]
    # Two-sided sign test by hand: 1 of 2 -> 2 * (1 + 2) / 4 capped at 1; 3 of 3 -> 2 / 8; 4 of 5 -> 2 * 6 / 32.
    assert [e["sign_test_p"] for e in out] == [1.0, 0.25, 0.375]
    assert rebel.sign_pairs(rows[4:]) == []


def test_rebel_paper_pairs_pair_the_papers_term_with_another_setting_of_the_same_seed_keys(monkeypatch):
    rebel = _experiment(monkeypatch, "rebel")
    base = {"algo": "rebel", "task": "walker_walk", "variant": rebel.PAPER_VARIANT, "train_seed": 2, "seeds": 3}
    base |= {"teacher": "oracle"}
    row = lambda estimator, lam, finals, log, **other: (
        base
        | {
            "estimator": estimator,
            "lam": lam,
            "final_returns": finals,
            "log": [log],
            **other,
        }
    )
    rows = [
        row("onpolicy", 0.001, [5.0, 3.0, 9.0], "a"),
        row("onpolicy", 0.01, [2.0, 2.0, 2.0], "a"),
        row("replay", 0.001, [1.0, 4.0, 9.0], "b"),  # differences 4, -1, 0 (a tie: not a pair)
        row("replay", 0.01, [1.0, 1.0, 1.0], "b"),  # 1, 1, 1
        row("replay", 0.1, [1.0, 1.0, 1.0], "b"),  # no on-policy twin
        row("replay", 0.001, [0.0, 0.0, 0.0], "c", train_seed=1),  # other seed keys: no pair
        row("replay", 0.01, [0.0, 0.0, 0.0], "d", variant="penalty, raw, tanh output"),  # another term
        row("onpolicy", 0.01, [3.0, 1.0, 2.0], "e", variant=rebel.SIGMOID_VARIANT),  # -1, 1, 0 against "a"
        row("onpolicy", 0.01, [9.0, 9.0, 9.0], "f", teacher="noisy"),  # the paper's term under another teacher
        {"algo": "pebble", "task": "walker_walk", "lam": None, "variant": None, "final_returns": [0.0] * 3},
    ]
    out = rebel.paper_pairs(rows, estimator="replay")
    assert [(e["lam"], e["differences"], e["positive"], e["pairs"]) for e in out] == [
        (0.001, [4.0, -1.0, 0.0], 1, 2),
        (0.01, [1.0, 1.0, 1.0], 3, 3),
        ("all", [4.0, -1.0, 0.0, 1.0, 1.0, 1.0], 4, 5),
    ]
    assert [e["log"] for e in out[:2]] == [[["a"], ["b"]]] * 2
    # By hand: 1 of 2 -> 1 (capped); 3 of 3 -> 2 / 8; 4 of 5 -> 2 * 6 / 32.
    assert [e["sign_test_p"] for e in out] == [1.0, 0.25, 0.375]
    assert rebel.paper_pairs(rows[2:], estimator="replay") == []
    sigmoid = rebel.paper_pairs(rows, variant=rebel.SIGMOID_VARIANT)
    assert [(e["lam"], e["differences"], e["log"]) for e in sigmoid[:1]] == [(0.01, [-1.0, 1.0, 0.0], [["a"], ["e"]])]
    assert sigmoid[-1]["lam"] == "all" and (sigmoid[-1]["positive"], sigmoid[-1]["pairs"]) == (1, 2)
    with pytest.raises(ValueError, match="paper's"):
        rebel.paper_pairs(rows)


def test_rebel_lambda_figure_draws_the_papers_v_at_500k_by_lambda(tmp_path, monkeypatch):
    rebel = _experiment(monkeypatch, "rebel")
    paper = {"algo": "rebel", "estimator": "onpolicy", "variant": rebel.PAPER_VARIANT, "method": "rebel", "task": "t"}
    paper |= {"teacher": "oracle"}
    rows = [
        {**paper, "lam": 0.01, "iqm": 300.0, "iqm_ci": [250.0, 350.0], "env_steps": 500_000},
        {**paper, "lam": -0.01, "iqm": 200.0, "iqm_ci": [150.0, 260.0], "env_steps": 500_000},
        {**paper, "lam": 0.1, "iqm": 900.0, "iqm_ci": [800.0, 950.0], "env_steps": 140_000},  # stopped: not drawn
        {**paper, "lam": 0.001, "iqm": 800.0, "iqm_ci": [0.0, 1.0], "env_steps": 500_000, "estimator": "replay"},
        {"algo": "pebble", "method": "pebble", "task": "t", "lam": None, "iqm": 400.0, "iqm_ci": [300.0, 500.0]},
        {"algo": "surf", "method": "surf", "task": "walker_walk", "lam": None, "iqm": 600.0, "iqm_ci": [0.0, 1.0]},
    ]
    path = tmp_path / "lambda.png"
    assert rebel.lambda_figure(rows, path, "t") == ([-0.01, 0.01], [200.0, 300.0])
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def _takeoff_run(run: pathlib.Path, precision: str, out_f32: bool, finals: list[float]) -> None:
    """A DrQ-v2 walker run of one column per entry of ``finals``: each seed's return ramps from 25 at 10k agent
    steps to its final at 60k (120k frames)."""
    run.mkdir(parents=True)
    cfg = {
        "algo": "drqv2",
        "env": {"task": "walker_walk_pixels"},
        "drqv2": {"precision": precision, "critic_out_f32": out_f32},
    }
    (run / "config.json").write_text(json.dumps(cfg))
    steps = np.arange(10_000, 60_001, 10_000)
    returns = 25.0 + np.outer((steps - 10_000) / 50_000, np.asarray(finals) - 25.0)
    lines = [json.dumps({"env_steps": int(s), "eval_return": r.tolist()}) for s, r in zip(steps, returns, strict=True)]
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")


def _walker_run(run: pathlib.Path, out_f32: bool, returns: np.ndarray) -> None:
    """A DrQ-v2 walker run (bf16) with ``returns`` (evals, seeds) at every 10k agent steps."""
    _takeoff_run(run, "bf16", out_f32, [25.0] * returns.shape[1])
    steps = 10_000 * np.arange(1, len(returns) + 1)
    lines = [json.dumps({"env_steps": int(s), "eval_return": r.tolist()}) for s, r in zip(steps, returns, strict=True)]
    (run / "metrics.jsonl").write_text("\n".join(lines) + "\n")


def test_takeoff_full_length_pools_each_arms_seeds_by_their_own_final_returns(tmp_path, monkeypatch):
    takeoff = _experiment(monkeypatch, "takeoff")
    rng = np.random.default_rng(0)
    long, stopped = rng.uniform(0, 1000, (25, 2)), rng.uniform(0, 300, (24, 1))  # 500k and 480k frames
    stopped[-12:] = 20.0  # its seed ends on the plateau: the last 10 evaluations alone decide
    _walker_run(tmp_path / "long", False, long)
    _walker_run(tmp_path / "stopped", False, stopped)
    _walker_run(tmp_path / "f32", True, np.full((25, 3), 900.0))
    reference = {"ref": (np.array([20.0, 800.0]), 500_000, "ref.csv")}
    out = takeoff.full_length([tmp_path / d for d in ("long", "stopped", "f32")], reference)
    plain = out["arms"]["bf16"]
    expected = [float(np.mean(long[-10:, j])) for j in range(2)] + [20.0]  # not cut to the stopped run's length
    np.testing.assert_allclose(plain["final_returns"], np.round(expected, 1))
    assert plain["walked"] == sum(v > takeoff.THRESHOLD for v in expected)
    assert plain["frames"] == [500_000, 480_000] and plain["seeds"] == 3
    f32, ref = out["arms"]["bf16 + float32 critic output"], out["arms"]["ref"]
    assert (f32["walked"], f32["frames"], ref["walked"], ref["log"]) == (3, 500_000, 1, ["ref.csv"])
    tables = {tuple(t["arms"]): t["table"] for t in out["fisher"]}
    assert tables[("bf16", "bf16 + float32 critic output")] == [[plain["walked"], 3 - plain["walked"]], [3, 0]]
    assert len(tables) == 3


def test_takeoff_counts_seeds_above_the_plateau_per_arm_named_by_config(tmp_path, monkeypatch):
    takeoff = _experiment(monkeypatch, "takeoff")
    plain = [25.0, 400.0, 30.0, 500.0, 600.0, 350.0, 450.0, 300.0]  # two stay on the plateau
    _takeoff_run(tmp_path / "a", "bf16", False, plain[:5])  # one arm's seeds over two directories
    _takeoff_run(tmp_path / "b", "bf16", False, plain[5:])
    _takeoff_run(tmp_path / "looks_like_bf16_but_is_f32", "bf16", True, [400.0] * 8)
    out = takeoff.summary(*takeoff.arm_curves([tmp_path / d for d in ("a", "b", "looks_like_bf16_but_is_f32")]))
    a, b = out["arms"]["bf16"], out["arms"]["bf16 + float32 critic output"]
    # Late means: evaluations at 50k and 60k agent steps (100k and 120k frames): 25 + 0.9 (final - 25).
    np.testing.assert_allclose(a["late_means"], [round(25 + 0.9 * (f - 25), 1) for f in plain])
    assert (a["seeds"], a["took_off"], b["took_off"], a["frames"]) == (8, 6, 8, 120_000)
    # Clopper-Pearson from the beta quantiles, and Fisher's two-sided p from the hypergeometric tables.
    low, high = scipy.stats.beta.ppf(0.025, 6, 3), scipy.stats.beta.ppf(0.975, 7, 2)
    np.testing.assert_allclose(a["rate_ci"], [round(low, 3), round(high, 3)])
    (test,) = out["fisher"]
    assert test["table"] == [[6, 2], [8, 0]]
    prob = [math.comb(14, k) * math.comb(2, 8 - k) / math.comb(16, 8) for k in range(6, 9)]
    np.testing.assert_allclose(test["fisher_p"], sum(p for p in prob if p <= prob[0] * (1 + 1e-9)))
    # A reference arm (DrQ-v2's own curves in main) is judged by the same criterion, from its own frames on.
    reference = (np.array([80_000, 100_000, 120_000]), np.array([[500.0, 20.0], [90.0, 20.0], [120.0, 500.0]]))
    curves, logs = takeoff.arm_curves([tmp_path / "a"])
    out = takeoff.summary(curves | {"ref": reference}, logs | {"ref": ["somewhere.csv"]})
    assert out["arms"]["ref"]["late_means"] == [105.0, 260.0]
    assert (out["arms"]["ref"]["took_off"], out["arms"]["ref"]["log"]) == (2, ["somewhere.csv"])
    assert [t["arms"] for t in out["fisher"]] == [["bf16", "ref"]]
    sac = tmp_path / "sac"
    _takeoff_run(sac, "bf16", False, [25.0])
    cfg = json.loads((sac / "config.json").read_text()) | {"algo": "sac"}
    (sac / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match="DrQ-v2 on walker_walk"):
        takeoff.arm_curves([sac])


def test_sample_std_is_numpys_with_one_degree_of_freedom_and_undefined_for_one_value():
    x = np.random.default_rng(3).normal(size=5)
    assert analysis.sample_std(x) == pytest.approx(np.sqrt(np.sum((x - x.mean()) ** 2) / (x.size - 1)))
    assert math.isnan(analysis.sample_std([1.0]))


# -- runs compared by key ----------------------------------------------------------------
def _keyed(tmp_path, name: str, seed: int, end: list[float]) -> dict:
    run_dir = write_run(tmp_path / name, RETURNS)
    config = json.loads((run_dir / "config.json").read_text())
    (run_dir / "config.json").write_text(json.dumps(config | {"train": {"seed": seed, "eval_episodes": 10}}))
    (run_dir / "final.json").write_text(json.dumps({"final_eval_return": end}))
    return analysis.keyed_run(run_dir, last=2)


def test_keyed_run_reads_both_measures_with_each_seeds_key(tmp_path):
    run = _keyed(tmp_path, "run", 3, [7.0, 8.0, 9.0])
    assert run["keys"] == [[3, 0], [3, 1], [3, 2]]
    assert run["end_of_run"] == [7.0, 8.0, 9.0]
    # The last 2 evaluations of each seed, from RETURNS by hand: (4 + 5) / 2, (8 + 10) / 2, (12 + 15) / 2.
    assert run["last10"] == [4.5, 9.0, 13.5]
    assert run["command"].endswith("--seeds 3") and run["date"] == "2026-11-23"


def test_paired_difference_takes_the_shared_keys_against_a_loop(tmp_path):
    a = {"keys": [[0, 0], [0, 1], [0, 2], [1, 0]], "end_of_run": [10.0, 4.0, 9.0, 50.0]}
    b = {"keys": [[0, 2], [0, 1], [0, 0]], "end_of_run": [3.0, 6.0, 1.0]}
    out = analysis.paired_difference(a, b, "end_of_run")
    expected = {}
    for key, value in zip(
        a["keys"], a["end_of_run"], strict=True
    ):  # the loop: a's keys that b has, b's value for the key
        for other_key, other in zip(b["keys"], b["end_of_run"], strict=True):
            if key == other_key:
                expected[tuple(key)] = value - other
    assert out["keys"] == [list(k) for k in sorted(expected)]
    assert out["differences"] == [expected[k] for k in sorted(expected)]  # 9, -2, 6
    assert out["mean"] == pytest.approx(np.mean(list(expected.values())), abs=0.01)
    assert out["positive"] == 2 and out["pairs"] == 3
    assert out["sign_test_p"] == pytest.approx(analysis.sign_test_p(2, 3))
    low, high = out["mean_ci"]
    assert min(expected.values()) <= low <= out["mean"] <= high <= max(expected.values())


def test_measured_gives_the_sample_std_and_none_for_one_seed():
    x = [1.0, 2.0, 4.0, 8.0]
    out = analysis.measured(x)
    assert out["std"] == pytest.approx(np.std(x, ddof=1), abs=0.01) and out["mean"] == 3.75 and out["seeds"] == 4
    assert out["iqm"] == pytest.approx(trimmed_mean_reference(x), abs=0.01)
    assert analysis.measured([5.0])["std"] is None
