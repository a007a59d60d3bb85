"""Tests of analysis/: statistics known answers and invariants, metric definitions, the planted sweep
report (tests/synthetic_runs.py), partial sweeps, single runs and the sweep index."""

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
from analysis.index import build_index, write_index
from analysis.load import load_runs, load_table
from analysis.metrics import mastery_iterations, mastery_speedup, speedup, time_to_threshold
from analysis.report import build_report, main
from analysis.stats import bootstrap_ci, iqm
from analysis.tables import ReportOptions

try:  # tests/ as a package (rootdir on sys.path) or as a plain folder (pytest puts tests/ on sys.path)
    from tests.synthetic_runs import FAST, PLANTED, SLOW, UNIFORM, make_sweep, write_run
except ImportError:
    from synthetic_runs import FAST, PLANTED, SLOW, UNIFORM, make_sweep, write_run

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


def test_bootstrap_known_answers():
    # Two seeds {0, 1}: a resampled mean is 0, 0.5 or 1 with p = 1/4, 1/2, 1/4 -> 95 % CI [0, 1].
    assert bootstrap_ci([0.0, 1.0], statistic=lambda x: np.mean(x, axis=0)) == (0.5, 0.0, 1.0)
    assert bootstrap_ci([3.0, 3.0, 3.0]) == (3.0, 3.0, 3.0)
    assert bootstrap_ci([4.0]) == (4.0, 4.0, 4.0)


def test_bootstrap_reproducible_and_curve_matches_columns():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(6, 3))
    a = bootstrap_ci(x, n_resamples=500, seed=3)
    b = bootstrap_ci(x, n_resamples=500, seed=3)
    for u, v in zip(a, b, strict=True):
        np.testing.assert_array_equal(u, v)
    # Seeds are resampled jointly across the curve: column j matches the 1-D bootstrap of column j.
    for j in range(3):
        point, low, high = bootstrap_ci(x[:, j], n_resamples=500, seed=3)
        assert (point, low, high) == pytest.approx((a[0][j], a[1][j], a[2][j]))
    assert bootstrap_ci(x[:, 0], n_resamples=500, seed=4) != bootstrap_ci(x[:, 0], n_resamples=500, seed=3)


@given(st.lists(finite, min_size=1, max_size=12))
@settings(max_examples=40, deadline=None)
def test_bootstrap_interval_within_data(values):
    point, low, high = bootstrap_ci(values, n_resamples=100)
    assert min(values) - 1e-6 <= low <= high <= max(values) + 1e-6
    assert min(values) - 1e-6 <= point <= max(values) + 1e-6


def test_speedup_stratified():
    assert speedup([40.0, 40.0, 40.0], [20.0, 20.0]) == (2.0, 2.0, 2.0)
    ratio, low, high = speedup([1.0, 2.0, 3.0, 4.0], [1.0, 2.0, 3.0, 5.0], n_resamples=500)
    assert ratio == pytest.approx(1.0)
    assert low < 1.0 < high  # noisy arms: the interval contains 1


# --------------------------------------------------------------------------------------------- metrics
def _curve(rates, bin_=0, step=5):
    return pd.DataFrame({"iteration": np.arange(len(rates)) * step, "bin": bin_, "failure_rate": rates})


def test_mastery_is_first_drop_below_threshold():
    df = pd.concat([
        _curve([0.5, 0.05, 0.3, 0.02], bin_=0),  # mastered at 5 even though it rises again
        _curve([0.5, 0.1, 0.1, 0.1], bin_=1),  # exactly at the threshold: never (strictly below)
        _curve([0.0, 0.0, 0.0, 0.0], bin_=2),  # mastered at the first evaluation
    ])
    m = mastery_iterations(df, threshold=0.1).set_index("bin")
    assert m.loc[0, "mastery_iteration"] == 5.0
    assert math.isnan(m.loc[1, "mastery_iteration"]) and not m.loc[1, "mastered"]
    assert m.loc[1, "last_iteration"] == 15.0
    assert m.loc[2, "mastery_iteration"] == 0.0


