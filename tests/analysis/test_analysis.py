"""Tests of analysis/: statistics known answers and invariants, metric definitions, the planted sweep
report (tests/analysis/synthetic_runs.py), planted answers for the statistics (false positives, a 2x speedup,
every censoring combination), partial sweeps, single runs and the sweep index."""

from __future__ import annotations

import math
import struct
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis import AnalysisError
from analysis.binomial import wilson_interval
from analysis.comparisons import baseline_comparisons, comparisons
from analysis.index import build_index, write_index
from analysis.load import load_runs, load_table
from analysis.markdown import plural
from analysis.metrics import (
    counts_as_mastered,
    first_sustained,
    mastery_per_seed,
    speedup,
    time_to_threshold,
    tracking_errors,
)
from analysis.report import build_report, main
from analysis.stats import (
    censored_pvalue,
    curve_intervals,
    iqm,
    km_median,
    permutation_pvalue,
    seed_interval,
)
from analysis.tables import SPEEDUP_COLUMNS, SUMMARY_COLUMNS, ReportOptions
from tests.analysis.synthetic_runs import (
    FAST,
    PLANTED,
    SLOW,
    UNIFORM,
    make_speedup_sweep,
    make_sweep,
    write_run,
)

RESAMPLES = 200
finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False)


# --------------------------------------------------------------------------------------------- stats
def test_iqm_known_answers():
    assert iqm(range(1, 9)) == 4.5  # drops 1, 2 and 7, 8
    assert iqm([1, 2, 3]) == 2.0  # n < 4: plain mean
    assert iqm([7.0]) == 7.0
    assert iqm([1, 2, 3, 100]) == 2.5  # the outlier is trimmed
    assert iqm([1, np.nan, 2, 3]) == 2.0  # NaNs ignored
    assert math.isnan(iqm([np.nan, np.nan]))
    cols = iqm(np.array([[1.0, 5.0], [2.0, np.nan], [3.0, 7.0], [4.0, 8.0]]), axis=0)
    np.testing.assert_allclose(cols, [2.5, 20.0 / 3.0])


@given(st.lists(finite, min_size=1, max_size=30), finite)
@settings(max_examples=60, deadline=None)
def test_iqm_invariants(values, shift):
    x = np.array(values)
    m = iqm(x)
    assert x.min() - 1e-6 <= m <= x.max() + 1e-6
    assert iqm(x[::-1]) == pytest.approx(m)
    assert iqm(x + shift) == pytest.approx(m + shift, abs=1e-6 * (1 + abs(shift) + np.abs(x).max()))


def test_seed_interval_is_the_range_below_five_seeds_and_a_bootstrap_from_five():
    # Fewer than 5 seeds: the range, never a "95%" interval; the point is the mean below 4 seeds.
    assert seed_interval([0.1, 0.3, 0.2], bootstrap=False) == pytest.approx((0.2, 0.1, 0.3, "range"))
    assert seed_interval([4.0], bootstrap=True) == (4.0, 4.0, 4.0, "range")
    assert seed_interval([1, 2, 3, 100], bootstrap=False)[0] == 2.5  # 4 seeds: the IQM
    # From 5 seeds: BCa where defined, percentile for degenerate data.
    point, low, high, method = seed_interval([1.0, 2.0, 3.0, 4.0, 7.0, 5.0], bootstrap=True, n_resamples=500)
    assert method == "bootstrap_bca" and low < point < high and point == iqm([1, 2, 3, 4, 7, 5])
    assert seed_interval([3.0] * 5, bootstrap=True) == (3.0, 3.0, 3.0, "bootstrap_percentile")
    assert math.isnan(seed_interval([np.nan, np.nan], bootstrap=True)[0])


def test_curve_intervals_match_columns_and_reproduce():
    rng = np.random.default_rng(1)
    m = rng.normal(size=(6, 4))
    m[5, 3] = np.nan  # a seed that stopped early
    a = curve_intervals(m, True, 300, seed=3)
    b = curve_intervals(m, True, 300, seed=3)
    for u, v in zip(a[:3], b[:3], strict=True):
        np.testing.assert_array_equal(u, v)
    for j in range(4):  # columns with the same seeds are resampled together, as each alone would be
        point, low, high, method = seed_interval(m[:, j], True, 300, seed=3)
        assert (point, low, high) == pytest.approx((a[0][j], a[1][j], a[2][j])) and method == a[3][j]


@given(st.lists(finite, min_size=5, max_size=10))
@settings(max_examples=25, deadline=None)
def test_bootstrap_interval_within_data(values):
    point, low, high, _ = seed_interval(values, bootstrap=True, n_resamples=100)
    assert min(values) - 1e-6 <= point <= max(values) + 1e-6
    assert low <= high + 1e-9


def test_permutation_pvalues_are_exact_for_small_n():
    # 3 vs 3 seeds: 20 equally likely splits; the observed one and its mirror are the most extreme.
    assert permutation_pvalue([1, 2, 3], [4, 5, 6]) == pytest.approx(0.1)
    assert permutation_pvalue([1, 2, 3], [1, 2, 3]) == 1.0
    assert permutation_pvalue([0.0] * 5, [1.0] * 5) == pytest.approx(2 / 252)
    assert math.isnan(permutation_pvalue([], [1.0]))
    # One seed against two (scipy refuses a group of one): 3 splits, the observed one is the most
    # extreme on one side, so p = 2 x 1/3 (capped at 1), and the same with the groups swapped.
    assert permutation_pvalue([0.0], [1.0, 2.0]) == pytest.approx(2 / 3)
    assert permutation_pvalue([1.0, 2.0], [0.0]) == pytest.approx(2 / 3)
    assert permutation_pvalue([5.0], [4.0]) == 1.0


@pytest.mark.parametrize(("successes", "trials", "low", "high"), [
    (81, 263, 0.2553, 0.3662), (15, 148, 0.0624, 0.1605), (0, 20, 0.0, 0.1611), (1, 29, 0.0061, 0.1718)])
def test_wilson_interval_matches_newcombes_published_intervals(successes, trials, low, high):
    # Newcombe (1998), Statistics in Medicine 17:857, Table I, method 3 (score interval without correction)
    got = wilson_interval(successes, trials)
    assert got == pytest.approx((low, high), abs=5e-5)


