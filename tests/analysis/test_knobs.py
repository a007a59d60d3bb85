"""The Knobs section (analysis.knobs): one knob at a time around a reference arm, on a planted study
(tests/analysis/synthetic_runs.make_knob_study) whose speedups are known exactly."""

from __future__ import annotations

import math
import shutil

import pandas as pd
import pytest

from analysis.knobs import knob_arms, knob_levels, knob_summary, knob_trends, rank_trend
from analysis.load import load_runs
from analysis.report import build_report
from analysis.report_compute import read_runs
from analysis.tables import ReportOptions
from tests.analysis.synthetic_runs import KNOB_REFERENCE, UNIFORM, make_knob_study, make_sweep


@pytest.fixture(scope="module")
def knob_report(tmp_path_factory):
    root = tmp_path_factory.mktemp("knobs")
    out = build_report([make_knob_study(root)], out=root / "report")
    return out, pd.read_csv(out / "knob_levels.csv"), pd.read_csv(out / "knob_summary.csv")


def test_each_sweep_file_expects_its_own_seeds(tmp_path):
    # The baselines have seeds 0-4 and each knob level 0-2, all in one folder: no knob level misses
    # seeds 3 and 4. A level's seed gone from disk is missing, as is the baseline's.
    study = make_knob_study(tmp_path)
    runs = load_runs(study)
    assert not (runs["status"] == "missing").any()
    level = next(a for a in runs["arm"].unique() if "gamma=0.5" in a)
    shutil.rmtree(study / level / "seed=1")
    shutil.rmtree(study / f"motion=m,{KNOB_REFERENCE}" / "seed=4")
    missing = load_runs(study).query("status == 'missing'")
    assert sorted(zip(missing["arm"], missing["seed"], strict=True)) == sorted(
        [(level, 1), (f"motion=m,{KNOB_REFERENCE}", 4)])


def test_without_sweep_files_the_grid_is_the_folders_seeds(tmp_path):
    # Runs launched without +sweep (an ad-hoc multirun): every arm is expected at every seed seen.
    sweep = make_sweep(tmp_path)  # its slow arm's seed 2 never started
    before = load_runs(sweep).query("status == 'missing'")
    assert list(before["seed"]) == [2]
    shutil.rmtree(sweep / UNIFORM / "seed=1")
    missing = load_runs(sweep).query("status == 'missing'")
    assert sorted(zip(missing["arm"], missing["seed"], strict=True)) == sorted(
        [(before["arm"].iloc[0], 2), (UNIFORM, 1)])


def test_knob_arms_finds_one_key_changes_of_the_reference(tmp_path):
    runs = read_runs([make_knob_study(tmp_path)], ReportOptions()).runs
    found = knob_arms(runs)
    assert set(found["reference"]) == {KNOB_REFERENCE}
    by_knob = found.groupby("knob")["value"].apply(sorted).to_dict()
    assert by_knob == {"sampler.gamma": [0.5, 0.9, 1.0], "sampler.lambda_uniform": [0.1, 0.4]}
    assert "sampler=uniform" not in set(found["arm"])


def test_an_arm_changing_two_keys_is_no_knob_level(tmp_path):
    sweep = make_knob_study(tmp_path)
    from tests.analysis.synthetic_runs import write_run
    arm = "motion=m,sampler.K=3,sampler.gamma=0.5,sampler=adaptive"
    write_run(sweep / arm / "seed=0", sampler="adaptive", seed=0, overrides=arm.split(","),
              mastery=[5.0, 10.0, 15.0, 20.0], sampler_cfg={"gamma": 0.5, "K": 3}, last_iteration=100)
    runs = read_runs([sweep], ReportOptions()).runs
    assert "sampler.K=3,sampler.gamma=0.5,sampler=adaptive" not in set(knob_arms(runs)["arm"])


def test_no_reference_no_knobs(tmp_path):
    runs = load_runs([make_sweep(tmp_path)])  # gamma 0.5 and 0.9 both set explicitly: no reference arm
    assert knob_arms(runs).empty
    assert knob_levels(knob_arms(runs), pd.DataFrame(columns=["arm", "seed", "value"]), pd.DataFrame(),
                       ReportOptions()).empty


