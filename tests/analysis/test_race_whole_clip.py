"""analysis.race_whole_clip: a race's whole-clip finish line decided afterwards from its evaluated checkpoints,
on planted race records (written by the race's own Race object) and planted whole-clip summaries."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import pytest

from analysis.race_whole_clip import main, race_whole_clip
from bmimic.runs.atomic_io import atomic_write_json
from bmimic.runs.race_record import WHOLE_CLIP_METRIC, Race, Threshold

SUCCESS = {100: 0.80, 200: 0.93, 300: 0.96, 400: 0.99, 500: 0.995, 600: 0.996}
"""Window success of the planted race at each evaluation (every 100 iterations, 10 s apart)."""


def _race_dir(tmp_path: Path, own_whole_clip: dict[int, float] | None = None) -> Path:
    """A run folder whose race.json the race's Race wrote: windows every 100 iterations from 110 s after
    launch, whole-clip thresholds 0.9 and 0.95 (sustain 2), measured in the race only at `own_whole_clip`."""
    race = Race([Threshold("eval_success_rate", 0.9), Threshold(WHOLE_CLIP_METRIC, 0.9),
                 Threshold(WHOLE_CLIP_METRIC, 0.95)], budget_s=1e9, sustain=2, launch_unix_s=0.0)
    for it, success in SUCCESS.items():
        trainer = SimpleNamespace(run_dir="RUN", learn_started_unix_s=100.0, eval_time_s=0.0,
                                  progress=SimpleNamespace(iteration=it, env_steps=1000 * it, wall_time_s=0.1 * it))
        summary = {"eval_success_rate": success, **({WHOLE_CLIP_METRIC: own_whole_clip[it]}
                                                    if own_whole_clip and it in own_whole_clip else {})}
        race.on_evaluation(trainer, summary, now=100.0 + it / 10)
    run = tmp_path / "run"
    run.mkdir()
    atomic_write_json(run / "race.json", race.to_json({"overrides": []}, None))  # as bmimic.race writes it
    return run


def _checkpoint(run: Path, it: int, success: float | None, native: bool = False) -> Path:
    folder = run / ("sim2sim/bmimic_g1" if native else "eval") / f"model_{it}" / "whole_clip"
    folder.mkdir(parents=True)
    if native:
        data = {"iteration": it, "conditions": {"nominal": {"success_rate": 1.0},
                                                **({"robust": {"success_rate": success}} if success is not None else {})}}
        path = folder / "eval_summary.json"
    else:
        data = {"iteration": it, **({WHOLE_CLIP_METRIC: success} if success is not None else {})}
        path = folder / "whole_clip_summary.json"
    path.write_text(json.dumps(data))
    return path


def _status(record: dict) -> list[tuple]:
    return [(t["threshold"], t["status"], t.get("iteration"), t.get("wall_from_launch_s")) for t in record["thresholds"]]


@pytest.mark.parametrize("native", [False, True])
def test_checkpoints_decide_the_finish_line_by_the_races_own_rule_on_its_clock(tmp_path, native):
    run = _race_dir(tmp_path)
    before = json.loads((run / "race.json").read_text())
    assert [t["status"] for t in before["thresholds"]] == ["reached", "censored", "censored"]
    for it, success in ((200, 0.50), (400, 0.92), (600, 0.96)):
        _checkpoint(run, it, success, native)
    record = race_whole_clip(run, native=native)
    # 0.9: held at 400 and 600 (two in a row that measured it), timed at 400 = 140 s from launch;
    # 0.95: met once (600), not sustained; the window threshold is the race's own (200, 120 s).
    assert _status(record) == [(0.9, "reached", 200, 120.0), (0.9, "reached", 400, 140.0), (0.95, "censored", None, None)]
    added = {e["iteration"]: e[WHOLE_CLIP_METRIC] for e in record["evaluations"] if WHOLE_CLIP_METRIC in e}
    assert added == {200: 0.50, 400: 0.92, 600: 0.96}
    assert all(e.get("whole_clip_after_the_race") for e in record["evaluations"] if WHOLE_CLIP_METRIC in e)
    assert ("native MuJoCo" if native else "MuJoCo-Warp") in record["whole_clip_source"]
    assert json.loads((run / "race.json").read_text()) == before  # the race's own record is left as it was


def test_the_races_own_whole_clip_measurement_stands(tmp_path):
    run = _race_dir(tmp_path, own_whole_clip={400: 0.5})
    _checkpoint(run, 400, 0.99)
    _checkpoint(run, 500, 0.99)
    record = race_whole_clip(run)
    at = {e["iteration"]: e for e in record["evaluations"]}
    assert at[400][WHOLE_CLIP_METRIC] == 0.5 and "whole_clip_after_the_race" not in at[400]
    assert at[500][WHOLE_CLIP_METRIC] == 0.99 and at[500]["whole_clip_after_the_race"] is True
    assert _status(record)[1] == (0.9, "censored", None, None)  # 0.5 then 0.99: one in a row


def test_nominal_only_summaries_are_skipped_and_the_json_is_written(tmp_path, capsys):
    run = _race_dir(tmp_path)
    _checkpoint(run, 300, None)
    _checkpoint(run, 400, 0.97)
    _checkpoint(run, 500, 0.98)
    out = tmp_path / "bench" / "race.json"
    assert main([str(run), "--json", str(out)]) == 0
    record = json.loads(out.read_text())
    assert _status(record)[1:] == [(0.9, "reached", 400, 140.0), (0.95, "reached", 400, 140.0)]
    printed = capsys.readouterr().out
    assert "robust whole-clip success >= 0.95: iteration 400, 140 s from launch" in printed
    assert "whole clips at 2 evaluations: 400: 0.97, 500: 0.98" in printed


@pytest.mark.parametrize("plant, message", [
    (lambda run: None, "no robust whole-clip evaluation of a checkpoint under eval/*/whole_clip"),
    (lambda run: _checkpoint(run, 250, 0.9), "iterations 250 have no evaluation in the race's record"),
    (lambda run: (_checkpoint(run, 400, 0.9), (run / "eval/latest/whole_clip").mkdir(parents=True),
                  (run / "eval/latest/whole_clip/whole_clip_summary.json").write_text(
                      json.dumps({"iteration": 400, WHOLE_CLIP_METRIC: 0.7}))),
     "two robust whole-clip results for iteration 400 (0.7 and 0.9)"),
    (lambda run: _checkpoint(run, 400, 1.5), "robust whole-clip success is 1.5, not a fraction"),
])
def test_bad_input_is_one_line_and_writes_nothing(tmp_path, capsys, plant, message):
    run = _race_dir(tmp_path)
    plant(run)
    out = tmp_path / "out.json"
    assert main([str(run), "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and message in err and "\n" not in err
    assert not out.exists()