def test_mastery_speedup_censoring():
    mastery = pd.DataFrame({
        "arm": ["base"] * 4 + ["arm"] * 4,
        "bin": [0, 1, 2, 3] * 2,
        "mastery_iteration": [10, np.nan, 20, np.nan, 5, 10, np.nan, np.nan],
        "mastered": [True, False, True, False, True, True, False, False],
        "last_iteration": [40.0] * 4 + [50.0] * 4,
    })
    s = mastery_speedup(mastery, "base").set_index("bin")
    assert s.loc[0, "ratio"] == 2.0 and s.loc[0, "censored"] == ""
    assert s.loc[1, "ratio"] == 4.0 and s.loc[1, "censored"] == "baseline never"  # 40 / 10
    assert s.loc[2, "ratio"] == 0.4 and s.loc[2, "censored"] == "arm never"  # 20 / 50
    assert math.isnan(s.loc[3, "ratio"]) and s.loc[3, "censored"] == "both never"
    with pytest.raises(ValueError, match="baseline"):
        mastery_speedup(mastery, "nope")


def test_time_to_threshold_inclusive_and_never():
    curve = pd.DataFrame({
        "run": ["a"] * 3 + ["b"] * 3,
        "iteration": [0, 10, 20] * 2,
        "env_steps": [0, 100, 200] * 2,
        "wall_time_s": [0.0, 1.0, 2.0] * 2,
        "success_rate": [0.5, 0.9, 0.95, 0.5, 0.6, 0.7],
    })
    t = time_to_threshold(curve, 0.9, by=["run"]).set_index("run")
    assert t.loc["a", "reached"] and t.loc["a", "iteration"] == 10 and t.loc["a", "env_steps"] == 100
    assert not t.loc["b", "reached"] and math.isnan(t.loc["b", "iteration"]) and t.loc["b", "last_iteration"] == 20


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
    assert {"run_dir", "arm", "seed", "segment", "failure_rate"} <= set(eval_df.columns)
    assert eval_df.groupby("run_dir").ngroups == 7


def test_planted_mastery(report):
    m = pd.read_csv(report / "mastery.csv")
    for arm, expected in PLANTED["mastery"].items():
        got = m[m["arm"] == arm].sort_values("bin")["mastery_iteration"].to_numpy()
        np.testing.assert_array_equal(got, expected)
    summary = pd.read_csv(report / "summary.csv").set_index("arm")
    for arm, n in PLANTED["never_mastered"].items():
        assert summary.loc[arm, "bins_never_mastered"] == n


def test_planted_speedups(report):
    per_bin = pd.read_csv(report / "mastery_speedup.csv")
    for arm, expected in PLANTED["mastery_ratio"].items():
        got = per_bin[per_bin["arm"] == arm].sort_values("bin")["ratio"].to_numpy()
        np.testing.assert_allclose(got, expected)
    speed = pd.read_csv(report / "speedup.csv").set_index(["arm", "measure"])
    for arm, median in PLANTED["mastery_median"].items():
        assert speed.loc[(arm, "mastery_median"), "ratio"] == pytest.approx(median)
    for measure, ratio in PLANTED["speedup"].items():
        row = speed.loc[(FAST, measure)]
        assert (row["ratio"], row["ci_low"], row["ci_high"]) == pytest.approx((ratio, ratio, ratio))
    times = pd.read_csv(report / "time_to_threshold.csv")
    for arm, it in PLANTED["time_to_threshold"].items():
        got = times.loc[times["arm"] == arm, "iteration"].to_numpy()
        np.testing.assert_array_equal(got, np.full(len(got), it))
    # The running uniform seed (up to iteration 45) already reached the threshold at 40.
    assert len(times[times["arm"] == UNIFORM]) == 3


def _png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path.name} is not a PNG"
    return struct.unpack(">II", head[16:24])


def test_report_files(report):
    tables = ["runs", "summary", "curves", "bin_failure", "final_bin_failure", "sampling", "mastery",
              "mastery_speedup", "time_to_threshold", "speedup", "sensitivity", "segment_failure"]
    figures = ["curve_mean_episode_length", "curve_mean_reward", "curve_eval_failure_rate",
               "bin_failure_heatmap", "final_bin_failure", "sampling_distribution", "mastery", "speedup",
               "sensitivity_sampler.gamma"]
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
    # SLOW never masters bin 3: its jump segment (bins 2, 3) ends at ((0.02 + 0.01 s) + (0.5 + 0.01 s)) / 2.
    assert seg.loc[(SLOW, "jump"), "final_failure"] == pytest.approx(0.265)
    assert seg.loc[(SLOW, "jump"), "bins_never_mastered"] == 1 and seg.loc[(SLOW, "walk"), "bins_never_mastered"] == 0
    assert seg.loc[(SLOW, "jump"), "difficulty"] == 0.8 and seg.loc[(SLOW, "jump"), "num_bins"] == 2
    # Uniform's running seed 2 counts at its last evaluation (iteration 45, all bins mastered).
    assert seg.loc[(UNIFORM, "walk"), "final_failure"] == pytest.approx(0.03)
    assert seg.loc[(UNIFORM, "walk"), "n_seeds"] == 3
    assert "## Segments" in (report / "report.md").read_text()


