"""`--max-iteration`: runs that trained further are read as if they had stopped at the common budget
(the design-choice study compares 3000-iteration runs with 1500-iteration ones)."""

from __future__ import annotations

import pandas as pd
import pytest

from analysis.report import build_report, main
from analysis.tables import ReportOptions
from tests.analysis.synthetic_runs import make_speedup_sweep, write_run


def test_a_common_budget_censors_what_came_later_and_drops_the_later_rows(tmp_path):
    # Uniform masters its last bin at about 80 x U(0.75, 1.3) >= 60 iterations, adaptive at about half that:
    # read up to 50, every uniform seed is censored there and no row past 50 is used.
    sweep = make_speedup_sweep(tmp_path, n_seeds=5, ratio=2.0)
    full = build_report(sweep, tmp_path / "full", ReportOptions(n_resamples=200))
    cut = build_report(sweep, tmp_path / "cut", ReportOptions(max_iteration=50, n_resamples=200))
    t_full, t_cut = (pd.read_csv(out / "time_to_threshold.csv").set_index(["arm", "seed"]) for out in (full, cut))
    uniform = t_cut.loc["sampler=uniform"]
    assert not uniform["reached"].any() and (uniform["last_iteration"] == 50).all()
    assert t_full.loc["sampler=uniform", "reached"].all()  # they all got there by 150
    adaptive = t_cut.loc["sampler=adaptive"]
    reached = adaptive["reached"]
    assert reached.any()
    # Where the cut arm reached the threshold, it did so exactly when the full read says it did.
    assert (adaptive.loc[reached, "iteration"] == t_full.loc["sampler=adaptive"].loc[reached, "iteration"]).all()
    assert (pd.read_csv(cut / "runs.csv")["iteration"] == 50).all()
    curves = pd.read_csv(cut / "curves.csv")
    assert curves["iteration"].max() <= 50
    assert "read up to iteration 50" in (cut / "report.md").read_text()


@pytest.mark.parametrize("value", ["0", "-3"])
def test_a_budget_below_one_iteration_is_refused_in_one_line(tmp_path, value, capsys):
    sweep = make_speedup_sweep(tmp_path, n_seeds=2)
    assert main([str(sweep), "--max-iteration", value, "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"error: --max-iteration must be >= 1, got {value}" and not (tmp_path / "r").exists()


def test_runs_on_different_evaluation_schedules_are_read_at_or_before_the_common_budget_and_the_report_says_so(
        tmp_path):
    # A stops at 60 evaluating every 20 iterations, B at 55 evaluating every 5: the common budget is 55, where A
    # has no evaluation, so A is read at 40 (never past the budget) and the text names both iterations.
    sweep = tmp_path / "schedules"
    mastery = [10.0, 30.0, 50.0, None]
    write_run(sweep / "sampler=uniform" / "seed=0", sampler="uniform", seed=0, overrides=["sampler=uniform"],
              mastery=mastery, last_iteration=60, eval_every=20)
    write_run(sweep / "sampler=adaptive" / "seed=0", sampler="adaptive", seed=0, overrides=["sampler=adaptive"],
              mastery=mastery, last_iteration=55, eval_every=5)
    out = build_report(sweep, tmp_path / "rep", ReportOptions(n_resamples=20))
    md = (out / "report.md").read_text()
    assert ("iteration 55, the last iteration every run's evaluations reach; each run is read at its last "
            "evaluation at or before it: iterations 40, 55") in md
    assert "iteration 55, the last evaluation every run has" not in md
    # A's final failure is its evaluation at 40: bin 2 (mastered at 50) still fails there.
    summary = pd.read_csv(out / "summary.csv").set_index(["arm", "metric"])
    evals = pd.read_parquet(sweep / "sampler=uniform" / "seed=0" / "eval.parquet")
    at_40 = evals[evals["iteration"] == 40]
    assert summary.loc[("sampler=uniform", "final_failure"), "mean"] == pytest.approx(
        at_40["failures"].sum() / at_40["start_episodes"].sum())
    # The same schedules with B also stopping at 60: every run has an evaluation at 60, the usual words.
    write_run(sweep / "sampler=adaptive" / "seed=0", sampler="adaptive", seed=0, overrides=["sampler=adaptive"],
              mastery=mastery, last_iteration=60, eval_every=5)
    md = (build_report(sweep, tmp_path / "rep2", ReportOptions(n_resamples=20)) / "report.md").read_text()
    assert "iteration 60, the last evaluation every run has" in md and "each run is read at" not in md


def test_a_library_run_past_the_common_budget_also_gets_its_clip_count_at_its_own_last_evaluation(tmp_path):
    # Clips walk (bins 0, 1) and jump (2, 3); failure 0.02 once a bin is mastered, 0.5 before. Uniform evaluates
    # every 20 to 60, adaptive every 5 to 55: at the common budget uniform is read at 40 (jump's bin 2, mastered
    # at 50, still fails: 1 clip at 95%); at its own last evaluation, 60, both clips pass.
    sweep = tmp_path / "library"
    clips, mastery = ["walk", "walk", "jump", "jump"], [10.0, 30.0, 50.0, 58.0]
    write_run(sweep / "sampler=uniform" / "seed=0", sampler="uniform", seed=0, overrides=["sampler=uniform"],
              mastery=mastery, last_iteration=60, eval_every=20, clips=clips)
    write_run(sweep / "sampler=adaptive" / "seed=0", sampler="adaptive", seed=0, overrides=["sampler=adaptive"],
              mastery=mastery, last_iteration=55, eval_every=5, clips=clips)
    out = build_report(sweep, tmp_path / "rep", ReportOptions(n_resamples=20))
    md = (out / "report.md").read_text()
    assert ("- `sampler=uniform`: 1 of 2 clips at final success >= 0.95 (failure <= 0.05); at each seed's own last "
            "evaluation: 2 (seed 0, iteration 60).") in md
    assert "- `sampler=adaptive`: 1 of 2 clips at final success >= 0.95 (failure <= 0.05)." in md  # ends at 55
    table = pd.read_csv(out / "clip_failure.csv", dtype={"iterations": str, "end_iterations": str}
                        ).set_index(["arm", "clip"])
    assert table.loc[("sampler=uniform", "jump"), ["iterations", "end_iterations"]].tolist() == ["40", "60"]
    assert float(table.loc[("sampler=uniform", "jump"), "per_seed_at_end"]) == pytest.approx(0.02)
    assert table.loc[("sampler=adaptive", "jump"), ["iterations", "end_iterations"]].tolist() == ["55", "55"]