def test_planted_speedups_and_tests(knob_report):
    _, levels, _ = knob_report
    lv = levels.set_index(["knob", "value"])
    assert lv.loc[("sampler.gamma", 0.5), "speedup_90"] == pytest.approx(2.0)
    assert lv.loc[("sampler.gamma", 1.0), "speedup_90"] == pytest.approx(1.0)
    assert lv.loc[("sampler.lambda_uniform", 0.4), "speedup_90"] == pytest.approx(40 / 60)
    assert lv.loc[("sampler.gamma", 0.9), "vs_uniform_90"] == pytest.approx(2.0)  # the reference vs uniform
    assert lv.loc[("sampler.gamma", 0.5), "vs_uniform_90"] == pytest.approx(4.0)
    assert lv.loc[("sampler.gamma", 0.5), "iterations_90"] == 20
    # every seed of gamma 0.5 beats every seed of the reference: the smallest p 3 v 5 seeds allow
    assert lv.loc[("sampler.gamma", 0.5), "speedup_p_90"] == pytest.approx(2 / math.comb(8, 3))
    assert lv.loc[("sampler.gamma", 1.0), "speedup_p_90"] == pytest.approx(1.0)
    # the speedup's 95% interval (the Gehan test inverted): gamma 0.5's excludes 1 as its p < 0.05 does and
    # holds its planted x2; gamma 1.0's holds 1
    low, high = lv.loc[("sampler.gamma", 0.5), ["speedup_low_90", "speedup_high_90"]]
    assert 1.0 < low <= 2.0 <= high
    low, high = lv.loc[("sampler.gamma", 1.0), ["speedup_low_90", "speedup_high_90"]]
    assert low <= 1.0 <= high
    # final failure is planted per seed alike in every arm: seeds 0-2 (mean 0.03) against 0-4 (0.04)
    assert lv.loc[("sampler.gamma", 0.5), "failure_difference"] == pytest.approx(-0.01)
    assert lv.loc[("sampler.gamma", 0.5), "failure_p"] > 0.05
    # its 95% interval (the same test inverted) holds the difference and, as p > 0.05, zero
    low, high = lv.loc[("sampler.gamma", 0.5), ["failure_difference_low", "failure_difference_high"]]
    assert low < -0.01 < 0.0 < high
    assert bool(lv.loc[("sampler.gamma", 0.9), "is_reference"])
    assert lv.loc[("sampler.gamma", 0.9), ["failure_difference_low", "failure_difference_high"]].isna().all()


def test_which_knobs_matter(knob_report):
    _, levels, summary = knob_report
    s = summary.set_index("knob")
    assert s.loc["sampler.gamma", "fastest_value"] == 0.5 and s.loc["sampler.gamma", "slowest_value"] == 1.0
    assert s.loc["sampler.gamma", "fastest_speedup"] == pytest.approx(2.0)
    # gamma 0.5's time p is the smallest 3 v 5 seeds allow (2/56): below 0.05 alone, not after Holm over 4 tests
    assert str(s.loc["sampler.gamma", "differing_levels_uncorrected"]) == "0.5"
    assert s.loc["sampler.gamma", "tests"] == 4
    assert s.loc["sampler.gamma", "verdict"] == "within noise" and pd.isna(s.loc["sampler.gamma", "differing_levels"])
    assert s.loc["sampler.lambda_uniform", "slowest_speedup"] == pytest.approx(40 / 60)
    # a knob whose only level matches the reference is within noise
    same = levels[(levels["knob"] == "sampler.gamma") & (levels["value"] != 0.5)]
    assert knob_summary(same)["verdict"].tolist() == ["within noise"]


def _levels(knob: str, ps: dict[float, tuple[float, float]]) -> pd.DataFrame:
    """knob_levels rows of a reference 0.9 and levels value -> (failure p, time p), everything else planted flat."""
    rows = [{"knob": knob, "value": 0.9, "arm": "ref", "is_reference": True, "failure_p": math.nan,
             "speedup_p_90": math.nan}]
    rows += [{"knob": knob, "value": v, "arm": f"a{v}", "is_reference": False, "failure_p": fp, "speedup_p_90": tp}
             for v, (fp, tp) in ps.items()]
    out = pd.DataFrame(rows)
    for c in ("speedup_90", "speedup_low_90", "speedup_high_90", "speedup_seed_min_90", "speedup_seed_max_90"):
        out[c] = 1.0
    out["failure_difference"] = 0.0
    out["failure_difference_low"], out["failure_difference_high"] = -1.0, 1.0
    return out


