"""The report's whole clips (issue 44): planted whole-clip tables in synthetic runs come out as the
success curve per arm and condition, the survival curves of each run's last whole-clip evaluation and
the final table with start transients apart from later failures; runs without the tables get no word
of whole clips."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from analysis.report import build_report
from analysis.tables import ReportOptions
from bmimic.runs.schema import CLIP_TIME_S, CONDITION, ITERATION, MPKPE_REL_MM
from tests.analysis.synthetic_runs import write_run

OPTS = ReportOptions(n_resamples=200, n_permutations=999)
ARMS = {"sampler=uniform": (0.25, 0.5), "sampler=adaptive": (0.5, 1.0)}
"""Robust whole-clip success at iterations 30 and 60, per arm (8 rollouts on each of 2 clips)."""


def _whole_clip_tables(run, success: tuple[float, float], seed: int, failures: bool = False) -> None:
    """The run's whole-clip tables: clips, and the failed rollouts, which are all the survival curve is
    derived from (the report never reads a survival file). By default every failed rollout failed between
    1 and 2 s in (clip 0 at 1.6 s, clip 1 at 1.2 s); with `failures`, the last evaluation's failures fall
    where test_where_whole_clip_rollouts_fail plants them and the first one's at 0.3 s."""
    clips, rows = [], []
    for it, s in zip((30, 60), success):
        completed = round(8 * s)
        for clip, duration in ((0, 2.5), (1, 1.5)):
            clips.append({ITERATION: it, "env_steps": 1000 * it, "wall_time_s": float(it), CONDITION: "robust",
                          "clip": clip, "clip_name": f"c{clip}", "clip_duration_s": duration, "rollouts": 8,
                          "completed": completed, "success_rate": completed / 8, "failures": 8 - completed,
                          "transient_failures": min(1, 8 - completed), "later_failures": 8 - completed - min(1, 8 - completed),
                          MPKPE_REL_MM: 30.0 + seed})
            failed = 8 - completed
            if not failures:
                times = [1.6 if clip == 0 else 1.2] * failed
            elif it == 30:
                times = [0.3] * failed
            else:  # clip 0 three at 2.2 s and one transient at 0.5 s, clip 1 all at 1.2 s
                times = ([0.5] + [2.2] * (failed - 1) if clip == 0 else [1.2] * failed) if failed else []
            rows += [{ITERATION: it, "env_steps": 1000 * it, CONDITION: "robust", "clip": clip,
                      "clip_name": f"c{clip}", "rollout": r, "failure_time_s": t, "transient": t < 1.0}
                     for r, t in enumerate(times)]
    pd.DataFrame(clips).to_parquet(run / "whole_clip.parquet")
    pd.DataFrame(rows).to_parquet(run / "whole_clip_failures.parquet")


def _study(root, with_whole_clip: bool, failures: bool = False):
    for arm, success in ARMS.items():
        for seed in (0, 1):
            run = write_run(root / arm / f"seed={seed}", sampler=arm.split("=")[1], seed=seed, overrides=[arm],
                            mastery=[10.0, 20.0, 30.0, 40.0])
            if with_whole_clip:
                _whole_clip_tables(run, success, seed, failures)
    return root


