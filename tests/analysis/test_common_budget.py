"""`--max-iteration`: runs that trained further are read as if they had stopped at the common budget
(the design-choice study compares 3000-iteration runs with 1500-iteration ones)."""

from __future__ import annotations

import pandas as pd
import pytest

from analysis.report import build_report, main
from analysis.tables import ReportOptions
from tests.analysis.synthetic_runs import make_speedup_sweep


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