def test_the_verdict_follows_holm_over_the_rows_tests():
    # three levels, six tests: Holm multiplies the smallest p by 6, the next by 5, ...
    s = knob_summary(_levels("k", {0.5: (0.005, 0.5), 0.7: (0.04, 0.9), 1.0: (0.2, 0.3)})).iloc[0]
    assert s["tests"] == 6 and s["differing_levels_uncorrected"] == "0.5, 0.7"
    assert s["differing_levels"] == "0.5" and s["verdict"] == "differs"  # 6 x 0.005 = 0.03; 5 x 0.04 = 0.2
    s = knob_summary(_levels("k", {0.5: (0.009, 0.5), 0.7: (0.04, 0.9), 1.0: (0.2, 0.3)})).iloc[0]
    assert s["differing_levels"] == "" and s["verdict"] == "within noise"  # 6 x 0.009 = 0.054
    # a NaN p (a time that cannot be compared) is no test: the family shrinks
    s = knob_summary(_levels("k", {0.5: (0.02, math.nan)})).iloc[0]
    assert s["tests"] == 1 and s["differing_levels"] == "0.5" and s["verdict"] == "differs"


def test_rank_trend_is_spearmans_rho_with_a_permutation_p():
    # a perfectly monotone 6 pairs: rho +-1, and exactly 2 of the 720 orders are as extreme
    assert rank_trend([1, 2, 3, 4, 5, 6], [0.1, 0.2, 0.3, 0.4, 0.5, 0.6]) == (1.0, pytest.approx(2 / 720))
    assert rank_trend([1, 2, 3, 4, 5, 6], [6, 5, 4, 3, 2, 1]) == (-1.0, pytest.approx(2 / 720))
    # ties (seeds share their level's value) take average ranks, as scipy's spearmanr
    values = [0.25] * 3 + [0.5] * 3 + [1.0] * 5 + [2.0] * 3 + [4.0] * 3
    outcomes = [0.3, 0.1, 0.7, 0.2, 0.9, 0.4, 0.5, 0.8, 0.6, 0.05, 0.75, 0.65, 0.15, 0.35, 0.85, 0.45, 0.55]
    rho, p = rank_trend(values, outcomes)
    from scipy.stats import spearmanr
    assert rho == pytest.approx(spearmanr(values, outcomes).statistic) and 0.0 < p <= 1.0
    assert all(math.isnan(x) for x in rank_trend([1, 2], [3, 4]) + rank_trend([1, 1, 1], [1, 2, 3]))


def test_knob_trends_find_a_planted_dose_response_and_not_an_absent_one():
    # knob "up": failure rises with the value in every seed; knob "flat": the same values at every level
    rows, knobs = [], []
    for knob, rise in (("up", 0.01), ("flat", 0.0)):
        for v in (0.5, 1.0, 2.0, 4.0):
            arm = f"{knob}={v}"
            knobs.append({"arm": arm, "knob": knob, "value": v, "reference": f"{knob}=1.0"})
            rows += [{"arm": arm, "seed": s, "value": 0.05 + rise * v + 0.001 * s} for s in range(3)]
    trends = knob_trends(pd.DataFrame(knobs), pd.DataFrame(rows), ReportOptions()).set_index("knob")
    assert trends.loc["up", "trend_runs"] == 12 and trends.loc["up", "trend_rho"] > 0.9
    assert trends.loc["up", "trend_p"] < 0.001
    assert abs(trends.loc["flat", "trend_rho"]) < 0.2 and trends.loc["flat", "trend_p"] > 0.5


def test_report_has_the_knob_section_and_figures(knob_report, tmp_path):
    out, _, _ = knob_report
    text = (out / "report.md").read_text()
    assert "## Knobs" in text and "| sampler.gamma | 0.9 | 0.5, 0.9, 1 |" in text
    assert "vs reference [95% interval] (p)" in text and "exact permutation test inverted" in text
    assert "trend of final failure over values (ρ, p)" in text and "Spearman's rank correlation" in text
    for key in ("gamma", "lambda_uniform"):
        for kind in ("speedup", "bins", "sampling"):
            assert (out / f"knob_{key}_{kind}.png").stat().st_size > 0
    plain = build_report([make_sweep(tmp_path)], out=tmp_path / "plain")
    assert "## Knobs" not in (plain / "report.md").read_text()


BIN_SIZE_ARM = "sampler.bin_size_seconds=1.0,sampler=adaptive"


