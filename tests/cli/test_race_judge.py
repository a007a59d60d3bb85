"""bmimic.runs.race_judge and `bmimic.race --native-whole-clip`: the judge's scheduling with a planted child
(a stand-in for sim2sim that writes a known result), the race placing results at their checkpoints' evaluations,
the refusals, and one tiny native race on the CPU, end to end."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from bmimic.race import main, parse_args, race_overrides
from bmimic.runs.race_judge import NativeJudge, native_summary_path
from bmimic.runs.race_record import WHOLE_CLIP_METRIC, Race, Threshold
from tests.conftest import TINY

PLANTED = {200: 0.5, 400: 0.92, 600: 0.97, 800: 0.99}
"""Robust whole-clip success the stand-in child reports per checkpoint iteration."""


def _stand_in(onnx: Path, out: Path) -> list[str]:
    """A child that writes what sim2sim would: the planted success of its checkpoint, in `out`."""
    it = int(onnx.stem.rsplit("_", 1)[1])
    summary = {"iteration": it, "conditions": {"robust": {"success_rate": PLANTED.get(it, 0.0)}}}
    code = (f"import json, os; os.makedirs({str(out)!r}, exist_ok=True); "
            f"open(os.path.join({str(out)!r}, 'eval_summary.json'), 'w').write({json.dumps(json.dumps(summary))})")
    return [sys.executable, "-c", code]


def _export(run: Path, it: int) -> None:
    (run / "checkpoints").mkdir(parents=True, exist_ok=True)
    (run / "checkpoints" / f"motion_policy_{it}.onnx").write_bytes(b"planted")


def _wait(judge: NativeJudge) -> None:
    while judge.running is not None and judge.running[1].poll() is None:
        time.sleep(0.05)


def test_the_judge_starts_when_the_windows_open_takes_the_newest_checkpoint_and_hands_back_results(tmp_path):
    run = tmp_path / "run"
    _export(run, 200)
    judge = NativeJudge(workers=2, rollouts=4, after_success=0.95, command=_stand_in)
    assert judge.poll(run, 0.90) == [] and judge.running is None  # windows not at 95%: nothing starts
    _export(run, 400)
    assert judge.poll(run, 0.96) == [] and judge.started == [400]  # the newest, not the oldest
    _wait(judge)
    _export(run, 600)
    _export(run, 800)
    assert judge.poll(run, 0.50) == [(400, 0.92)]  # opened for good: a later low window does not close it
    assert judge.started == [400, 800]
    _wait(judge)
    assert judge.poll(run, 0.99) == [(800, 0.99)] and judge.running is None  # nothing newer than 800
    assert json.loads(native_summary_path(run, 800).read_text())["iteration"] == 800
    assert judge.judge_now(run, 600) == 0.97 and judge.judge_now(run, 1000) is None  # no export of 1000


def test_a_failed_child_is_no_result_and_close_stops_a_running_one(tmp_path):
    run = tmp_path / "run"
    _export(run, 200)
    judge = NativeJudge(workers=1, after_success=0.0, command=lambda onnx, out: [sys.executable, "-c", "raise SystemExit(3)"])
    judge.poll(run, 0.0)
    _wait(judge)
    assert judge.poll(run, 0.0) == [] and (run / "sim2sim" / "race_native_judge.log").exists()
    _export(run, 400)
    slow = NativeJudge(workers=1, after_success=0.0, command=lambda onnx, out: [sys.executable, "-c", "import time; time.sleep(60)"])
    slow.poll(run, 0.0)
    proc = slow.running[1]
    slow.close()
    assert proc.poll() is not None and slow.running is None


class _Planted:
    """A judge whose results are planted per evaluation (what arrives after which evaluation)."""

    def __init__(self, arrivals: dict[int, list[tuple[int, float]]]):
        self.arrivals, self.iteration = arrivals, 0

    def poll(self, run_dir, window_success):
        return self.arrivals.get(self.iteration, [])


def test_the_race_times_a_judged_threshold_at_its_checkpoint_and_stops_when_the_result_arrives():
    race = Race([Threshold("eval_success_rate", 0.9), Threshold(WHOLE_CLIP_METRIC, 0.9)], budget_s=1e9,
                sustain=2, launch_unix_s=0.0)
    # checkpoints 200 and 400 judged 0.92 and 0.95; their results arrive one evaluation later each
    race.judge = judge = _Planted({300: [(200, 0.92)], 500: [(400, 0.95)]})
    stopped_at = None
    for it in range(100, 700, 100):
        judge.iteration = it
        trainer = SimpleNamespace(run_dir="RUN", learn_started_unix_s=100.0, eval_time_s=0.0,
                                  progress=SimpleNamespace(iteration=it, env_steps=10 * it, wall_time_s=0.1 * it))
        if race.on_evaluation(trainer, {"eval_success_rate": 0.96}, now=100.0 + it / 10):
            stopped_at = it
            break
    assert stopped_at == 500  # when the second result came in
    whole = race.to_json({}, None)["thresholds"][1]
    assert (whole["status"], whole["iteration"], whole["wall_from_launch_s"]) == ("reached", 200, 120.0)
    judged = {e["iteration"]: e.get(WHOLE_CLIP_METRIC) for e in race.evaluations}
    assert judged == {100: None, 200: 0.92, 300: None, 400: 0.95, 500: None}
    assert race.evaluations[1]["whole_clip_native"] is True


def test_native_options_are_checked_and_set_the_judges_cadence():
    for argv, _message in ((["--native-whole-clip", "0"], "must be >= 1 worker"),
                          (["--native-whole-clip", "2", "--no-whole-clip"], "contradict")):
        with pytest.raises(SystemExit) as e:
            parse_args(argv)
        assert e.value.code == 2
    native = race_overrides(["seed=1"], native=True)
    assert "ppo.save_interval=200" in native and "eval.whole_clip.rollouts=128" in native
    assert not any(a.startswith(("eval.whole_clip.max_share", "eval.whole_clip.at_end")) for a in native)
    assert race_overrides(["ppo.save_interval=400"], native=True).count("ppo.save_interval=400") == 1


def test_a_judged_checkpoint_must_fall_on_an_evaluation(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["--native-whole-clip", "1", *TINY, "eval.every_iters=2", "ppo.save_interval=3",
                 f"hydra.run.dir={tmp_path / 'run'}", "logger=none"]) == 2
    # (Warp's own CUDA notice may precede it when this is the first test of its process to import Warp)
    err = [line for line in capsys.readouterr().err.strip().splitlines() if not line.startswith("Warp ")]
    assert len(err) == 1 and "ppo.save_interval (3) must be a multiple of eval.every_iters (2)" in err[0]
    assert not (tmp_path / "run" / "checkpoints").exists()


@pytest.mark.slow
def test_a_tiny_native_race_judges_its_checkpoints_beside_training(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    args = ["--native-whole-clip", "1", "--success", "0.01", "--mpkpe-rel-mm", "1000", "--whole-clip-success", "0.5",
            *[a for a in TINY if not a.startswith(("max_iterations", "motion"))], "motion=easy_only", "motion.duration_s=7",
            "max_iterations=4", "eval.every_iters=1", "ppo.save_interval=1", "eval.whole_clip.rollouts=2",
            "eval.whole_clip.after_success=null", f"hydra.run.dir={run}", "logger=none"]
    assert main(args) == 0
    record = json.loads((run / "race.json").read_text())
    assert record["config"]["native_whole_clip_workers"] == 1
    final = record["final_whole_clip"]  # the final policy, judged after the clock
    assert final["native"] is True and final["iteration"] == record["evaluations"][-1]["iteration"]
    assert 0.0 <= final[WHOLE_CLIP_METRIC] <= 1.0 and native_summary_path(run, final["iteration"]).is_file()
    for e in record["evaluations"]:  # whatever came back during the race sits at its checkpoint, in [0, 1]
        if WHOLE_CLIP_METRIC in e:
            assert e["whole_clip_native"] is True and 0.0 <= e[WHOLE_CLIP_METRIC] <= 1.0
            assert native_summary_path(run, e["iteration"]).is_file()
    assert not any(p.name == "whole_clip.parquet" for p in run.iterdir())  # MuJoCo-Warp never paused training


def test_the_judge_sees_the_checkpoint_of_the_evaluation_it_follows(tmp_path, monkeypatch):
    """The stopping rule runs after the iteration's checkpoint, so the judge polled after evaluation k finds
    motion_policy_k.onnx: it starts on the policy whose windows opened it, not one save interval behind."""
    monkeypatch.chdir(tmp_path)
    run, seen = tmp_path / "run", []
    real_poll = NativeJudge.poll

    def poll(self, run_dir, window_success):
        seen.append(sorted(int(p.stem.rsplit("_", 1)[1]) for p in Path(run_dir, "checkpoints").glob("motion_policy_*.onnx")))
        return real_poll(self, run_dir, window_success)

    monkeypatch.setattr(NativeJudge, "poll", poll)
    monkeypatch.setattr(NativeJudge, "sim2sim_command", lambda self, onnx, out: _stand_in(onnx, out))
    args = ["--native-whole-clip", "1", "--success", "0.01", "--mpkpe-rel-mm", "1000", "--whole-clip-success", "0.5",
            *[a for a in TINY if not a.startswith("max_iterations")], "max_iterations=3", "eval.every_iters=1",
            "ppo.save_interval=1", "eval.whole_clip.rollouts=2", "eval.whole_clip.after_success=null",
            f"hydra.run.dir={run}", "logger=none"]
    assert main(args) == 0
    # evaluations after iterations 1, 2 and 3; the loop checkpoints every iteration but the last (the job then does)
    assert seen[:2] == [[1], [1, 2]]