def test_whole_clip_success_survival_and_final_table(tmp_path):
    out = build_report([_study(tmp_path / "study", True)], opts=OPTS)
    md = (out / "report.md").read_text()
    assert "## Whole clips" in md
    assert "![Whole-clip success over training per condition" in md and "whole_clip_survival.png" in md
    # two clips of 8 robust rollouts: 0.5 / sqrt(8) = 0.177
    assert "robust: 8 rollouts per clip, a binomial standard error of up to 0.177 (at success 0.5)" in md
    for name in ("whole_clip_success.png", "whole_clip_survival.png", "whole_clip_curves.csv", "whole_clip_final.csv"):
        assert (out / name).stat().st_size > 0
    curves = pd.read_csv(out / "whole_clip_curves.csv").set_index(["arm", ITERATION])
    arm = {a: next(label for label in curves.index.get_level_values("arm") if a.split("=")[1] in label) for a in ARMS}
    for a, (first, last) in ARMS.items():
        assert curves.loc[(arm[a], 30), "point"] == pytest.approx(first)
        assert curves.loc[(arm[a], 60), "point"] == pytest.approx(last)
    final = pd.read_csv(out / "whole_clip_final.csv").set_index("arm")
    assert final.loc[arm["sampler=uniform"], "mean"] == pytest.approx(0.5)
    assert final.loc[arm["sampler=uniform"], "transient_failures_per_seed"] == pytest.approx(2.0)  # 1 per clip
    assert final.loc[arm["sampler=uniform"], "later_failures_per_seed"] == pytest.approx(6.0)
    assert final.loc[arm["sampler=adaptive"], MPKPE_REL_MM] == pytest.approx(30.5)  # seeds 30 and 31 mm
    assert final.loc[arm["sampler=adaptive"], "iterations"] == "60;60"
    survival = pd.read_csv(out / "whole_clip_survival.csv").set_index(["arm", CLIP_TIME_S])
    uniform = survival.loc[arm["sampler=uniform"]]
    assert uniform.loc[1.0, "tracking_frac"] == pytest.approx(1.0)  # both clips, all 8 rollouts
    # clips of 2.5 s and 1.5 s, half of each one's rollouts failing between 1 and 2 s: a Kaplan-Meier curve
    assert uniform.loc[1.5, "tracking_frac"] == pytest.approx(0.75)  # 4 of clip 1's 8 at clip 1's end, 16 at risk
    assert uniform.loc[2.0, "tracking_frac"] == pytest.approx(0.375)  # then 4 of clip 0's 8, clip 1 ended
    assert uniform.loc[2.5, "tracking_frac"] == pytest.approx(0.375)


def test_where_whole_clip_rollouts_fail(tmp_path):
    out = build_report([_study(tmp_path / "study", True, failures=True)], opts=OPTS)
    places = pd.read_csv(out / "whole_clip_failure_places.csv")
    # uniform at its last evaluation (60): 4 failures per clip and seed, 16 pooled over its 2 seeds
    uniform = places[places["arm"].str.contains("uniform")]
    assert list(zip(uniform["clip_name"], uniform["second"], strict=True)) == [("c1", 1), ("c0", 2), ("c0", 0)]
    assert uniform["share"].tolist() == pytest.approx([0.5, 0.375, 0.125])
    assert (uniform["arm_failures"] == 16).all()
    assert not places["arm"].str.contains("adaptive").any()  # every rollout completed at iteration 60
    md = (out / "report.md").read_text()
    assert "Where they fail" in md and "c1 1–2 s (50%), c0 2–3 s (38%), c0 0–1 s (12%)" in md


def test_a_report_without_whole_clip_tables_says_nothing_about_them(tmp_path):
    out = build_report([_study(tmp_path / "study", False)], opts=OPTS)
    assert "hole clip" not in (out / "report.md").read_text() and "hole-clip" not in (out / "report.md").read_text()
    assert not list(out.glob("whole_clip*"))


def _checkpoint_whole_clip(run, iteration: int, condition: str, completed: int, fail_times: list[float],
                           duration: float = 4.0) -> None:
    """What `bmimic.eval RUN --whole-clip` writes for a checkpoint: eval/model_<it>/whole_clip/ (no iteration
    column; the summary, written last, names it)."""
    import json

    out = run / "eval" / f"model_{iteration}" / "whole_clip"
    out.mkdir(parents=True, exist_ok=True)
    rollouts = completed + len(fail_times)
    pd.DataFrame([{CONDITION: condition, "clip": 0, "clip_name": "c0", "clip_duration_s": duration,
                   "rollouts": rollouts, "completed": completed, "success_rate": completed / rollouts,
                   "failures": len(fail_times), "transient_failures": sum(t < 1.0 for t in fail_times),
                   "later_failures": sum(t >= 1.0 for t in fail_times)}]).to_csv(out / "whole_clip.csv", index=False)
    pd.DataFrame([{CONDITION: condition, "clip": 0, "clip_name": "c0", CLIP_TIME_S: t, "rollouts": rollouts,
                   "tracking": completed + sum(f > t for f in fail_times),
                   "tracking_frac": (completed + sum(f > t for f in fail_times)) / rollouts} for t in (0.0, 1.0, 2.0, 3.0)]
                 ).to_csv(out / "whole_clip_survival.csv", index=False)
    pd.DataFrame([{CONDITION: condition, "clip": 0, "clip_name": "c0", "rollout": i, "failure_frame": int(t * 50),
                   "failure_time_s": t, "bin": int(t), "transient": t < 1.0} for i, t in enumerate(fail_times)],
                 columns=[CONDITION, "clip", "clip_name", "rollout", "failure_frame", "failure_time_s", "bin", "transient"]
                 ).to_csv(out / "whole_clip_failures.csv", index=False)
    (out / "whole_clip_summary.json").write_text(json.dumps({"iteration": iteration, "env_steps": 1000 * iteration}))


