"""Planted answers for what a reader of the report relies on (issue 31): one failure unit beside the
overall failure, speedups as a curve over success thresholds with censoring, iso-failure ratios,
corrected tests over many arms, the effective support of the sampling distribution and degenerate
signals, smoothness "not recorded" for old tables, and wall time only within one machine kind."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from analysis.adaptation import at_evaluations, sampling_support, signal_summary
from analysis.comparisons import baseline_comparisons
from analysis.curve_text import flat_span
from analysis.report import build_report
from analysis.speedup_curve import THRESHOLDS, first_crossing, iso_failure, speedup_curve
from analysis.stats import bootstrap_coverage, holm, smallest_pvalue
from analysis.tables import ReportOptions
from tests.analysis.synthetic_runs import write_run

OPTS = ReportOptions(n_resamples=200, n_permutations=999)


# ------------------------------------------------------------------------------------------- statistics
def test_holm_known_answers():
    np.testing.assert_allclose(holm([0.01, 0.04, 0.03]), [0.03, 0.06, 0.06])
    np.testing.assert_allclose(holm([0.01, 0.02, 0.03, 0.04]), [0.04, 0.06, 0.06, 0.06])
    np.testing.assert_allclose(holm([0.5, 0.9]), [1.0, 1.0])  # capped at 1
    out = holm([0.02, np.nan, 0.01])  # NaN is not a test of the family
    assert math.isnan(out[1]) and out[0] == pytest.approx(0.02) and out[2] == pytest.approx(0.02)
    assert holm([]).shape == (0,)


def test_smallest_attainable_p():
    assert smallest_pvalue(4, 4) == pytest.approx(2 / 70)  # 0.029: the peer study's floor
    assert smallest_pvalue(5, 5) == pytest.approx(2 / 252)
    assert smallest_pvalue(2, 2) == pytest.approx(1 / 3)
    assert smallest_pvalue(1, 1) == 1.0
    assert smallest_pvalue(10, 10) == pytest.approx(2 / 184_756)  # the confirmatory test's splits, enumerated
    assert smallest_pvalue(11, 11, n_resamples=999) == pytest.approx(2 / 1000)  # too many splits: random ones
    assert math.isnan(smallest_pvalue(0, 3))


def test_bca_undercovers_at_five_seeds():
    # A nominal 95% interval of the IQM over 5 normal seeds covers about 89% (review: ~0.90).
    cover = bootstrap_coverage(5, n_draws=300, n_resamples=500)
    assert 0.8 < cover < 0.94


def test_baseline_comparisons_test_and_report_the_difference_of_means_with_holm():
    # "skew": an outlier seed moves the mean, not the IQM: the printed difference is the tested one (means)
    vals = {"base": [0.30, 0.31, 0.32, 0.33], "better": [0.20, 0.21, 0.22, 0.23], "skew": [0.30, 0.31, 0.32, 0.73]}
    df = pd.DataFrame([(f"{a}/{i}", a, i, v) for a, vs in vals.items() for i, v in enumerate(vs)],
                      columns=["run_dir", "arm", "seed", "value"])
    comp = baseline_comparisons({"final_failure": df}, "final_failure", "base", OPTS).set_index("arm")
    assert comp.loc["skew", "difference"] == pytest.approx(0.10)  # means 0.415 - 0.315
    assert comp.loc["skew", "point"] == pytest.approx(0.315)  # IQM: the outlier is trimmed
    assert comp.loc["better", "p_value"] == pytest.approx(2 / 70) and comp.loc["better", "smallest_p"] == pytest.approx(2 / 70)
    # Holm over the 2 tests: the smaller p doubled
    assert comp.loc["better", "p_holm"] == pytest.approx(min(1.0, 2 * 2 / 70))
    assert comp.loc["better", "claim"] and not comp.loc["better", "claim_holm"]


# ------------------------------------------------------------------------------------------- speedup curve
def _overall(curves: dict[str, list], grid: dict[str, float], end: float = 1000.0) -> pd.DataFrame:
    """Per-run overall failure frames: ``curves[arm]`` = [failure(t) per seed], evaluated every
    ``grid[arm]`` iterations up to ``end``."""
    rows = []
    for arm, fs in curves.items():
        its = np.arange(grid[arm], end + 1e-9, grid[arm])
        for seed, f in enumerate(fs):
            for t in its:
                rows.append((f"{arm}/{seed}", arm, seed, float(t), 100.0 * t, t, float(f(t))))
    df = pd.DataFrame(rows, columns=["run_dir", "arm", "seed", "iteration", "env_steps", "wall_time_s", "failure_rate"])
    df["success_rate"] = 1.0 - df["failure_rate"]
    return df


def _runs(arms, n) -> pd.DataFrame:
    return pd.DataFrame([(f"{a}/{s}", a, True) for a in arms for s in range(n)], columns=["run_dir", "arm", "included"])


def test_a_twofold_speedup_is_x2_at_every_threshold():
    # The arm's failure at t is the baseline's at 2t (each seed its own time scale), evaluated twice as
    # often: its time to every threshold is exactly half the baseline's.
    scales = [80.0, 100.0, 120.0, 90.0, 110.0]
    base = [lambda t, s=s: 0.6 * np.exp(-t / s) for s in scales]
    arm = [lambda t, s=s: 0.6 * np.exp(-2 * t / s) for s in scales]
    overall = _overall({"base": base, "fast": arm}, {"base": 10.0, "fast": 5.0})
    curve = speedup_curve(overall, "base", _runs(["base", "fast"], 5), OPTS)
    its = curve[curve["measure"] == "iteration"].set_index("threshold")
    assert list(its.index) == list(THRESHOLDS) and (its["status"] == "estimate").all()
    np.testing.assert_allclose(its["ratio"], 2.0)
    assert (its["ci_low"] <= 2.0).all() and (its["ci_high"] >= 2.0).all()
    assert (its["p_value"] < 0.05).all() and np.allclose(its["smallest_p"], 2 / 252)


def test_a_speedup_that_grows_with_the_threshold():
    # baseline failure 0.6 exp(-t/T), arm 0.6 exp(-(t/T)^1.5): to failure L the ratio is ln(0.6/L)^(1/3).
    base = [lambda t: 0.6 * np.exp(-t / 100.0)] * 5
    arm = [lambda t: 0.6 * np.exp(-((t / 100.0) ** 1.5))] * 5
    overall = _overall({"base": base, "grow": arm}, {"base": 1.0, "grow": 1.0})
    curve = speedup_curve(overall, "base", _runs(["base", "grow"], 5), OPTS, measures=("iteration",))
    c = curve.set_index("threshold")
    assert (c["status"] == "estimate").all()
    expected = np.log(0.6 / (1.0 - c.index.to_numpy())) ** (1 / 3)
    np.testing.assert_allclose(c["ratio"], expected, rtol=0.02)  # within the 1-iteration grid
    assert np.all(np.diff(c["ratio"].to_numpy()) > -1e-9) and c["ratio"].iloc[-1] > 1.5 * c["ratio"].iloc[0]


def test_censored_arms_on_the_curve():
    # "stuck" never gets below failure 0.15: an upper bound from success 0.86 on; the baseline never
    # gets below 0.05 while "good" does: lower bounds there; above both: not estimable.
    base = [lambda t: max(0.05, 0.6 * np.exp(-t / 100.0))] * 3
    stuck = [lambda t: max(0.15, 0.6 * np.exp(-t / 100.0))] * 3
    good = [lambda t: max(0.02, 0.6 * np.exp(-t / 100.0))] * 3
    overall = _overall({"base": base, "stuck": stuck, "good": good}, {"base": 10.0, "stuck": 10.0, "good": 10.0})
    curve = speedup_curve(overall, "base", _runs(["base", "stuck", "good"], 3), OPTS, measures=("iteration",))
    s = curve[curve["arm"] == "stuck"].set_index("threshold")
    assert (s.loc[[0.5, 0.7, 0.85], "status"] == "estimate").all()
    assert (s.loc[[0.86, 0.9, 0.95], "status"] == "upper_bound").all()
    assert s.loc[0.9, "ratio"] == pytest.approx(s.loc[0.9, "ratio"]) and s.loc[0.9, "ratio"] < 1
    assert (s.loc[[0.96, 0.99], "status"] == "not_estimable").all()
    g = curve[curve["arm"] == "good"].set_index("threshold")
    assert (g.loc[[0.96, 0.98], "status"] == "lower_bound").all() and g.loc[0.99, "status"] == "not_estimable"
    assert math.isnan(s.loc[0.9, "ci_low"])  # 3 seeds: no interval


def test_first_crossing_interpolates_and_bounds():
    t = np.array([10.0, 20.0, 30.0])
    assert first_crossing(t, np.array([0.5, 0.3, 0.1]), 0.4) == (15.0, "estimate")
    assert first_crossing(t, np.array([0.5, 0.3, 0.1]), 0.6) == (10.0, "lower_bound")
    assert first_crossing(t, np.array([0.5, 0.3, 0.2]), 0.1)[1] == "upper_bound"
    assert first_crossing(np.array([0.0, 10.0]), np.array([0.1, 0.05]), 0.2)[1] == "not_estimable"


def test_iso_failure_of_a_twofold_faster_arm():
    base = [lambda t: 1.0 - t / 1000.0] * 3  # linear: the arm reaches the baseline's level in half the time
    fast = [lambda t: max(0.0, 1.0 - t / 500.0)] * 3
    iso = iso_failure(_overall({"base": base, "fast": fast}, {"base": 100.0, "fast": 100.0}), "base",
                      measures=("iteration",))
    est = iso[iso["status"] == "estimate"]
    assert list(est["baseline_time"]) == [300.0 + 100 * i for i in range(8)] and np.allclose(est["ratio"], 2.0)
    # at 100 and 200 the arm was at the baseline's level by its first evaluation (100): only a bound
    early = iso.set_index("baseline_time").loc[[100.0, 200.0]]
    assert (early["status"] == "lower_bound").all() and list(early["ratio"]) == [1.0, 2.0]


# ------------------------------------------------------------------------------------------- support
def test_effective_support_of_known_distributions():
    p = [0.5, 0.25, 0.25, 0.0]  # 1 / sum p^2 = 1 / 0.375; S = 4; clips {0, 1} and {2, 3}: masses 0.75, 0.25
    df = pd.DataFrame({"run_dir": "r", "arm": "a", "seed": 0, "iteration": [0] * 4 + [1] * 4, "bin": [0, 1, 2, 3] * 2,
                       "probability": p + [0.25] * 4, "smoothed_failure_rate": [0.4, 0.1, 0.1, 0.0] + [1.0] * 4})
    s = sampling_support(df, pd.Series(["x", "x", "y", "y"], index=[0, 1, 2, 3])).set_index("iteration")
    assert s.loc[0, "effective_support"] == pytest.approx(1 / 0.375 / 4)
    assert s.loc[0, "max_p_rel"] == pytest.approx(2.0)
    assert s.loc[0, "clip_effective_support"] == pytest.approx(1 / (0.75**2 + 0.25**2) / 2)
    assert s.loc[0, "clip_max_p_rel"] == pytest.approx(1.5)
    assert s.loc[1, "effective_support"] == pytest.approx(1.0) and s.loc[1, "max_p_rel"] == pytest.approx(1.0)
    assert s.loc[0, "signal_flat"] == 0 and s.loc[1, "signal_flat"] == 1


def test_support_is_read_at_each_runs_own_evaluations_from_the_update_logged_before_them():
    # A logs its sampler at 0, 500, 1000 and evaluated at 500 and 1000; B logs at 0 and 500, evaluated at 400
    # and stopped there: B is read at 400 (from its log at 0) and never at A's 500 or 1000.
    support = pd.DataFrame({"run_dir": ["A", "A", "A", "B", "B"], "arm": ["a", "a", "a", "b", "b"],
                            "iteration": [0, 500, 1000, 0, 500], "effective_support": [1.0, 0.5, 0.25, 0.9, 0.8]})
    evaluations = pd.DataFrame({"run_dir": ["A", "A", "B"], "iteration": [500, 1000, 400]})
    got = at_evaluations(support, evaluations).set_index(["run_dir", "iteration"])["effective_support"]
    assert got.to_dict() == {("A", 500): 0.5, ("A", 1000): 0.25, ("B", 400): 0.9}


def test_a_flat_signal_is_degenerate_and_named(tmp_path):
    # "stuck" never masters a bin: its signal (the planted failure rate) is equal in every bin and its
    # distribution stays uniform; "moving" masters bins at different times.
    for seed in (0, 1):
        write_run(tmp_path / "s" / "sampler.x=stuck" / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler.x=stuck"], mastery=[None] * 4)
        write_run(tmp_path / "s" / "sampler.x=moving" / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler.x=moving"], mastery=[10.0, 20.0, 30.0, 40.0])
    out = build_report([tmp_path / "s"], opts=OPTS)
    signals = pd.read_csv(out / "sampler_signals.csv").set_index("arm")
    assert signals.loc["sampler.x=stuck", "degenerate"] and signals.loc["sampler.x=stuck", "constant"]
    assert not signals.loc["sampler.x=moving", "degenerate"]
    support = pd.read_csv(out / "sampling_support.csv")
    assert np.allclose(support.loc[support["arm"] == "sampler.x=stuck", "effective_support"], 1.0)
    md = (out / "report.md").read_text()
    assert "**Degenerate signals:** `sampler.x=stuck`" in md and "(sampling_support.png)" in md
    assert signal_summary(pd.read_csv(out / "sampling_support.csv")).set_index("arm").loc[
        "sampler.x=stuck", "flat_until"] == "never;never"


# ------------------------------------------------------------------------------------------- units
def _planted_library_eval(run: Path) -> None:
    """Clips walk (bins 0, 1) and jump (bins 2, 3), 10 starts per bin; an episode visits its start bin
    and the next bin of its clip. Every episode started in jump fails in bin 3: per visit, jump fails
    20 of its 30 visits; per started episode, 20 of 20. Walk never fails."""
    e = pd.read_parquet(run / "eval.parquet")
    per_bin = {"start_episodes": [10, 10, 10, 10], "visits": [10, 20, 10, 20], "failures": [0, 0, 0, 20],
               "start_failures": [0, 0, 10, 10]}
    for col, values in per_bin.items():
        e[col] = e["bin"].map(dict(enumerate(values)))
    e["failure_rate"] = e["failures"] / e["visits"]
    e.to_parquet(run / "eval.parquet", index=False)


def test_clip_and_segment_failure_are_per_started_episode(tmp_path):
    clips = ["walk", "walk", "jump", "jump"]
    for seed in (0, 1):
        run = write_run(tmp_path / "lib" / "sampler=uniform" / f"seed={seed}", sampler="uniform", seed=seed,
                        overrides=["sampler=uniform"], mastery=[10.0, 20.0, 30.0, 40.0], clips=clips)
        _planted_library_eval(run)
    out = build_report([tmp_path / "lib"], opts=OPTS)
    clip = pd.read_csv(out / "clip_failure.csv").set_index("clip")["final_failure"]
    assert clip["jump"] == pytest.approx(1.0) and clip["walk"] == 0.0  # per visit jump would be 20/30
    summary = pd.read_csv(out / "summary.csv").set_index("metric")
    overall = summary.loc["final_failure", "mean"]
    assert overall == pytest.approx(0.5)  # 20 of 40 started episodes: the start-weighted mean of the clips
    seg = pd.read_csv(out / "segment_failure.csv").set_index("segment")["final_failure"]  # walk = bins 0-1
    assert seg["walk"] == 0.0 and seg["jump"] == pytest.approx(1.0)
    bins = pd.read_csv(out / "final_bin_failure.csv").set_index("bin")["point"]
    assert bins[3] == pytest.approx(1.0) and bins[2] == 0.0  # per visit, where failures happened
    md = (out / "report.md").read_text()
    assert "final failure (failed / started episodes, by start clip)" in md
    assert "failed / started episodes" in md.split("## Definitions")[1] and "unweighted mean" not in md


# ------------------------------------------------------------------------------------------- smoothness, machines
def test_smoothness_where_recorded_and_not_recorded_elsewhere(tmp_path):
    for seed in range(2):
        new = write_run(tmp_path / "s" / "env=new" / f"seed={seed}", sampler="adaptive", seed=seed,
                        overrides=["env=new"], mastery=[10, 20, 30, 40])
        e = pd.read_parquet(new / "eval.parquet")
        e["eval_steps"], e["action_rate"], e["joint_acc_radps2"] = 100, 0.5 + 0.1 * seed, 20.0
        e["broken"] = np.where((e["bin"] == 1) & (e["iteration"] == 10), 1, 0)
        e.to_parquet(new / "eval.parquet", index=False)
        old = write_run(tmp_path / "s" / "env=old" / f"seed={seed}", sampler="adaptive", seed=seed,
                        overrides=["env=old"], mastery=[10, 20, 30, 40])
        e = pd.read_parquet(old / "eval.parquet")
        e["eval_steps"] = 100
        e.to_parquet(old / "eval.parquet", index=False)
    out = build_report([tmp_path / "s"], opts=OPTS)
    md = (out / "report.md").read_text()
    block = md.split("### Smoothness of the policy")[1].split("\n## ")[0]
    assert "| env=old | not recorded | not recorded | not recorded |" in block
    assert "| env=new | 0.55 (mean; range of 2 seeds: 0.5–0.6" in block and "| 20 (mean" in block
    summary = pd.read_csv(out / "summary.csv").set_index(["arm", "metric"])
    assert summary.loc[("env=new", "broken_episodes"), "per_seed"] == "1;1"
    assert ("env=old", "final_action_rate") not in summary.index


def test_wall_time_is_not_compared_across_machine_kinds(tmp_path):
    for seed in range(2):
        write_run(tmp_path / "s" / "sampler=uniform" / f"seed={seed}", sampler="uniform", seed=seed,
                  overrides=["sampler=uniform"], mastery=[10, 20, 30, 40], machine="NVIDIA H100")
        write_run(tmp_path / "s" / "sampler=adaptive" / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler=adaptive"], mastery=[5, 10, 15, 20], seconds_per_iteration=2.0,
                  machine="NVIDIA H200" if seed else "NVIDIA H100")
    out = build_report([tmp_path / "s"], opts=OPTS)
    assert set(pd.read_csv(out / "speedup.csv")["measure"]) == {"iteration", "env_steps"}
    md = (out / "report.md").read_text()
    assert "Wall time is not compared" in md and "`sampler=adaptive`: 1 on NVIDIA H100, 1 on NVIDIA H200" in md
    assert "wall time (s) to threshold" not in md.split("## Arms")[1].split("\n## ")[0]
    assert set(pd.read_csv(out / "budget.csv")["machine"]) == {"NVIDIA H100", "NVIDIA H200"}


def test_the_summary_names_the_threshold_of_every_speedup(tmp_path):
    for seed in range(2):
        write_run(tmp_path / "s" / "sampler=uniform" / f"seed={seed}", sampler="uniform", seed=seed,
                  overrides=["sampler=uniform"], mastery=[10, 20, 30, 40])
        write_run(tmp_path / "s" / "sampler=adaptive" / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler=adaptive"], mastery=[5, 10, 15, 20])
    out = build_report([tmp_path / "s"], opts=OPTS)
    curve = pd.read_csv(out / "speedup_curve.csv")
    assert set(curve["threshold"]) == set(THRESHOLDS) and set(curve["measure"]) == {"iteration", "env_steps"}
    assert (out / "speedup_curve.png").is_file() and (out / "iso_failure.png").is_file()
    summary = (out / "report.md").read_text().split("## Summary")[1].split("\n## ")[0]
    line = next(x for x in summary.splitlines() if x.startswith("- `sampler=adaptive` vs `sampler=uniform`"))
    # the range over thresholds, with the thresholds named, and the report's threshold with its value
    assert "at every threshold where both medians were reached (0.5–" in line and "at 0.9: ×2" in line
    assert "p (Holm, 1 test)" in summary


def test_curve_figures_mark_each_status():
    from matplotlib.collections import PathCollection

    from analysis.curve_plots import plot_iso_failure, plot_sampling_support, plot_speedup_curve

    curve = pd.DataFrame({"arm": "a", "baseline": "b", "measure": "iteration", "threshold": [0.5, 0.6, 0.7, 0.8],
                          "ratio": [1.0, 1.5, 2.0, np.nan], "ci_low": [0.9, 1.2, np.nan, np.nan],
                          "ci_high": [1.1, 1.8, np.nan, np.nan],
                          "status": ["estimate", "estimate", "lower_bound", "not_estimable"]})
    ax = plot_speedup_curve(curve).axes[0]
    offsets = [c.get_offsets() for c in ax.collections if isinstance(c, PathCollection)]
    assert sorted(len(o) for o in offsets) == [1, 2]  # 2 estimates, 1 lower bound, the n/e not drawn
    assert ax.get_ylim()[1] == pytest.approx(2.0 * 1.15)
    iso = curve.rename(columns={"threshold": "baseline_time"}).assign(status=["estimate"] * 3 + ["upper_bound"],
                                                                     ratio=[1.0, 1.5, 2.0, 0.5])
    ax = plot_iso_failure(iso).axes[0]
    assert sorted(len(c.get_offsets()) for c in ax.collections if isinstance(c, PathCollection)) == [1, 3]
    summary = pd.DataFrame({"arm": ["a", "a"], "iteration": [10, 20], "effective_support": [1.0, 0.5],
                            "max_p_rel": [1.0, 3.0], "clip_effective_support": np.nan, "clip_max_p_rel": np.nan})
    fig = plot_sampling_support(summary)
    assert [len(ax.lines) for ax in fig.axes] == [1, 1]
    np.testing.assert_allclose(fig.axes[1].lines[0].get_ydata(), [1.0, 3.0])


def test_clip_rollouts_are_summarised_per_arm(tmp_path):
    # phc's clip rollouts: at both evaluations every clip failed -> its signal ranks no clip above another
    clips = ["walk", "walk", "jump", "jump"]
    for seed in (0, 1):
        run = write_run(tmp_path / "lib" / "sampler=phc" / f"seed={seed}", sampler="phc", seed=seed,
                        overrides=["sampler=phc"], mastery=[10.0, 20.0, 30.0, 40.0], clips=clips)
        pd.DataFrame({"iteration": [5, 5, 10, 10], "env_steps": 0, "clip": [0, 1, 0, 1],
                      "clip_name": ["walk", "jump"] * 2, "failed": True}).to_parquet(run / "clip_eval.parquet")
    md = (build_report([tmp_path / "lib"], opts=OPTS) / "report.md").read_text()
    assert "`sampler=phc` clip rollouts (one from each clip's first frame per evaluation): every clip failed in 4 " \
           "and no clip in 0 of 4 evaluations" in md


def test_flat_span_says_which_seeds_stayed_flat_in_words():
    assert flat_span(["never", "500", "400", "never", "never"]) == (
        "until iteration 500, 400 in 2 seeds and throughout in 3 seeds")
    assert flat_span(["300"]) == "until iteration 300 in 1 seed"
    assert flat_span(["never", "never"]) == "throughout in 2 seeds"
