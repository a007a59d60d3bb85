"""Outputs written into a folder the user names never replace files bmimic did not write (issue 77): a
report's report.md and runs.csv, an evaluation's tables and summary. A report or evaluation of bmimic's own
in that folder is replaced as before."""

from __future__ import annotations

import json

import pytest

from analysis.report import main as report_main
from bmimic.eval import EarlierEvaluationError, keep_earlier
from tests.analysis.synthetic_runs import write_run


@pytest.mark.parametrize("name", ["report.md", "runs.csv"])
def test_report_refuses_a_users_file_of_its_name(tmp_path, capsys, name):
    run = write_run(tmp_path / "run", sampler="uniform", seed=0, overrides=[], mastery=[10.0, 20.0, 30.0, 40.0])
    out = tmp_path / "mine"
    out.mkdir()
    (out / name).write_text("my notes\n")
    assert report_main([str(run), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and f"its {name} is not a bmimic report's" in err[0]
    assert sorted(p.name for p in out.iterdir()) == [name] and (out / name).read_text() == "my notes\n"
    (out / name).unlink()
    assert report_main([str(run), "--out", str(out)]) == 0  # an empty folder, then its own report again
    assert report_main([str(run), "--out", str(out)]) == 0


def test_evaluation_refuses_a_users_files_of_its_names(tmp_path):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "eval_summary.json").write_text(json.dumps({"my": "numbers"}))
    with pytest.raises(EarlierEvaluationError, match="not a bmimic evaluation's summary"):
        keep_earlier(out, tmp_path, force=True)  # --force replaces bmimic's evaluations, never a user's file
    (out / "eval_summary.json").unlink()
    (out / "eval_bins.parquet").write_text("mine")
    with pytest.raises(EarlierEvaluationError, match="no evaluation's summary beside it"):
        keep_earlier(out, tmp_path, force=False)
    (out / "eval_bins.parquet").unlink()
    (out / "eval_summary.json").write_text(json.dumps({"checkpoint": "model_2.pt", "eval_success_rate": 0.5}))
    keep_earlier(out, tmp_path, force=False)  # an earlier evaluation of bmimic's: replaced, with a warning