def test_checkpoint_whole_clip_evaluations_join_the_report_with_seconds_tracked(tmp_path):
    """Runs evaluated after training (`bmimic.eval --whole-clip`) report like runs evaluated during it; the
    seconds tracked per rollout are the area under the survival curve, planted: uniform's 4 robust rollouts
    fail at 1, 2, 3 and 3 s of a 4 s clip (2.25 s), adaptive's 2 complete and 2 fail at 2 s (3.0 s)."""
    root = tmp_path / "study"
    plant = {"sampler=uniform": (0, [1.0, 2.0, 3.0, 3.0]), "sampler=adaptive": (2, [2.0, 2.0])}
    for arm, (completed, fails) in plant.items():
        for seed in (0, 1):
            run = write_run(root / arm / f"seed={seed}", sampler=arm.split("=")[1], seed=seed, overrides=[arm],
                            mastery=[10.0, 20.0, 30.0, 40.0])
            _checkpoint_whole_clip(run, 60, "robust", completed, fails)
    out = build_report([root], opts=OPTS)
    final = pd.read_csv(out / "whole_clip_final.csv").set_index("arm")
    arm = {a: next(label for label in final.index if a.split("=")[1] in label) for a in plant}
    assert final.loc[arm["sampler=uniform"], "mean"] == pytest.approx(0.0)
    assert final.loc[arm["sampler=adaptive"], "mean"] == pytest.approx(0.5)
    assert final.loc[arm["sampler=uniform"], "tracked_s_mean"] == pytest.approx(2.25)
    assert final.loc[arm["sampler=adaptive"], "tracked_s_mean"] == pytest.approx(3.0)
    assert final.loc[arm["sampler=adaptive"], "iterations"] == "60;60"
    md = (out / "report.md").read_text()
    assert "seconds tracked per rollout" in md and "2.25" in md


def test_a_checkpoint_evaluation_adds_only_what_training_did_not_evaluate(tmp_path):
    """Training evaluated robust whole clips at 30 and 60; a later `bmimic.eval --whole-clip` of the
    iteration-60 checkpoint adds its nominal rollout and leaves training's robust rows as they were."""
    root = _study(tmp_path / "study", True)
    for run in root.glob("*/seed=*"):
        _checkpoint_whole_clip(run, 60, "robust", 0, [0.5] * 8)  # would change success if it were counted
        _checkpoint_whole_clip(run, 60, "nominal", 1, [])
    out = build_report([root], opts=OPTS)
    final = pd.read_csv(out / "whole_clip_final.csv").set_index(["arm", CONDITION])
    uniform = next(a for a in final.index.get_level_values("arm") if "uniform" in a)
    assert final.loc[(uniform, "robust"), "mean"] == pytest.approx(0.5)  # training's, not the planted 0
    assert final.loc[(uniform, "nominal"), "mean"] == pytest.approx(1.0)
    # training's failures, not the planted ones: 4 of 8 per clip at 1.6 s (clip 0, 2.5 s) and 1.2 s (clip 1,
    # 1.5 s), the others tracked to the end: (4 * 1.6 + 4 * 2.5 + 4 * 1.2 + 4 * 1.5) / 16
    assert final.loc[(uniform, "robust"), "tracked_s_mean"] == pytest.approx(1.7)


def test_a_checkpoint_evaluation_without_its_iteration_is_one_line(tmp_path):
    import json

    from analysis import AnalysisError

    root = _study(tmp_path / "study", False)
    run = next(root.glob("*/seed=0"))
    _checkpoint_whole_clip(run, 60, "robust", 1, [])
    summary = run / "eval" / "model_60" / "whole_clip" / "whole_clip_summary.json"
    summary.write_text(json.dumps({"iteration": "sixty"}))
    with pytest.raises(AnalysisError, match=r"whole_clip_summary.json: 'iteration' must be an integer >= 0, got 'sixty'"):
        build_report([root], opts=OPTS)