def test_wilson_interval_holds_the_estimate_narrows_with_rollouts_and_ends_at_the_bounds():
    assert wilson_interval(0, 128)[0] == 0.0 and wilson_interval(128, 128)[1] == 1.0
    assert 0.0 < wilson_interval(0, 128)[1] < 0.03  # 0 of 128 still allows up to ~3%
    widths = [np.subtract(*wilson_interval(n * 95 // 100, n)[::-1]) for n in (20, 128, 1000)]
    assert widths[0] > widths[1] > widths[2] > 0
    low, high = wilson_interval(121, 128)
    assert low < 121 / 128 < high and wilson_interval(121, 128, confidence=0.5)[0] > low
    for bad in ((1, 0), (-1, 10), (11, 10)):
        with pytest.raises(ValueError, match="successes"):
            wilson_interval(*bad)


def test_km_median_known_answers():
    assert km_median([1, 2, 3, 4, 5], [1] * 5) == 3.0  # uncensored: the ordinary median
    assert km_median([1, 2, 3, 4], [1] * 4) == 2.5
    assert math.isnan(km_median([1, 2, 9, 9], [1, 1, 0, 0]))  # exactly half got there: not reached
    assert km_median([1, 2, 3, 9], [1, 1, 1, 0]) == 2.5
    assert km_median([10, 20, 30], [1, 1, 0]) == 20.0
    # Censored early (a run still going at 5): Kaplan-Meier keeps it at risk only until then.
    assert km_median([5, 10, 20, 30], [0, 1, 1, 1]) == 20.0
    np.testing.assert_array_equal(km_median(np.array([[1, 2, 3], [4, 5, 6]]), np.ones((2, 3), bool)), [2, 5])


def test_censored_pvalue_orders_censored_times_as_later():
    assert censored_pvalue([1, 2, 3], [1, 1, 1], [10, 10, 10], [0, 0, 0]) == pytest.approx(0.1)
    assert censored_pvalue([1, 2, 3], [1, 1, 1], [1, 2, 3], [1, 1, 1]) == 1.0
    assert math.isnan(censored_pvalue([5], [0], [5], [0]))  # no event anywhere: nothing to compare


# --------------------------------------------------------------------------------------------- metrics
def test_first_sustained_needs_persistence_or_the_end_of_the_run():
    assert first_sustained([0, 1, 0, 1, 1], 2) == 3  # the blip at 1 does not count
    assert first_sustained([0, 0, 1], 2) == 2  # below for the rest of the run
    assert first_sustained([1, 0, 0], 2) == -1
    assert first_sustained([0, 1, 0, 1], 1) == 1
    assert first_sustained([], 2) == -1
    with pytest.raises(ValueError):
        first_sustained([1], 0)


def _curve(rates, bin_=0, step=5, **extra):
    n = len(rates)
    return pd.DataFrame({"run_dir": "r", "arm": "a", "seed": 0, "iteration": np.arange(n) * step,
                         "env_steps": np.arange(n) * step * 10, "wall_time_s": np.arange(n) * 1.0, "bin": bin_,
                         "failure_rate": rates, **extra})


def test_mastery_per_seed_with_persistence_and_censoring():
    df = pd.concat([
        _curve([0.5, 0.05, 0.3, 0.02, 0.01], bin_=0),  # first below at 5 but rises: mastered at 15
        _curve([0.5, 0.1, 0.1, 0.1, 0.1], bin_=1),  # exactly at the threshold: never (strictly below)
        _curve([0.0] * 5, bin_=2),  # mastered at the first evaluation
        _curve([0.5, 0.5, 0.5, 0.5, 0.05], bin_=3),  # only the last evaluation: the rest of the run
    ])
    m = mastery_per_seed(df, threshold=0.1, persist=2).set_index("bin")
    assert m.loc[0, "iteration"] == 15.0 and m.loc[0, "env_steps"] == 150.0
    assert not m.loc[1, "mastered"] and math.isnan(m.loc[1, "iteration"]) and m.loc[1, "last_iteration"] == 20.0
    assert m.loc[2, "iteration"] == 0.0
    assert m.loc[3, "iteration"] == 20.0


def test_horizon_truncated_bins_need_a_bin_tracked_through():
    df = pd.DataFrame({"failure_rate": [0.0, 0.0, 0.0, 0.5], "horizon_truncated": [False, True, True, False],
                       "tracked_through": [0, 0, 3, 9]})
    assert counts_as_mastered(df, 0.1).tolist() == [True, False, True, False]
    assert counts_as_mastered(df[["failure_rate"]], 0.1).tolist() == [True, True, True, False]  # old tables


def test_time_to_threshold_inclusive_persistent_and_never():
    curve = pd.DataFrame({
        "run": ["a"] * 4 + ["b"] * 4,
        "iteration": [0, 10, 20, 30] * 2,
        "env_steps": [0, 100, 200, 300] * 2,
        "wall_time_s": [0.0, 1.0, 2.0, 3.0] * 2,
        "success_rate": [0.5, 0.9, 0.95, 0.92, 0.95, 0.6, 0.7, 0.8],
    })
    t = time_to_threshold(curve, 0.9, persist=2, by=["run"]).set_index("run")
    assert t.loc["a", "reached"] and t.loc["a", "iteration"] == 10 and t.loc["a", "env_steps"] == 100
    assert not t.loc["b", "reached"] and math.isnan(t.loc["b", "iteration"]) and t.loc["b", "last_iteration"] == 30


@pytest.mark.parametrize("base, arm, status, ratio", [
    # (times, reached) per seed, baseline then arm; speedup = baseline median / arm median
    (([40, 40, 40], [1, 1, 1]), ([20, 20, 20], [1, 1, 1]), "estimate", 2.0),
    (([60, 60, 60], [0, 0, 0]), ([20, 30, 20], [1, 1, 1]), "lower_bound", 3.0),  # baseline censored at 60
    (([40, 20, 60], [1, 1, 0]), ([20, 60, 60], [1, 0, 0]), "upper_bound", 40 / 60),  # arm: 1/3 got there
    (([60, 60, 60], [0, 0, 1]), ([60, 60, 60], [0, 0, 0]), "not_estimable", math.nan),
    (([10, 20, 60, 60], [1, 1, 0, 0]), ([10, 10, 10, 10], [1, 1, 1, 1]), "lower_bound", 6.0),  # half is not more than half
])
def test_speedup_status_for_each_censoring_combination(base, arm, status, ratio):
    s = speedup(*base, *arm, bootstrap=False)
    assert s.status == status
    assert (math.isnan(s.ratio) and math.isnan(ratio)) or s.ratio == pytest.approx(ratio)
    assert math.isnan(s.ci_low) and math.isnan(s.ci_high)  # no interval for bounds or below 5 seeds
    assert 0.0 < s.p_value <= 1.0


# --------------------------------------------------------------------------------------------- planted answers
def _random_comparison(rng, n: int) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Two arms with no true difference: per-seed final failures and censored times to threshold."""
    rows, times = [], []
    for arm in ("a", "b"):
        for seed in range(n):
            rows.append((f"{arm}/{seed}", arm, seed, rng.beta(2, 8)))
            t = 5 * math.ceil(rng.lognormal(math.log(300), 0.3) / 5)
            reached = t <= 400  # runs end at iteration 400: later seeds are censored there
            times.append((f"{arm}/{seed}", arm, seed, reached, min(t, 400)))
    return (pd.DataFrame(rows, columns=["run_dir", "arm", "seed", "value"]),
            pd.DataFrame(times, columns=["run_dir", "arm", "seed", "reached", "time"]))


def test_baseline_comparisons_planted():
    # every seed of "better" lies below every seed of "base": the exact two-sided p for 4 v 4 is 2/70;
    # "same" interleaves with the baseline: no claim
    vals = {"base": [0.30, 0.31, 0.32, 0.33], "better": [0.20, 0.21, 0.22, 0.23], "same": [0.305, 0.315, 0.325, 0.335]}
    df = pd.DataFrame([(f"{a}/{i}", a, i, v) for a, vs in vals.items() for i, v in enumerate(vs)],
                      columns=["run_dir", "arm", "seed", "value"])
    comp = baseline_comparisons({"final_failure": df}, "final_failure", "base", ReportOptions()).set_index("arm")
    assert set(comp.index) == {"better", "same"} and (comp["baseline"] == "base").all()
    assert comp.loc["better", "difference"] == pytest.approx(-0.10)
    assert comp.loc["better", "p_value"] == pytest.approx(2 / 70) and comp.loc["better", "claim"]
    assert not comp.loc["same", "claim"]
    assert baseline_comparisons({"final_failure": df}, "final_failure", "absent", ReportOptions()).empty
    assert baseline_comparisons({"final_failure": df}, "final_failure", None, ReportOptions()).empty


@pytest.mark.parametrize("n_seeds", [3, 10])
def test_no_true_difference_is_rarely_claimed(n_seeds):
    rng = np.random.default_rng(n_seeds)
    opts = ReportOptions(n_resamples=RESAMPLES, n_permutations=2000)
    claims = {"final_failure": 0, "time": 0}
    for _ in range(200):
        final, times = _random_comparison(rng, n_seeds)
        comp = comparisons({"final_failure": final}, "final_failure", opts)
        claims["final_failure"] += int(comp["claim"].iloc[0])
        a, b = times[times["arm"] == "a"], times[times["arm"] == "b"]
        s = speedup(b["time"], b["reached"], a["time"], a["reached"], bootstrap=False,
                    n_permutations=opts.n_permutations)
        claims["time"] += int(s.p_value < opts.alpha)
    assert claims["final_failure"] <= 20 and claims["time"] <= 20, claims  # at most 10% of 200 draws


@pytest.fixture(scope="module")
def speedup_report(tmp_path_factory) -> Path:
    sweep = make_speedup_sweep(tmp_path_factory.mktemp("speed"), n_seeds=10, ratio=2.0)
    return build_report([sweep], opts=ReportOptions(n_resamples=1000))


def test_a_two_fold_speedup_is_recovered_with_ten_seeds(speedup_report):
    speed = pd.read_csv(speedup_report / "speedup.csv")
    assert list(speed.columns) == SPEEDUP_COLUMNS
    row = speed.set_index("measure").loc["iteration"]
    assert row["status"] == "estimate" and row["baseline"] == "sampler=uniform"
    assert row["ci_low"] <= 2.0 <= row["ci_high"] and row["ci_low"] > 1.0, row.to_dict()
    assert row["p_value"] < 0.01
    per_bin = pd.read_csv(speedup_report / "mastery_speedup.csv")
    assert (per_bin["status"] == "estimate").all() and (per_bin["ci_low"] > 1.0).all()
    summary = pd.read_csv(speedup_report / "summary.csv")
    assert set(summary["ci_method"]) <= {"bootstrap_bca", "bootstrap_percentile"}  # 10 seeds: bootstrap
    assert (summary.loc[summary["n_seeds"] >= 4, "iqm"].notna()).all()
    md = (speedup_report / "report.md").read_text()
    assert "against the baseline" in md and "for the 1 test " in md and "1 tests" not in md  # one arm, one test


# --------------------------------------------------------------------------------------------- planted sweep
@pytest.fixture(scope="module")
def sweep(tmp_path_factory) -> Path:
    return make_sweep(tmp_path_factory.mktemp("sweeps"))


@pytest.fixture(scope="module")
def report(sweep) -> Path:
    return build_report([sweep], opts=ReportOptions(n_resamples=RESAMPLES))


def test_load_runs_statuses(sweep):
    runs = load_runs(sweep).set_index(["arm", "seed"])
    assert set(runs.index.get_level_values("arm")) == {UNIFORM, FAST, SLOW}
    assert runs.loc[(FAST, 2), "status"] == "failed" and not runs.loc[(FAST, 2), "included"]
    assert "simulated crash" in runs.loc[(FAST, 2), "problem"]
    assert runs.loc[(SLOW, 2), "status"] == "missing" and not runs.loc[(SLOW, 2), "included"]
    assert runs.loc[(UNIFORM, 2), "status"] == "running" and runs.loc[(UNIFORM, 2), "included"]
    assert runs.loc[(UNIFORM, 2), "iteration"] == 45
    assert runs.loc[(FAST, 0), "param.sampler.gamma"] == 0.5
    assert runs.loc[(SLOW, 2), "param.sampler.gamma"] == 0.9  # a missing job inherits its arm's values
    eval_df = load_table(runs.reset_index(), "eval")
    assert {"run_dir", "arm", "seed", "segment", "failure_rate", "visits"} <= set(eval_df.columns)
    assert eval_df.groupby("run_dir").ngroups == 7


def test_planted_mastery(report):
    per_seed = pd.read_csv(report / "mastery_per_seed.csv")
    m = pd.read_csv(report / "mastery.csv")
    for arm, expected in PLANTED["mastery"].items():
        got = m[m["arm"] == arm].sort_values("bin")["mastery_iteration"].to_numpy()
        np.testing.assert_array_equal(got, expected)
        seeds = per_seed[per_seed["arm"] == arm]
        for b, it in enumerate(expected):  # every seed masters each bin at the planted iteration
            np.testing.assert_array_equal(seeds.loc[seeds["bin"] == b, "iteration"], it)
    slow = m[(m["arm"] == SLOW) & (m["bin"] == 3)].iloc[0]
    assert slow["n_mastered"] == 0 and slow["follow_up"] == 60 and slow["per_seed"] == ">60;>60"
    summary = pd.read_csv(report / "summary.csv")
    bins = summary[summary["metric"] == "bins_mastered"].set_index("arm")
    for arm, n in PLANTED["never_mastered"].items():
        assert bins.loc[arm, "mean"] == 4 - n


def test_summary_csv_columns_and_small_n_labels(report):
    summary = pd.read_csv(report / "summary.csv", keep_default_na=False)
    assert list(summary.columns) == SUMMARY_COLUMNS
    assert set(summary["ci_method"]) == {"range"}  # 2-3 seeds per arm: never a bootstrap interval
    assert (summary["iqm"] == "").all()  # below 4 seeds there is no IQM
    row = summary[(summary["arm"] == UNIFORM) & (summary["metric"] == "final_failure")].iloc[0]
    # At iteration 45 (the running seed's last evaluation) every uniform bin is mastered: 0.02 + 0.01 s.
    assert row["per_seed"] == "0.02;0.03;0.04" and float(row["mean"]) == pytest.approx(0.03)
    assert (float(row["ci_low"]), float(row["ci_high"])) == pytest.approx((0.02, 0.04))
    md = (report / "report.md").read_text()
    assert "range of 3 seeds" in md and "95%" not in md.split("## Definitions")[0]


def test_planted_speedups(report):
    speed = pd.read_csv(report / "speedup.csv").set_index(["arm", "measure"])
    for measure, ratio in PLANTED["speedup"].items():
        row = speed.loc[(FAST, measure)]
        assert row["status"] == "estimate" and row["ratio"] == pytest.approx(ratio)
        assert math.isnan(row["ci_low"])  # 2-3 seeds: no interval
        assert row["p_value"] == pytest.approx(0.2)  # 3 vs 2 seeds: 10 splits, the observed is the most extreme
    # SLOW never masters bin 3, so never reaches the threshold: its speedup is an upper bound.
    assert speed.loc[(SLOW, "iteration"), "status"] == "upper_bound"
    assert speed.loc[(SLOW, "iteration"), "ratio"] == pytest.approx(40.0 / 60.0)
    per_bin = pd.read_csv(report / "mastery_speedup.csv")
    for arm, expected in PLANTED["mastery_ratio"].items():
        got = per_bin[per_bin["arm"] == arm].sort_values("bin")
        np.testing.assert_allclose(got["ratio"], expected)
    assert per_bin[(per_bin["arm"] == SLOW) & (per_bin["bin"] == 3)]["status"].item() == "upper_bound"
    times = pd.read_csv(report / "time_to_threshold.csv")
    for arm, it in PLANTED["time_to_threshold"].items():
        got = times.loc[times["arm"] == arm, "iteration"].to_numpy()
        np.testing.assert_array_equal(got, np.full(len(got), it))
    assert len(times[times["arm"] == UNIFORM]) == 3  # the running seed reached it at 40, before 45


def test_censoring_statuses_through_the_report(tmp_path):
    """Baseline never reaches the threshold, the arm does: a lower bound, not an estimate; both never:
    not estimable."""
    never = [10.0, 20.0, 30.0, None]
    for seed in (0, 1, 2):
        write_run(tmp_path / "s" / "sampler=uniform" / f"seed={seed}", sampler="uniform", seed=seed,
                  overrides=["sampler=uniform"], mastery=never)
        write_run(tmp_path / "s" / "sampler=adaptive" / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler=adaptive"], mastery=[5.0, 10.0, 15.0, 20.0])
        write_run(tmp_path / "s" / "sampler=beyondmimic" / f"seed={seed}", sampler="beyondmimic", seed=seed,
                  overrides=["sampler=beyondmimic"], mastery=never)
    out = build_report([tmp_path / "s"], opts=ReportOptions(n_resamples=50))
    speed = pd.read_csv(out / "speedup.csv").set_index(["arm", "measure"])
    lower = speed.loc[("sampler=adaptive", "iteration")]
    assert lower["status"] == "lower_bound" and lower["ratio"] == pytest.approx(60.0 / 20.0)
    assert speed.loc[("sampler=beyondmimic", "iteration"), "status"] == "not_estimable"
    md = (out / "report.md").read_text()
    assert "≥ ×3 (a lower bound" in md and "not estimable" in md
    assert "1 not estimable" in md and "not estimables" not in md  # an adjective, never pluralised


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path.name} is not a PNG"
    return struct.unpack(">II", head[16:24])


def test_report_files(report):
    tables = ["runs", "summary", "curves", "bin_failure", "final_bin_failure", "sampling", "mastery",
              "mastery_per_seed", "mastery_speedup", "time_to_threshold", "time_to_threshold_summary", "speedup",
              "sensitivity", "segment_failure", "budget", "comparisons", "baseline_comparisons", "speedup_curve",
              "iso_failure", "sampling_support", "sampling_support_summary", "sampler_signals"]
    figures = ["curve_mean_episode_length", "curve_mean_reward", "curve_eval_failure_rate",
               "bin_failure_heatmap", "final_bin_failure", "sampling_distribution", "mastery", "speedup",
               "sensitivity_sampler.gamma", "speedup_curve", "iso_failure", "sampling_support"]
    for name in tables:
        assert len(pd.read_csv(report / f"{name}.csv")) > 0, name
    for name in figures:
        w, h = _png_size(report / f"{name}.png")
        assert 100 < w <= 1300 and 100 < h <= 600, (name, w, h)
    md = (report / "report.md").read_text()
    for name in figures:
        assert f"({name}.png)" in md
    assert not list(report.glob("*.tmp")) and not list(report.glob(".*"))


def test_report_tables_hold_no_absolute_paths_below_cwd(sweep, tmp_path, monkeypatch):
    monkeypatch.chdir(sweep.parent)
    out = build_report([sweep.name], out=tmp_path / "rep", opts=ReportOptions(n_resamples=20))
    for name in ("runs", "time_to_threshold"):
        text = (out / f"{name}.csv").read_text()
        assert str(sweep.parent) not in text, name
    runs = pd.read_csv(out / "runs.csv")
    assert runs["run_dir"].str.startswith(sweep.name + "/").all()


def test_segment_failure_planted(report):
    seg = pd.read_csv(report / "segment_failure.csv").set_index(["arm", "segment"])
    assert list(seg.loc[SLOW].index) == ["walk", "jump"]  # motion order, not alphabetical
    # At iteration 45 SLOW has not mastered bin 3: its jump segment (bins 2, 3) is at
    # ((0.02 + 0.01 s) + (0.5 + 0.01 s)) / 2 for seeds 0, 1 -> mean 0.265.
    assert seg.loc[(SLOW, "jump"), "final_failure"] == pytest.approx(0.265)
    assert seg.loc[(SLOW, "jump"), "bins_not_mastered"] == 1 and seg.loc[(SLOW, "walk"), "bins_not_mastered"] == 0
    assert seg.loc[(SLOW, "jump"), "difficulty"] == 0.8 and seg.loc[(SLOW, "jump"), "num_bins"] == 2
    assert seg.loc[(UNIFORM, "walk"), "final_failure"] == pytest.approx(0.03)
    assert seg.loc[(UNIFORM, "walk"), "n_seeds"] == 3
    assert "## Segments" in (report / "report.md").read_text()


def test_report_text_partial_sweep(report):
    md = (report / "report.md").read_text()
    assert "failed — failed: RuntimeError: simulated crash" in md
    assert "missing — job folder missing" in md
    assert "Still running" in md and "up to iteration 45" in md
    # The running seed stopped at 45 of 60 iterations: the budgets differ and the report says so.
    assert "Warning: unequal budgets" in md and "iteration 45, the last evaluation every run has" in md
    assert f"Lowest final overall failure (iteration 45, the last evaluation every run has): **`{FAST}`**" in md
    assert "no difference shown at the 0.05 level" in md
    assert "This arm was picked after seeing the data: the 2 tests against it below are post hoc" in md
    assert "(post hoc, uncorrected; smallest attainable 0.2)" in md  # 3 v 2 seeds: 10 splits
    assert "at 0.9: ×2 (no interval), p = 0.2 (uncorrected; smallest attainable 0.2)" in md
    assert "0.86–0.97: ≤ ×0.667 (the arm's median not reached: a bound)" in md
    assert "1 upper bound" in md and "1 bins" not in md
    assert set(pd.read_csv(report / "sampling.csv")["arm"]) == {FAST, SLOW}
    sens = pd.read_csv(report / "sensitivity.csv")
    assert set(sens["arm"]) == {FAST, SLOW} and set(sens["value"]) == {0.5, 0.9}


def test_curves_carry_seeds_and_label_the_point(report):
    curves = pd.read_csv(report / "curves.csv")
    c = curves[(curves["arm"] == FAST) & (curves["metric"] == "mean_episode_length")].set_index("iteration")
    # Seeds 0 and 1 have 10 + iteration + seed: the mean (2 seeds) is 10.5 + iteration, range [10, 11] + it.
    assert c.loc[30, "point"] == 40.5 and c.loc[30, "ci_low"] == 40.0 and c.loc[30, "ci_high"] == 41.0
    assert c.loc[30, "point_label"] == "mean" and c.loc[30, "ci_method"] == "range"
    u = curves[(curves["arm"] == UNIFORM) & (curves["metric"] == "eval_failure_rate")].set_index("iteration")
    assert u.loc[45, "n_seeds"] == 3 and u.loc[50, "n_seeds"] == 2  # the running seed stops at 45


def test_report_is_reproducible(report, sweep, tmp_path):
    again = build_report([sweep], out=tmp_path / "again", opts=ReportOptions(n_resamples=RESAMPLES))
    for name in ("speedup.csv", "summary.csv", "final_bin_failure.csv", "mastery.csv"):
        pd.testing.assert_frame_equal(pd.read_csv(report / name), pd.read_csv(again / name))


def test_exact_ties_name_no_winner(tmp_path):
    for arm in ("a", "b"):
        for seed in (0, 1):
            write_run(tmp_path / "t" / f"sampler.x={arm}" / f"seed={seed}", sampler="adaptive", seed=seed,
                      overrides=[f"sampler.x={arm}"], mastery=[10.0, 20.0, 30.0, 40.0])
    md = (build_report([tmp_path / "t"], opts=ReportOptions(n_resamples=20)) / "report.md").read_text()
    assert "tie at" in md and "no winner" in md and "Lowest final overall failure" not in md


def test_old_eval_tables_and_truncated_bins_are_flagged(tmp_path):
    write_run(tmp_path / "old" / "sampler=uniform" / "seed=0", sampler="uniform", seed=0,
              overrides=["sampler=uniform"], mastery=[10.0, 20.0, 30.0, 40.0], old_eval=True)
    md = (build_report([tmp_path / "old"], opts=ReportOptions(n_resamples=20)) / "report.md").read_text()
    assert "predates per-visit accounting" in md
    # A horizon-truncated bin with no episode tracked through it never counts as mastered.
    write_run(tmp_path / "trunc" / "sampler=uniform" / "seed=0", sampler="uniform", seed=0,
              overrides=["sampler=uniform"], mastery=[10.0, 20.0, 30.0, 40.0], truncated_bins=(3,))
    out = build_report([tmp_path / "trunc"], opts=ReportOptions(n_resamples=20))
    m = pd.read_csv(out / "mastery.csv").set_index("bin")
    assert m.loc[3, "n_mastered"] == 0 and m.loc[3, "horizon_truncated"] and m.loc[2, "n_mastered"] == 1
    md = (out / "report.md").read_text()
    assert "Horizon-truncated bin 3" in md and "| 3† |" in md


def test_committed_study_layout(tmp_path, capsys):
    """docs/results/<study>/runs/<arm>/seed=<s>/ holds the compact per-run tables; the report runs on it."""
    runs = tmp_path / "study" / "runs"
    for seed in (0, 1):
        write_run(runs / "sampler=uniform" / f"seed={seed}", sampler="uniform", seed=seed,
                  overrides=["sampler=uniform"], mastery=[10.0, 20.0, 30.0, 40.0])
        write_run(runs / "sampler=adaptive" / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler=adaptive"], mastery=[5.0, 10.0, 15.0, 20.0])
    assert main([str(runs), "--out", str(tmp_path / "study"), "--resamples", "20"]) == 0
    speed = pd.read_csv(tmp_path / "study" / "speedup.csv")
    assert set(speed["arm"]) == {"sampler=adaptive"} and set(speed["baseline"]) == {"sampler=uniform"}
    assert main([str(runs), "--mastery-persist", "0"]) == 2
    assert "--mastery-persist" in capsys.readouterr().err


def test_equal_env_steps_comparison_only_when_steps_per_iteration_differ():
    from analysis.tables import per_run_metrics

    def overall(run, arm, steps_per_it, failure):
        its = np.arange(0, 41, 10)
        return pd.DataFrame({"run_dir": run, "arm": arm, "seed": 0, "iteration": its, "env_steps": its * steps_per_it,
                             "wall_time_s": its * 1.0, "failure_rate": failure(its)})

    same = pd.concat([overall("a", "a", 100, lambda i: 1 - i / 40), overall("b", "b", 100, lambda i: 1 - i / 80)])
    assert "final_failure_equal_env_steps" not in per_run_metrics(None, same, None, pd.DataFrame(), pd.DataFrame())
    # Arm b collects twice the env steps per iteration: at equal env steps (4000) it has done 20 iterations.
    both = pd.concat([overall("a", "a", 100, lambda i: 1 - i / 40), overall("b", "b", 200, lambda i: 1 - i / 80)])
    m = per_run_metrics(None, both, None, pd.DataFrame(), pd.DataFrame())
    assert m["final_failure"].set_index("arm")["value"].to_dict() == {"a": 0.0, "b": 0.5}
    assert m["final_failure_equal_env_steps"].set_index("arm")["value"].to_dict() == {"a": 0.0, "b": 0.75}


def test_tracking_errors_are_weighted_by_the_steps_measured():
    # Bin 2 was never reached (0 steps, errors NaN): it must not dilute or poison the mean.
    e = pd.DataFrame({"run_dir": "r", "arm": "a", "seed": 0, "iteration": [5, 5, 5, 10, 10, 10],
                      "env_steps": [50, 50, 50, 100, 100, 100], "bin": [0, 1, 2] * 2,
                      "eval_steps": [1, 3, 0, 2, 2, 0], "mpkpe_rel_mm": [10.0, 20.0, np.nan, 30.0, 50.0, np.nan],
                      "joint_vel_err_radps": [1.0, 2.0, np.nan, 1.0, 1.0, np.nan]})
    t = tracking_errors(e).set_index("iteration")
    assert t.loc[5, "mpkpe_rel_mm"] == pytest.approx(17.5) and t.loc[5, "joint_vel_err_radps"] == pytest.approx(1.75)
    assert t.loc[10, "mpkpe_rel_mm"] == pytest.approx(40.0) and t.loc[10, "env_steps"] == 100
    assert "mpkpe_mm" not in t  # only the error columns the table has
    assert tracking_errors(e.drop(columns="eval_steps")).empty  # tables without step counts: no errors


def test_tracking_quality_names_the_planted_winner_of_each_error(tmp_path):
    # Arm `a` tracks closer (root-relative MPKPE 40 vs 45 mm), arm `b` has the smaller joint-velocity
    # error (0.9 vs 1.0 rad/s), 5 seeds each: each error's winner is named with a significant difference.
    for arm, mpkpe, jvel in (("a", 40.0, 1.0), ("b", 45.0, 0.9)):
        for seed in range(5):
            run = write_run(tmp_path / f"env={arm}" / f"seed={seed}", sampler="adaptive", seed=seed,
                            overrides=[f"env={arm}"], mastery=[10, 20, 30, 40])
            e = pd.read_parquet(run / "eval.parquet")
            e["eval_steps"] = 100
            e["mpkpe_rel_mm"] = mpkpe + 0.1 * seed
            e["joint_vel_err_radps"] = jvel + 0.01 * seed
            e.to_parquet(run / "eval.parquet", index=False)
    out = build_report([tmp_path], tmp_path / "report", ReportOptions(n_resamples=RESAMPLES))
    md = (out / "report.md").read_text()
    section = md.split("## Tracking quality")[1].split("\n## ")[0]
    assert "| env=a | 40.2 " in section and "| env=b | 45.2 " in section
    assert "Lowest root-relative MPKPE (mm) (iteration 60, the last evaluation every run has): **`env=a`**" in section
    assert "Lowest joint velocity error (rad/s) (iteration 60, the last evaluation every run has): **`env=b`**" in section
    assert section.count("a difference at the 0.05 level") == 2
    comp = pd.read_csv(out / "comparisons.csv").set_index("metric")
    assert comp.loc["final_mpkpe_rel_mm", "best"] == "env=a" and comp.loc["final_joint_vel_err_radps", "best"] == "env=b"
    assert set(pd.read_csv(out / "tracking_errors.csv")["iteration"]) == set(range(0, 61, 5))
    curve = pd.read_csv(out / "curves.csv").query("metric == 'eval_mpkpe_rel_mm'").groupby("arm")["point"].max()
    assert curve.to_dict() == pytest.approx({"env=a": 40.2, "env=b": 45.2}) and (out / "curve_eval_mpkpe_rel_mm.png").is_file()


def test_plural():
    assert plural(1, "bin") == "1 bin" and plural(0, "bin") == "0 bins" and plural(2, "seed") == "2 seeds"


# --------------------------------------------------------------------------------------------- single runs, errors
def _single(root: Path, name: str, sampler: str, seed: int, overrides: list[str], **kw) -> Path:
    return write_run(root / name / f"2026-01-0{seed + 1}_00-00-00", sampler=sampler, seed=seed,
                     overrides=overrides, mastery=[10, 20, 30, 40], **kw)


def test_single_run_arms(tmp_path):
    a = _single(tmp_path, "a", "uniform", 0, ["sampler=uniform"])
    b = _single(tmp_path, "b", "adaptive", 1, ["sampler=adaptive", "sampler.gamma=0.5"], sampler_cfg={"gamma": 0.5})
    c = _single(tmp_path, "c", "adaptive", 2, ["sampler=adaptive", "sampler.gamma=0.7"], sampler_cfg={"gamma": 0.7})
    runs = load_runs([a, b, c]).set_index("run_dir")
    assert runs.loc[str(a), "arm"] == "uniform"
    assert runs.loc[str(b), "arm"] == "adaptive,sampler.gamma=0.5"
    assert runs.loc[str(c), "arm"] == "adaptive,sampler.gamma=0.7"
    assert load_runs(tmp_path / "a")["arm"].tolist() == ["uniform"]


def test_single_run_report_and_cli(tmp_path, capsys):
    run = _single(tmp_path, "solo", "adaptive", 0, ["sampler=adaptive"])
    assert main([str(run), "--resamples", "50"]) == 0
    out = run / "report"
    assert (out / "report.md").is_file() and (out / "mastery.png").stat().st_size > 0
    assert "no arm has sampler.name == uniform" in (out / "report.md").read_text()
    assert main([str(run), "--baseline", "nope", "--out", str(tmp_path / "r")]) == 2
    assert "--baseline 'nope'" in capsys.readouterr().err
    assert main([str(tmp_path / "absent")]) == 2
    assert "no such file or folder" in capsys.readouterr().err


def test_unreadable_table_is_excluded_not_fatal(tmp_path):
    good = _single(tmp_path, "good", "uniform", 0, ["sampler=uniform"])
    bad = _single(tmp_path, "bad", "uniform", 1, ["sampler=uniform"])
    (bad / "eval.parquet").write_bytes(b"not parquet")
    runs = load_runs(tmp_path).set_index("run_dir")
    assert runs.loc[str(good), "included"]
    assert not runs.loc[str(bad), "included"] and "eval.parquet unreadable" in runs.loc[str(bad), "problem"]
    pd.read_parquet(good / "eval.parquet").drop(columns=["failure_rate"]).to_parquet(bad / "eval.parquet")
    assert "lacks columns ['failure_rate']" in load_runs(bad)["problem"].iloc[0]
    (tmp_path / "empty").mkdir()
    with pytest.raises(AnalysisError, match="no run folders"):
        load_runs(tmp_path / "empty")


# --------------------------------------------------------------------------------------------- index
def test_index_rebuild(tmp_path):
    sweep = make_sweep(tmp_path)
    path = write_index(sweep)
    index = pd.read_csv(path)
    assert len(index) == 8  # one row per job folder: the missing job has none
    assert set(index.loc[index["status"] == "failed", "job"]) == {f"{FAST}/seed=2"}
    assert set(index["git_commit"]) == {"0123abc"}
    done = index.set_index("job").loc[f"{UNIFORM}/seed=0"]
    assert done["final_eval_failure_rate"] == pytest.approx(0.02) and done["iterations"] == 61
    assert math.isnan(index.set_index("job").loc[f"{UNIFORM}/seed=2", "final_eval_failure_rate"])
    pd.testing.assert_frame_equal(build_index(sweep), index, check_dtype=False)

    # A job folder that disappears after it was indexed is reported as missing.
    job = sweep / UNIFORM / "seed=1"
    for f in sorted(job.rglob("*"), reverse=True):
        f.rmdir() if f.is_dir() else f.unlink()
    job.rmdir()
    runs = load_runs(sweep).set_index(["arm", "seed"])
    assert runs.loc[(UNIFORM, 1), "status"] == "missing"


def test_index_concurrent_writers(tmp_path):
    sweep = make_sweep(tmp_path)
    errors = []

    def rebuild():
        try:
            for _ in range(3):
                write_index(sweep)
        except Exception as e:  # surfaced below: a thread's exception would otherwise be lost
            errors.append(e)

    threads = [threading.Thread(target=rebuild) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    assert len(pd.read_csv(sweep / "index.csv")) == 8
    assert not [p for p in sweep.iterdir() if p.name.endswith(".tmp")]


def test_index_of_empty_sweep(tmp_path):
    assert len(build_index(tmp_path)) == 0
    assert pd.read_csv(write_index(tmp_path)).columns[0] == "job"


def test_an_index_the_disk_refuses_is_one_error_line(tmp_path, capsys):
    """A write that fails (here index.csv is a folder) ends bmimic-index in one line, exit 2, not a traceback."""
    from analysis.index import main as index_main

    sweep = make_sweep(tmp_path)
    (sweep / "index.csv").mkdir()
    assert index_main([str(sweep)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "index.csv" in err and "cannot write" in err and len(err.splitlines()) == 1
    assert (sweep / "index.csv").is_dir() and not [p for p in sweep.iterdir() if p.name.endswith(".tmp")]


def test_a_users_own_index_csv_is_never_replaced(tmp_path, capsys):
    """Issue 77's second round: an index.csv bmimic did not write was taken for a sweep's and replaced by
    an empty index (exit 0). Now refused in one line, the file byte-identical; an index it wrote, of any
    version, is still rebuilt."""
    from analysis.index import main as index_main

    (tmp_path / "index.csv").write_text("name,phone\nalice,1\n")
    (tmp_path / "notes.txt").write_text("x")
    assert index_main([str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "did not write" in err and len(err.splitlines()) == 1
    assert (tmp_path / "index.csv").read_text() == "name,phone\nalice,1\n"
    sweep = make_sweep(tmp_path / "sweep")
    (sweep / "index.csv").write_text("job,arm,seed,status\nold,x,0,done\n")  # an older index of bmimic's
    assert len(pd.read_csv(write_index(sweep))) == 8


def test_short_arm_labels_keep_only_what_differs():
    from analysis.load import short_arm_labels

    labels, shared = short_arm_labels(["a=1,b=2,sampler=uniform", "a=1,b=2,sampler=adaptive", None])
    assert labels == {"a=1,b=2,sampler=uniform": "sampler=uniform", "a=1,b=2,sampler=adaptive": "sampler=adaptive"}
    assert shared == ["a=1", "b=2"]
    labels, _ = short_arm_labels(["k=1,sampler=adaptive", "sampler=adaptive"])
    assert labels == {"k=1,sampler=adaptive": "k=1", "sampler=adaptive": "base"}
    assert short_arm_labels(["only"]) == ({"only": "only"}, [])




def test_the_report_has_a_per_clip_table_for_a_library(tmp_path):
    from analysis.clip_tables import clip_failure
    from tests.analysis.synthetic_runs import write_run

    sweep = tmp_path / "lib"
    clips = ["walk", "walk", "jump", "jump"]
    for seed in (0, 1):
        write_run(sweep / "sampler=uniform" / f"seed={seed}", sampler="uniform", seed=seed,
                  overrides=["sampler=uniform"], mastery=[10.0, 20.0, 30.0, 40.0], clips=clips)
        # the adaptive arm never masters bin 3 and its sampler never started from clip "jump"
        write_run(sweep / "sampler=adaptive" / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler=adaptive"], mastery=[5.0, 10.0, 15.0, None], clips=clips,
                  sampler_episodes=[30, 20, 0, 0])
    out = build_report([sweep], tmp_path / "report")
    table = pd.read_csv(out / "clip_failure.csv").set_index(["arm", "clip"])
    # final failure of a clip: failed / started episodes of its bins (episodes stay in their start bin
    # here; seed s adds 0.01 s to every rate)
    assert table.loc[("sampler=adaptive", "jump"), "final_failure"] == pytest.approx((0.02 + 0.5) / 2 + 0.005)
    assert table.loc[("sampler=uniform", "walk"), "final_failure"] == pytest.approx(0.02 + 0.005)
    assert table.loc[("sampler=uniform", "walk"), "seeds"] == "0;1"  # and each seed's failure, in that order
    assert [float(v) for v in table.loc[("sampler=uniform", "walk"), "per_seed"].split(";")] == pytest.approx([0.02, 0.03])
    assert table.loc[("sampler=adaptive", "jump"), "bins_not_mastered"] == 1
    assert table.loc[("sampler=uniform", "jump"), "bins_not_mastered"] == 0
    # the sampler's probability mass on the clip (uniform over 4 bins: half on each clip of 2)
    assert table.loc[("sampler=uniform", "jump"), "sampling_mass"] == pytest.approx(0.5)
    assert table.loc[("sampler=adaptive", "walk"), "sampling_mass"] == pytest.approx(1.0)
    text = (out / "report.md").read_text()
    assert "## Clips" in text and "No sampling probability at any logged iteration: `sampler=adaptive`: jump." in text
    # one clip: no per-clip section
    assert clip_failure(pd.DataFrame({"bin": [0], "clip": ["a"]}), pd.DataFrame(), pd.DataFrame(), pd.DataFrame(),
                        None).empty


def test_a_library_counts_clips_at_95_percent_by_the_mean_and_by_each_seed():
    """Planted final failures of 3 clips over seeds 0 and 1: (0.04, 0.05), (0.01, 0.02), (0.07, 0.02). The
    means 0.045, 0.015, 0.045 put all 3 clips at success >= 0.95; seed 0 alone has 2 there, seed 1 all 3
    (0.05 is on the line)."""
    from analysis.report_views import _clips_at_success

    per_seed = ["0.04;0.05", "0.01;0.02", "0.07;0.02"]
    tab = pd.DataFrame({"arm": "a", "clip": ["x", "y", "z"], "n_seeds": 2, "seeds": "0;1", "per_seed": per_seed,
                        "final_failure": [0.045, 0.015, 0.045], "iterations": "60;60", "end_iterations": "60;60",
                        "per_seed_at_end": per_seed})
    assert _clips_at_success(tab) == ["- `a`: 3 of 3 clips at final success >= 0.95 (failure <= 0.05) by the mean "
                                      "over seeds; per seed: 2 (seed 0), 3 (seed 1)."]
    four = tab.assign(n_seeds=4, seeds="0;1;2;3", per_seed=["0.04;0.05;0.01;0.01", "0.01;0.02;0.01;0.01",
                                                             "0.07;0.02;0.01;0.01"])
    assert "by the IQM over seeds; per seed: 2 (seed 0), 3 (seed 1), 3 (seed 2), 3 (seed 3)." in _clips_at_success(four)[0]
    one = tab.assign(n_seeds=1, seeds="0", per_seed=["0.04", "0.01", "0.07"], final_failure=[0.04, 0.01, 0.07],
                     iterations="60", end_iterations="60", per_seed_at_end=["0.04", "0.01", "0.07"])
    assert _clips_at_success(one) == ["- `a`: 2 of 3 clips at final success >= 0.95 (failure <= 0.05)."]
    # seed 1 went on to iteration 90, where clip z fails more (0.06): its own count there is 2
    past = tab.assign(iterations="60;60", end_iterations="60;90", per_seed_at_end=["0.04;0.05", "0.01;0.02", "0.07;0.06"])
    assert _clips_at_success(past)[0].endswith(
        "per seed: 2 (seed 0), 3 (seed 1); at each seed's own last evaluation: 2 (seed 0, iteration 60), "
        "2 (seed 1, iteration 90).")


# --------------------------------------------------------------------------------------------- budgets
def _set_budget(run_dir: Path, max_iterations: int, resolved: int | None = None) -> None:
    """Give a planted run the budget its .hydra/config.yaml records (and, as after a resume that raised
    it, the one its resolved_config.json records)."""
    import json

    import yaml

    path = Path(run_dir) / ".hydra" / "config.yaml"
    cfg = yaml.safe_load(path.read_text())
    path.write_text(yaml.safe_dump({**cfg, "max_iterations": max_iterations, "num_envs": 8}))
    if resolved is not None:
        (Path(run_dir) / "resolved_config.json").write_text(json.dumps({**cfg, "max_iterations": resolved,
                                                                         "num_envs": 8}))


def test_a_report_refuses_runs_of_different_budgets_unless_told(tmp_path):
    sweep = make_sweep(tmp_path)
    runs = sorted(p for p in sweep.rglob("seed=*") if (p / ".hydra").is_dir())
    for run in runs:
        _set_budget(run, 60)
    _set_budget(runs[0], 4)  # a smoke run in the study's folder
    with pytest.raises(AnalysisError, match=r"different budgets \(max_iterations: .*--allow-mixed"):
        load_runs(sweep)
    assert len(load_runs(sweep, allow_mixed=True)) > 0
    _set_budget(runs[0], 4, resolved=60)  # extended by a resume to the study's budget: one study again
    load_runs(sweep)
    index = build_index(sweep)
    assert set(index["max_iterations"].dropna()) == {60} and "num_envs" in index.columns


def _set_motion_key(run_dir: Path, key: str, value) -> None:
    import yaml

    path = Path(run_dir) / ".hydra" / "config.yaml"
    cfg = yaml.safe_load(path.read_text())
    motion = dict(cfg.get("motion") or {})
    if value is _ABSENT:
        motion.pop(key, None)
    else:
        motion[key] = value
    path.write_text(yaml.safe_dump({**cfg, "motion": motion}))


_ABSENT = object()


def test_a_motion_key_that_only_checks_the_file_is_not_a_different_motion(tmp_path):
    """motion.check_plausible (added after some committed runs) decides whether a file is refused, not what
    is trained on: absent, True and False compare as one motion; a key that picks the motion still differs."""
    sweep = make_sweep(tmp_path)
    runs = sorted(p for p in sweep.rglob("seed=*") if (p / ".hydra").is_dir())
    _set_motion_key(runs[0], "check_plausible", _ABSENT)
    _set_motion_key(runs[1], "check_plausible", False)
    for run in runs[2:]:
        _set_motion_key(run, "check_plausible", True)
    assert len(load_runs(sweep)) > 0
    _set_motion_key(runs[1], "clip", "walk1_subject1")
    with pytest.raises(AnalysisError, match=r"different motions \(motion.clip: "):
        load_runs(sweep)


def test_the_baseline_is_chosen_in_numbers_and_said_in_words():
    from types import SimpleNamespace

    from analysis.report_views import _baseline_note
    from analysis.tables import choose_baseline

    runs = pd.DataFrame({"arm": ["u2", "u1", "a", "a"], "sampler": ["uniform", "uniform", "adaptive", "adaptive"],
                         "included": [True, True, True, True]})
    assert choose_baseline(runs, None) == ("u1", ["u1", "u2"])
    assert choose_baseline(runs, "a") == ("a", [])
    assert choose_baseline(runs[runs["sampler"] != "uniform"], None) == (None, [])
    with pytest.raises(AnalysisError, match="--baseline 'x'"):
        choose_baseline(runs, "x")
    say = lambda baseline, uniform: _baseline_note(SimpleNamespace(baseline=baseline, uniform_arms=uniform))  # noqa: E731
    assert say("u1", ["u1", "u2"]) == ("baseline `u1` (its sampler is uniform); other uniform arms: `u2` "
                                       "(pick one with --baseline)")
    assert say("u1", ["u1"]) == "baseline `u1` (its sampler is uniform)"
    assert say("a", []) == "baseline `a` (given)"
    assert say(None, []).endswith("speedups are skipped")


def test_the_per_bin_mastery_table_prints_up_to_its_limit_and_points_to_the_csv_beyond():
    from analysis.report_views import MASTERY_TABLE_MAX_BINS, per_bin_mastery
    from bmimic.runs.schema import BIN, HORIZON_TRUNCATED

    def mastery(n_bins: int) -> pd.DataFrame:
        return pd.DataFrame({BIN: range(n_bins), "arm": "a", "mastery_iteration": 100.0, "n_mastered": 1,
                             "n_seeds": 1, "segment": "s", HORIZON_TRUNCATED: False})

    small = "\n".join(per_bin_mastery(mastery(3)))
    assert small.count("(1/1)") == 3 and "mastery.csv" not in small
    at_limit = "\n".join(per_bin_mastery(mastery(MASTERY_TABLE_MAX_BINS))).splitlines()
    assert sum(line.startswith("| ") for line in at_limit) == MASTERY_TABLE_MAX_BINS + 1  # header + a row per bin
    big = "\n".join(per_bin_mastery(mastery(MASTERY_TABLE_MAX_BINS + 1)))
    assert "(1/1)" not in big and f"{MASTERY_TABLE_MAX_BINS + 1} bins" in big and "mastery.csv" in big


def test_the_hardest_clips_curves_follow_the_planted_failures_hardest_first():
    from analysis.clip_tables import hardest_clip_curves
    from analysis.curve_plots import plot_hardest_clips
    from bmimic.runs.schema import BIN, ITERATION

    # 3 clips of 2 bins; per started episode at iterations 10 / 20: clip a 0.5 / 0.25, b 0.1 / 0.0, c 0.9 / 0.6
    planted = {"a": (0.5, 0.25), "b": (0.1, 0.0), "c": (0.9, 0.6)}
    rows = [{"run_dir": "r0", "arm": "x", "seed": 0, ITERATION: it, BIN: 2 * k + j, "clip": clip,
             "start_failures": 20 * planted[clip][i], "start_episodes": 20}
            for k, clip in enumerate(planted) for j in range(2) for i, it in enumerate((10, 20))]
    eval_df = pd.DataFrame(rows)
    clip_tab = pd.DataFrame({"arm": "x", "clip": list(planted), "final_failure": [v[1] for v in planted.values()]})
    curves = hardest_clip_curves(eval_df, clip_tab, k=2)
    assert list(curves["clip"].cat.categories) == ["c", "a"]  # hardest first; b is left out
    got = curves.set_index(["clip", ITERATION])["failure_rate"]
    assert got[("c", 10)] == pytest.approx(0.9) and got[("c", 20)] == pytest.approx(0.6)
    assert got[("a", 10)] == pytest.approx(0.5) and got[("a", 20)] == pytest.approx(0.25)
    fig = plot_hardest_clips(curves)
    assert [ax.get_title() for ax in fig.axes if ax.get_visible()] == ["c", "a"]
    assert hardest_clip_curves(eval_df.assign(clip="a"), clip_tab).empty  # one clip: no figure


def test_a_smoke_scale_report_says_so_in_its_title_and_a_study_does_not(report, speedup_report):
    """The planted sweep's runs stop before iteration 100 (a pipeline check); the speedup sweep's run to 150."""
    from analysis.report_views import REPORT_TITLE, SMOKE_ITERATIONS

    smoke = (report / "report.md").read_text().splitlines()
    assert smoke[0] == f"{REPORT_TITLE} (smoke scale: not a result)"
    assert smoke[2].startswith("**Smoke scale.**") and str(SMOKE_ITERATIONS) in smoke[2]
    study = (speedup_report / "report.md").read_text()
    assert study.splitlines()[0] == REPORT_TITLE and "Smoke scale" not in study
