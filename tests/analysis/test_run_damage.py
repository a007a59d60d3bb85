"""Run folders that would have reached a report as if valid (issue 47): one seed launched several times,
a damaged or hand-edited table, a seed written as an interpolation. Each is counted once, refused in
one line naming the file and column, or read with the value the run trained with."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import yaml

from analysis import AnalysisError
from analysis.load import load_runs, load_table
from analysis.report import main as report_main
from tests.analysis.synthetic_runs import write_run

MASTERY = [10.0, 20.0, 30.0, 40.0]


def test_one_seed_launched_five_times_counts_once_and_says_so(tmp_path, caplog):
    for k in range(5):
        write_run(tmp_path / "runs" / "adaptive" / f"2026-01-0{k + 1}_00-00-00", sampler="adaptive", seed=0,
                  overrides=[], mastery=MASTERY, seconds_per_iteration=1.0 + k / 10, last_iteration=40 + k)
        write_run(tmp_path / "runs" / "uniform" / f"2026-01-0{k + 1}_00-00-00", sampler="uniform", seed=0,
                  overrides=["sampler=uniform"], mastery=MASTERY, seconds_per_iteration=1.0 + k / 10)
    runs = load_runs(tmp_path / "runs")
    used = runs[runs["included"]]
    assert sorted(used["arm"]) == ["adaptive", "uniform"] and set(used["seed"]) == {0}
    kept = used.set_index("arm")["run_dir"]
    assert kept["adaptive"].endswith("2026-01-05_00-00-00")  # trained longest
    left_out = runs[~runs["included"]]
    assert len(left_out) == 8 and left_out["problem"].str.contains("seed 0 of arm .* again", regex=True).all()
    assert sum("seed 0 appears in 5 runs; counted once" in r.getMessage() for r in caplog.records) == 2


def _run(tmp_path):
    return write_run(tmp_path / "run", sampler="uniform", seed=0, overrides=[], mastery=MASTERY)


def _damage(run, table, change):
    path = run / f"{table}.parquet"
    df = pd.read_parquet(path)
    change(df) if callable(change) else None
    (df if not isinstance(change, pd.DataFrame) else change).to_parquet(path, index=False)


@pytest.mark.parametrize("table, change, column, words", [
    ("eval", lambda d: d.__setitem__("failure_rate", 5.0), "failure_rate", "holds 5.0, outside [0, 1]"),
    ("eval", lambda d: d.loc.__setitem__((d.index[-1], "bin"), 99), "bin", "holds 99, but the run has 4 bins"),
    ("eval", lambda d: d.__setitem__("bin_end_s", d["bin_end_s"] * 3), "bin_end_s", "outside [0, 8]"),
    ("eval", lambda d: d.__setitem__("failure_rate", np.nan), "failure_rate", "has no finite value"),
    ("eval", lambda d: d.__setitem__("iteration", d["iteration"].astype(str) + "x"), "iteration", "'0x', not numbers"),
    ("eval", lambda d: d.__setitem__("visits", -1), "visits", "holds -1, outside >= 0"),
    ("train_metrics", lambda d: d.__setitem__("iteration", d["iteration"] + 0.5), "iteration", "not a whole number"),
    ("train_metrics", lambda d: d.__setitem__("mean_reward", np.nan), "mean_reward", "episodes ended"),
    ("sampler", lambda d: d.__setitem__("probability", 0.5), "probability", "sums to 2"),
    # issue 77: invariants across columns and rows
    ("eval", lambda d: d.__setitem__("failures", d["visits"] + 1), "failures", "more than visits"),
    ("eval", lambda d: d.__setitem__("mpkpe_mm", -1.0), "mpkpe_mm", "negative"),
    ("train_metrics", lambda d: d.__setitem__("iteration", 0), "iteration", "not increasing from row to row"),
    ("train_metrics", lambda d: d.__setitem__("env_steps", d["env_steps"][::-1].to_numpy()), "env_steps",
     "not increasing"),
    # issue 77's second round: a rate its counts contradict (28 bins read as mastered, not 4); time going back
    ("eval", lambda d: d.__setitem__("failure_rate", 0.0), "failure_rate", "not failures / visits"),
    ("train_metrics", lambda d: d.__setitem__("wall_time_s", d["wall_time_s"][::-1].to_numpy()), "wall_time_s",
     "decreasing"),
])
def test_a_table_out_of_range_is_one_line_naming_file_and_column(tmp_path, capsys, table, change, column, words):
    run = _run(tmp_path)
    _damage(run, table, change)
    with pytest.raises(AnalysisError, match=f"{table}.parquet: column {column}"):
        load_table(load_runs(run), table)
    assert report_main([str(run)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:") and f"{table}.parquet: column {column}" in err[0]
    assert words in err[0]
    assert not (run / "report" / "report.md").exists()


@pytest.mark.parametrize("table", ["eval", "train_metrics"])
def test_a_table_with_no_rows_is_refused(tmp_path, capsys, table):
    run = _run(tmp_path)
    path = run / f"{table}.parquet"
    pd.read_parquet(path).iloc[:0].to_parquet(path, index=False)
    assert report_main([str(run)]) == 2
    assert f"{table}.parquet: has no rows" in capsys.readouterr().err


def test_an_interpolated_seed_reads_the_value_the_run_trained_with(tmp_path, capsys):
    """`seed=${oc.env:SLURM_ARRAY_TASK_ID}` (a run recorded before bmimic recorded values) took the
    report down with a traceback: the seed comes from resolved_config.json, else the run is left out."""
    run = _run(tmp_path)
    config = run / ".hydra" / "config.yaml"
    cfg = yaml.safe_load(config.read_text())
    config.write_text(yaml.safe_dump({**cfg, "seed": "${oc.env:SLURM_ARRAY_TASK_ID}"}))
    runs = load_runs(run)
    assert not runs["included"].any() and "seed '${oc.env:SLURM_ARRAY_TASK_ID}' is not a whole number" in runs[
        "problem"][0]
    (run / "resolved_config.json").write_text(json.dumps({**cfg, "seed": 3}))
    runs = load_runs(run)
    assert runs["included"].all() and runs["seed"].tolist() == [3]
    assert report_main([str(run)]) == 0


def test_a_copy_with_its_seed_edited_is_refused_not_counted_as_a_second_seed(tmp_path, capsys):
    """Issue 77: a run copied and its seed edited (config and overrides) counted as a second seed, its tables
    and wall times identical. Two runs never train to the same bytes: one line naming both, exit 2."""
    import shutil

    first = write_run(tmp_path / "runs" / "uniform" / "seed=0", sampler="uniform", seed=0, overrides=[],
                      mastery=MASTERY)
    copy = tmp_path / "runs" / "uniform" / "seed=1"
    shutil.copytree(first, copy)
    for name in ("config.yaml", "overrides.yaml"):
        path = copy / ".hydra" / name
        path.write_text(path.read_text().replace("seed: 0", "seed: 1").replace("seed=0", "seed=1"))
    assert yaml.safe_load((copy / ".hydra" / "config.yaml").read_text())["seed"] == 1
    assert report_main([str(tmp_path / "runs"), "--out", str(tmp_path / "report")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error:"), err
    assert str(copy) in err[0] and str(first) in err[0] and "differ only in their seed" in err[0]
    assert not (tmp_path / "report").exists()
    # the sweep index compares nothing: it lists the copy, left out with the reason
    runs = load_runs(tmp_path / "runs", compare=False)
    assert runs.set_index("seed").loc[1, "problem"].startswith(f"its tables are byte-identical to {first}'s")
    assert runs["included"].tolist() == [True, False]
    # a real second seed (other tables) and a byte-identical copy (counted once) are read as before
    write_run(copy, sampler="uniform", seed=1, overrides=[], mastery=MASTERY)
    shutil.copytree(first, tmp_path / "runs" / "uniform" / "seed=0_copy")
    runs = load_runs(tmp_path / "runs")
    assert sorted(runs.loc[runs["included"], "seed"]) == [0, 1]
    assert runs["problem"].fillna("").str.contains("byte-identical to .*counted once", regex=True).sum() == 1


def test_a_path_with_too_many_folders_to_search_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    """Found by the generated harness at 500 examples (issue 77): `bmimic-report RUN /` walked the whole file
    system for minutes. A search of more than MAX_SEARCHED_FOLDERS folders is one line instead."""
    from analysis import run_files

    monkeypatch.setattr(run_files, "MAX_SEARCHED_FOLDERS", 20)
    for k in range(30):
        (tmp_path / "big" / f"d{k}").mkdir(parents=True)
    run = _run(tmp_path)
    assert report_main([str(run), str(tmp_path / "big"), "--out", str(tmp_path / "report")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {tmp_path / 'big'}: more than 20 folders to search for runs; name the study's sweep "
                   "folder or its run folders"]
    assert not (tmp_path / "report").exists()


@pytest.mark.parametrize("value", ["Infinity", "NaN", "1e30", "-3", "2.5"])
def test_a_status_iteration_that_is_not_a_whole_number_reads_as_unknown(tmp_path, value):
    """Found by the generated harness at 500 examples (issue 77): status.json's `"iteration": Infinity` failed
    the runs frame's integer column (OverflowError) in report and index, NaN the report's header."""
    run = _run(tmp_path)
    status = run / "status.json"
    status.write_text(json.dumps({"status": "done", "error": None, "iteration": 0}).replace("0}", f"{value}}}"))
    runs = load_runs(run)
    assert runs["iteration"].isna().all() and runs["included"].all()
    assert report_main([str(run), "--out", str(tmp_path / "report")]) == 0