@pytest.fixture(scope="module")
def bin_size_study(tmp_path_factory):
    """The planted knob study plus a bin-size knob: 8 bins of 1 s over the same 8 s (the others: 4 of 2 s),
    each second mastered when the reference masters it."""
    from tests.analysis.synthetic_runs import write_run
    root = tmp_path_factory.mktemp("bin_size")
    sweep = make_knob_study(root)
    for seed in range(3):
        write_run(sweep / f"motion=m,{BIN_SIZE_ARM}" / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["motion=m", *BIN_SIZE_ARM.split(",")], mastery=[10.0 * (b // 2 + 1) for b in range(8)],
                  sampler_cfg={"gamma": 0.9, "lambda_uniform": 0.1, "bin_size_seconds": 1.0}, last_iteration=100,
                  bin_size_s=1.0)
    return sweep


def test_a_bin_size_knob_is_compared_overall_and_kept_out_of_the_per_bin_tables(bin_size_study, tmp_path):
    from analysis import AnalysisError
    with pytest.raises(AnalysisError, match="bin layouts"):  # one bin layout unless the user says otherwise
        build_report([bin_size_study], out=tmp_path / "refused")
    out = build_report([bin_size_study], out=tmp_path / "report", allow_mixed=True)
    levels = pd.read_csv(out / "knob_levels.csv").set_index(["knob", "value"])
    assert levels.loc[("sampler.bin_size_seconds", 1.0), "iterations_90"] == 40  # overall: compared as any level
    mastery = pd.read_csv(out / "mastery.csv")
    assert BIN_SIZE_ARM not in set(mastery["arm"]) and mastery["bin"].max() == 3  # the reference's 4 bins, never 8
    assert set(mastery.loc[mastery["bin"] == 1, "segment"]) == {"walk"}  # bin 1 is 2-4 s, not 1-2 s's max/min mix
    per_bin = pd.read_csv(out / "bin_failure.csv")
    assert BIN_SIZE_ARM not in set(per_bin["arm"]) and per_bin["bin"].max() == 3
    text = (out / "report.md").read_text()
    assert f"Cut into other bins than the baseline's: `{BIN_SIZE_ARM}`" in text
    assert (out / "knob_bin_size_seconds_speedup.png").is_file()
    assert not (out / "knob_bin_size_seconds_bins.png").exists()  # bins of 1 s and 2 s share no axis
    clip_time = pd.read_csv(out / "knob_bin_size_seconds_clip_time.csv")  # ... but share clip time
    assert (out / "knob_bin_size_seconds_clip_time.png").is_file()
    widths = clip_time.assign(w=clip_time["bin_end_s"] - clip_time["bin_start_s"]).groupby("arm")["w"].agg(["min", "count"])
    assert widths.loc[BIN_SIZE_ARM].tolist() == [1.0, 8] and widths.loc[KNOB_REFERENCE].tolist() == [2.0, 4]
    assert (out / "knob_gamma_bins.png").is_file()


def test_the_sweep_index_lists_runs_of_every_bin_layout(bin_size_study):
    from analysis.index import write_index
    index = pd.read_csv(write_index(bin_size_study))
    assert (index["arm"].str.contains("bin_size_seconds=1.0")).sum() == 3 and len(index) == 5 + 5 + 3 + 3 + 3 + 3


def test_over_clip_time_puts_every_layout_on_one_axis():
    from analysis.bin_tables import over_clip_time
    rows, samp = [], []
    for arm, probs in (("coarse", [0.25, 0.75]), ("fine", [0.1, 0.2, 0.3, 0.4])):
        width = 4.0 / len(probs)
        for seed, fail in ((0, 0.1), (1, 0.3)):
            for b, p in enumerate(probs):
                edges = dict(bin=b, bin_start_s=b * width, bin_end_s=(b + 1) * width)
                rows += [dict(arm=arm, run_dir=f"{arm}{seed}", iteration=it, failure_rate=fail + it, **edges)
                         for it in (5, 10)]
                samp.append(dict(arm=arm, run_dir=f"{arm}{seed}", iteration=9, probability=p, **edges))
    cells = over_clip_time(pd.DataFrame(rows), pd.DataFrame(samp)).set_index(["arm", "bin"])
    assert cells.loc["coarse", "density"].tolist() == pytest.approx([0.5, 1.5])  # probability per second / uniform's
    assert cells.loc["fine", "density"].tolist() == pytest.approx([0.4, 0.8, 1.2, 1.6])
    assert cells["failure_rate"].tolist() == pytest.approx([10.2] * 6)  # the last evaluation, mean of the seeds
