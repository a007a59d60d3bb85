"""The report's whole clips (issue 44): planted whole-clip tables in synthetic runs come out as the
success curve per arm and condition, the survival curves of each run's last whole-clip evaluation and
the final table with start transients apart from later failures; runs without the tables get no word
of whole clips."""

from __future__ import annotations

import pandas as pd
import pytest

from analysis.report import build_report
from analysis.tables import ReportOptions
from bmimic.run_schema import CLIP_TIME_S, CONDITION, ITERATION, MPKPE_REL_MM
from tests.analysis.synthetic_runs import write_run

OPTS = ReportOptions(n_resamples=200, n_permutations=999)
ARMS = {"sampler=uniform": (0.25, 0.5), "sampler=adaptive": (0.5, 1.0)}
"""Robust whole-clip success at iterations 30 and 60, per arm (8 rollouts on each of 2 clips)."""


def _whole_clip_tables(run, success: tuple[float, float], seed: int) -> None:
    clips, survival = [], []
    for it, s in zip((30, 60), success):
        completed = round(8 * s)
        for clip, duration in ((0, 2.5), (1, 1.5)):
            clips.append({ITERATION: it, "env_steps": 1000 * it, "wall_time_s": float(it), CONDITION: "robust",
                          "clip": clip, "clip_name": f"c{clip}", "clip_duration_s": duration, "rollouts": 8,
                          "completed": completed, "success_rate": completed / 8, "failures": 8 - completed,
                          "transient_failures": min(1, 8 - completed), "later_failures": 8 - completed - min(1, 8 - completed),
                          MPKPE_REL_MM: 30.0 + seed})
            # every failed rollout failed between 1 and 2 s in: all 8 tracking at 0 and 1 s, `completed` after
            times = [0.0, 1.0, 2.0, duration] if duration > 2 else [0.0, 1.0, duration]
            survival += [{ITERATION: it, "env_steps": 1000 * it, CONDITION: "robust", "clip": clip, "clip_name": f"c{clip}",
                          CLIP_TIME_S: t, "rollouts": 8, "tracking": 8 if t <= 1.0 else completed,
                          "tracking_frac": (8 if t <= 1.0 else completed) / 8} for t in times]
    pd.DataFrame(clips).to_parquet(run / "whole_clip.parquet")
    pd.DataFrame(survival).to_parquet(run / "whole_clip_survival.parquet")


def _study(root, with_whole_clip: bool):
    for arm, success in ARMS.items():
        for seed in (0, 1):
            run = write_run(root / arm / f"seed={seed}", sampler=arm.split("=")[1], seed=seed, overrides=[arm],
                            mastery=[10.0, 20.0, 30.0, 40.0])
            if with_whole_clip:
                _whole_clip_tables(run, success, seed)
    return root


def test_whole_clip_success_survival_and_final_table(tmp_path):
    out = build_report([_study(tmp_path / "study", True)], opts=OPTS)
    md = (out / "report.md").read_text()
    assert "## Whole clips" in md
    assert "![Whole-clip success over training per condition" in md and "whole_clip_survival.png" in md
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
    assert uniform.loc[2.0, "tracking_frac"] == pytest.approx(0.5)  # clip 0 alone is 2.5 s long
    assert uniform.loc[1.5, "tracking_frac"] == pytest.approx(0.5)  # clip 1's last frame


def test_a_report_without_whole_clip_tables_says_nothing_about_them(tmp_path):
    out = build_report([_study(tmp_path / "study", False)], opts=OPTS)
    assert "hole clip" not in (out / "report.md").read_text() and "hole-clip" not in (out / "report.md").read_text()
    assert not list(out.glob("whole_clip*"))
