"""RunRecord (the training tables: rows, resume truncation, flushes, metrics.json) and the loop's Schedule."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from bmimic.runs.folder import EVAL_TABLES, SIM2SIM_GAP, table_path
from bmimic.runs.record import RunRecord, RunRecordError, metrics, write_evaluation
from bmimic.runs.schema import FINAL_METRICS, RUN_METRICS
from bmimic.training.schedule import Schedule


def _record(run_dir, iterations, enabled=True):
    r = RunRecord(run_dir, enabled=enabled)
    for it in range(iterations):
        r.append("train_metrics", {"iteration": it, "failure_rate": 0.5})
        r.append("eval", pd.DataFrame({"iteration": [it + 1] * 2, "bin": [0, 1]}))
    return r


def test_flush_writes_every_table_with_rows_and_resume_keeps_the_completed_iterations(tmp_path):
    _record(tmp_path, 4).flush()
    assert len(pd.read_parquet(table_path(tmp_path, "train_metrics"))) == 4
    assert not table_path(tmp_path, "sampler").exists()  # no rows, no file
    resumed = RunRecord(tmp_path)
    resumed.truncate(2)  # a checkpoint after 2 iterations: training rows 0-1, evaluations after 1 and 2
    assert [r["iteration"] for r in resumed.rows("train_metrics")] == [0, 1]
    assert resumed.last_iteration("eval") == 2 and resumed.last_iteration("train_metrics") == 1
    assert resumed.last_iteration("clip_eval") is None


def test_a_record_that_is_not_enabled_writes_nothing(tmp_path):
    _record(tmp_path, 2, enabled=False).flush()
    assert list(tmp_path.iterdir()) == []


def test_a_whole_table_is_written_at_once_and_a_row_table_is_refused(tmp_path):
    table = pd.DataFrame({"iteration": [3, 3], "bin": [0, 1]})
    RunRecord(tmp_path, enabled=False).write_table("eval_robust", table)
    assert list(tmp_path.iterdir()) == []
    RunRecord(tmp_path).write_table("eval_robust", table)
    pd.testing.assert_frame_equal(pd.read_parquet(table_path(tmp_path, "eval_robust")), table)
    with pytest.raises(RunRecordError, match="flush"):
        RunRecord(tmp_path).write_table("eval", table)


def test_an_evaluation_is_written_whole_with_the_summary_last(tmp_path, monkeypatch):
    import bmimic.runs.atomic_io as atomic_io

    written, write = [], atomic_io.atomic_write
    monkeypatch.setattr(atomic_io, "atomic_write",
                        lambda path, w: (written.append(path.name), write(path, w))[1])
    frame = pd.DataFrame({"bin": [0, 1], "segment": ["", "walk"]})
    out = write_evaluation(tmp_path / "sim2sim" / "bmimic_g1" / "model_3", frame, frame, frame,
                           {"label": "model_3"}, gap=frame)
    assert written == [SIM2SIM_GAP, *EVAL_TABLES] and sorted(p.name for p in out.iterdir()) == sorted(written)
    pd.testing.assert_frame_equal(pd.read_csv(out / EVAL_TABLES[2], keep_default_na=False), frame)
    written.clear()
    write_evaluation(tmp_path / "eval" / "model_3", frame, frame, frame, {"label": "model_3"})
    assert written == list(EVAL_TABLES)


@pytest.mark.parametrize("damage", ["garbage", "no_iteration"])
def test_a_damaged_table_stops_the_resume_with_its_own_error(tmp_path, damage):
    path = table_path(tmp_path, "eval")
    if damage == "garbage":
        path.write_bytes(b"not parquet")
    else:
        pd.DataFrame({"bin": [0]}).to_parquet(path)
    with pytest.raises(RunRecordError, match="move it aside"):
        RunRecord(tmp_path).truncate(3)


def test_metrics_json_in_the_schemas_order():
    final = {"eval_failure_rate": 0.25, "eval_success_rate": 0.75, "eval_mpkpe_mm": 30.0,
             "eval_bins_mastered_frac": 0.5, "eval_broken": 0.0}
    run = {k: i for i, k in enumerate(RUN_METRICS)}
    out = metrics(final, {"final_robust_eval_failure_rate": 0.5}, run)
    assert list(out) == [*FINAL_METRICS, "final_robust_eval_failure_rate", *RUN_METRICS]
    assert out["final_eval_failure_rate"] == 0.25 and out["num_envs"] == RUN_METRICS.index("num_envs")
    with pytest.raises(RunRecordError, match="device"):
        metrics(final, {}, {k: v for k, v in run.items() if k != "device"})
    assert math.isnan(metrics(dict.fromkeys(final, math.nan), {}, run)["final_eval_mpkpe_mm"])


def test_the_schedule_evaluates_every_k_and_never_checkpoints_the_last_iteration():
    s = Schedule(eval_every=3, save_every=2)
    assert [i for i in range(1, 10) if s.evaluates(i)] == [3, 6, 9]
    assert [i for i in range(1, 7) if s.checkpoints(i, last=i == 6)] == [2, 4]
    assert not any(Schedule(0, 1).evaluates(i) for i in range(1, 5))