def test_report_text_partial_sweep(report, sweep):
    md = (report / "report.md").read_text()
    assert "failed — failed: RuntimeError: simulated crash" in md
    assert "missing — job folder missing" in md
    assert "Still running" in md and "up to iteration 45" in md
    assert f"Lowest final overall failure: **`{FAST}`**" in md
    assert "within noise" in md  # FAST vs uniform final failure intervals overlap
    assert "iterations ×2 [2, 2]" in md
    # Sampling heatmaps only for the adaptive arms; sensitivity without the uniform arm's unused gamma.
    assert set(pd.read_csv(report / "sampling.csv")["arm"]) == {FAST, SLOW}
    sens = pd.read_csv(report / "sensitivity.csv")
    assert set(sens["arm"]) == {FAST, SLOW} and set(sens["value"]) == {0.5, 0.9}


def test_curves_are_iqm_over_seeds(report):
    curves = pd.read_csv(report / "curves.csv")
    c = curves[(curves["arm"] == FAST) & (curves["metric"] == "mean_episode_length")].set_index("iteration")
    # Seeds 0 and 1 have 10 + iteration + seed: IQM (n < 4: mean) = 10.5 + iteration, CI [10, 11] + iteration.
    assert c.loc[30, "iqm"] == 40.5 and c.loc[30, "ci_low"] == 40.0 and c.loc[30, "ci_high"] == 41.0
    u = curves[(curves["arm"] == UNIFORM) & (curves["metric"] == "eval_failure_rate")].set_index("iteration")
    assert u.loc[45, "n_seeds"] == 3 and u.loc[50, "n_seeds"] == 2  # the running seed stops at 45


def test_report_is_reproducible(report, sweep, tmp_path):
    again = build_report([sweep], out=tmp_path / "again", opts=ReportOptions(n_resamples=RESAMPLES))
    for name in ("speedup.csv", "summary.csv", "final_bin_failure.csv"):
        pd.testing.assert_frame_equal(pd.read_csv(report / name), pd.read_csv(again / name))


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


def test_short_arm_labels_keep_only_what_differs():
    from analysis.load import short_arm_labels

    labels, shared = short_arm_labels(["a=1,b=2,sampler=uniform", "a=1,b=2,sampler=adaptive", None])
    assert labels == {"a=1,b=2,sampler=uniform": "sampler=uniform", "a=1,b=2,sampler=adaptive": "sampler=adaptive"}
    assert shared == ["a=1", "b=2"]
    labels, _ = short_arm_labels(["k=1,sampler=adaptive", "sampler=adaptive"])
    assert labels == {"k=1,sampler=adaptive": "k=1", "sampler=adaptive": "base"}
    assert short_arm_labels(["only"]) == ({"only": "only"}, [])


def test_speedup_text_calls_a_censored_ratio_a_bound_not_noise():
    from analysis.report import _speedup_text
    from analysis.tables import ReportOptions

    def table(note, bound):
        rows = [("A", m, 486.0, 445.0, 1.09, 1.0, 1.22, note, bound) for m in ("iteration", "env_steps", "wall_time_s")]
        rows.append(("A", "mastery_median", np.nan, np.nan, 1.0, np.nan, np.nan, "48 bins", ""))
        return pd.DataFrame(rows, columns=["arm", "measure", "baseline_value", "arm_value", "ratio", "ci_low",
                                           "ci_high", "note", "bound"])

    lower = " ".join(_speedup_text(table("no baseline seed reached it: the ratio is a lower bound", "lower"), "U",
                                   ReportOptions()))
    assert "iterations ×1.09 [1, 1.22]; a lower bound" in lower and "within noise" not in lower
    upper = " ".join(_speedup_text(table("no arm seed reached it: the ratio is an upper bound", "upper"), "U",
                                   ReportOptions()))
    assert "an upper bound" in upper and "within noise" not in upper
    both = " ".join(_speedup_text(table("1/3 arm seeds, 0/3 baseline seeds never reached it", ""), "U",
                                  ReportOptions()))
    assert "CI contains 1: within noise" in both