def test_clips_of_different_lengths_pool_as_a_kaplan_meier_curve_and_equal_ones_as_the_fraction():
    from analysis.whole_clip import pooled_survival

    def table(rows: list[tuple[int, float, int]]) -> pd.DataFrame:  # (clip, time_s, tracking) of 2 rollouts each
        return pd.DataFrame([{"arm": "a", "run_dir": "r", "condition": "robust", "clip": c, "time_s": t,
                              "rollouts": 2, "tracking": k} for c, t, k in rows])

    # clip 0 ends at 2 s, one rollout failing in (0, 1]; clip 1 ends at 4 s, one failing in (2, 3]
    km = pooled_survival(table([(0, 0.0, 2), (0, 1.0, 1), (0, 2.0, 1),
                                (1, 0.0, 2), (1, 1.0, 2), (1, 2.0, 2), (1, 3.0, 1), (1, 4.0, 1)]))
    assert km["kaplan_meier"].all()
    # at risk 4, 4, 3, 2, 1; failures 0, 1, 0, 1, 0 (the plain fraction would read 0.5 at 3 s: clip 1 alone)
    np.testing.assert_allclose(km["frac"], [1.0, 0.75, 0.75, 0.375, 0.375])
    same = pooled_survival(table([(0, 0.0, 2), (0, 1.0, 1), (1, 0.0, 2), (1, 1.0, 2)]))
    assert not same["kaplan_meier"].any()
    np.testing.assert_allclose(same["frac"], [1.0, 0.75])


def test_the_per_clip_table_says_how_finely_one_evaluation_resolves_a_clip():
    from analysis.whole_clip import per_clip_resolution
    rows = [{"arm": "a", CONDITION: c, "clip": k, "rollouts": r} for c, r in (("robust", 32), ("nominal", 1)) for k in (0, 1)]
    line = per_clip_resolution(pd.DataFrame(rows))
    # 0.5 / sqrt(32) = 0.0884: the largest standard error of a success read from 32 rollouts
    assert "robust: 32 rollouts per clip, a binomial standard error of up to 0.0884" in line
    assert "nominal: one rollout per clip (0 or 1)" in line


def test_a_library_counts_its_clips_by_the_mean_and_by_each_seed():
    """Planted: 3 clips, 2 seeds, 32 robust rollouts. Seed 0 completes 32, 30 and 16 (1, 0.9375, 0.5), seed 1
    28, 32 and 31 (0.875, 1, 0.96875): the means 0.9375, 0.96875, 0.734 put 2 clips at >= 0.9 and 1 at >= 0.95,
    seed 0 alone 2 and 1, seed 1 alone 2 and 2 (a seed's count is one policy's, not read off the mean)."""
    from analysis.whole_clip import _per_clip_section, per_clip_rows

    completed = {0: (32, 30, 16), 1: (28, 32, 31)}
    clips = pd.DataFrame([{"run_dir": f"s{seed}", "arm": "a", "seed": seed, CONDITION: "robust", ITERATION: 100,
                           "clip": k, "clip_name": f"c{k}", "rollouts": 32, "completed": n, MPKPE_REL_MM: 40.0}
                          for seed, ns in completed.items() for k, n in enumerate(ns)])
    last = pd.DataFrame({"run_dir": ["s0", "s1"], CONDITION: "robust", ITERATION: 100})
    rows = per_clip_rows(clips, last)
    assert list(rows["seeds"]) == ["0;1"] * 3 and list(rows["per_seed"]) == ["1;0.875", "0.9375;1", "0.5;0.96875"]
    text = "\n".join(_per_clip_section(rows))
    assert ("- `a`, robust: clips at whole-clip success >= 0.9: 2, >= 0.95: 1 of 3 by the mean over seeds (per seed: "
            "seed 0 >= 0.9: 2, >= 0.95: 1; seed 1 >= 0.9: 2, >= 0.95: 2); ") in text
    # one seed: the count alone
    one = per_clip_rows(clips[clips["seed"] == 0], last)
    assert "- `a`, robust: clips at whole-clip success >= 0.9: 2, >= 0.95: 1 of 3; " in "\n".join(_per_clip_section(one))
