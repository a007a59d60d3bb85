"""`python -m bmimic.race`: the stopping rule on planted evaluation sequences (sustained thresholds,
the first of the sustained evaluations timed, censoring at the wall budget), refusals in one line,
one tiny end-to-end race on the CPU, and one under torchrun on 3 CPU ranks (gloo): one race, rank 0
writes it, every rank stops after the same iteration."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from types import SimpleNamespace

import pytest

from bmimic.race import WHOLE_CLIP_METRIC, Race, Threshold, parse_args, race_overrides
from tests.conftest import RANKS_GROUP, TINY, cli_env

RANKS = 3
"""Ranks of the torchrun races: more than two, so that nothing is written for a pair only (issue 48)."""


def _trainer(iteration: int) -> SimpleNamespace:
    progress = SimpleNamespace(iteration=iteration, env_steps=1000 * iteration, wall_time_s=0.5 * iteration)
    return SimpleNamespace(run_dir="RUN", learn_started_unix_s=110.0, eval_time_s=0.1 * iteration, progress=progress)


def _race(budget_s=1e9, sustain=2):
    return Race([Threshold("eval_success_rate", 0.9), Threshold("eval_success_rate", 0.99),
                 Threshold("eval_mpkpe_rel_mm", 40.0)], budget_s, sustain, launch_unix_s=100.0)


def _feed(race, sequence, every=50):
    """Evaluations every `every` iterations, one second of wall time per iteration; returns the iteration
    at which the rule stopped training (None: it never did)."""
    for k, (success, mpkpe) in enumerate(sequence, start=1):
        it = every * k
        if race.on_evaluation(_trainer(it), {"eval_success_rate": success, "eval_mpkpe_rel_mm": mpkpe},
                              now=110.0 + it):
            return it
    return None


def test_a_threshold_counts_only_when_sustained_and_is_timed_at_its_first_evaluation():
    race = _race()
    # 0.91 at 100 is a blip (0.85 follows); 0.92 from 200 holds: 90% is reached at 200, not 100 or 250.
    stopped = _feed(race, [(0.5, 60), (0.91, 45), (0.85, 39), (0.92, 39), (0.95, 38), (0.991, 36), (0.995, 35)])
    assert stopped == 350
    at = {t.value: t.reached_at for t in race.thresholds}
    assert at[0.9]["iteration"] == 200 and at[0.9]["wall_from_launch_s"] == pytest.approx(210.0)
    assert at[0.9]["wall_from_first_iteration_s"] == pytest.approx(200.0) and at[0.9]["env_steps"] == 200_000
    assert at[40.0]["iteration"] == 150  # 39 mm from 150 on
    assert at[0.99]["iteration"] == 300
    assert race.stopped == "every threshold reached"
    assert all(line.startswith("race: ") for line in race.lines())


def test_the_wall_budget_stops_the_race_and_censors_what_was_not_reached():
    race = _race(budget_s=260.0)
    stopped = _feed(race, [(0.95, 45), (0.96, 45), (0.97, 45), (0.97, 45), (0.999, 30)])
    assert stopped == 250  # the evaluation at 250 is the first 260 s after launch
    record = race.to_json({}, None)
    status = {(t["metric"], t["threshold"]): t["status"] for t in record["thresholds"]}
    assert status == {("eval_success_rate", 0.9): "reached", ("eval_success_rate", 0.99): "censored",
                      ("eval_mpkpe_rel_mm", 40.0): "censored"}
    assert any("not reached by iteration 250" in line and "censored" in line for line in race.lines())


def test_ranks_make_one_race_clocked_from_the_earliest_launch():
    race = _race()
    race.join_ranks([104.0, 100.0, 102.5])  # rank 1 launched first
    assert race.launch_unix_s == 100.0 and race.gpus == 3
    _feed(race, [(0.95, 45)])  # evaluated at 160 s (first iteration at 110 s)
    record = race.to_json({"num_envs": 4096}, None)
    assert record["evaluations"][0]["wall_from_launch_s"] == pytest.approx(60.0)
    assert record["startup_s"] == pytest.approx(10.0)  # from the earliest launch to the first iteration
    assert (record["gpus"], record["num_envs_per_gpu"], record["num_envs_total"]) == (3, 4096, 3 * 4096)
    assert record["rank_launch_spread_s"] == pytest.approx(4.0)
    assert any("one race over 3 ranks, launched within 4.0 s" in line for line in race.lines())
    # A single process's record has none of these keys, as before torchrun races existed.
    single = _race()
    _feed(single, [(0.95, 45)])
    assert not {"gpus", "num_envs_per_gpu", "num_envs_total", "rank_launch_spread_s"} & set(
        single.to_json({"num_envs": 4096}, None))
    assert single.gpus == 1 and not any("ranks" in line for line in single.lines())


def test_whole_clip_thresholds_are_sustained_over_the_evaluations_that_measured_them():
    """Whole clips are evaluated at every other window evaluation: 0.85 at 100, 0.92 at 200, 0.93 at 300
    (window success 0.95-0.98 throughout): 90% is reached at 200, sustained at 300, where the race stops;
    the windows' evaluations in between neither break nor extend the whole-clip streak."""
    race = Race([Threshold("eval_success_rate", 0.9), Threshold(WHOLE_CLIP_METRIC, 0.9)], 1e9, 2, launch_unix_s=100.0)
    summaries = [{"eval_success_rate": 0.95}, {"eval_success_rate": 0.96, WHOLE_CLIP_METRIC: 0.85},
                 {"eval_success_rate": 0.97}, {"eval_success_rate": 0.97, WHOLE_CLIP_METRIC: 0.92},
                 {"eval_success_rate": 0.98}, {"eval_success_rate": 0.98, WHOLE_CLIP_METRIC: 0.93}]
    stops = [race.on_evaluation(_trainer(50 * k), s, now=110.0 + 50 * k) for k, s in enumerate(summaries, start=1)]
    assert stops == [False] * 5 + [True]
    windows, whole = race.thresholds
    assert windows.reached_at["iteration"] == 50 and whole.reached_at["iteration"] == 200
    assert whole.label == "robust whole-clip success >= 0.9"
    assert [e.get(WHOLE_CLIP_METRIC) for e in race.evaluations] == [None, 0.85, None, 0.92, None, 0.93]
    assert any(line.startswith("race: robust whole-clip success >= 0.9 at iteration 200") for line in race.lines())


def test_the_race_evaluates_whole_clips_by_its_share_rule_unless_told_otherwise():
    defaults = race_overrides(["seed=3"])
    assert {"eval.whole_clip.conditions=[robust]", "eval.whole_clip.rollouts=128", "eval.whole_clip.after_success=0.95",
            "eval.whole_clip.max_share=0.1", "eval.whole_clip.at_end=true"} <= set(defaults)
    assert not any(a.startswith("eval.whole_clip") for a in race_overrides(["seed=3"], whole_clip=False))
    mine = race_overrides(["eval.whole_clip.max_share=0.3"])
    assert "eval.whole_clip.max_share=0.1" not in mine and mine[-1] == "eval.whole_clip.max_share=0.3"


def test_the_final_policys_whole_clips_are_recorded_and_say_whether_the_clock_saw_them():
    race = Race([Threshold(WHOLE_CLIP_METRIC, 0.9)], budget_s=150.0, launch_unix_s=100.0)
    assert race.on_evaluation(_trainer(100), {"eval_success_rate": 0.99}, now=260.0)  # budget spent, none measured
    metrics = {"iterations": 100, "env_steps": 100_000, "final_eval_success_rate": 0.99,
               f"final_{WHOLE_CLIP_METRIC}": 0.9296875, "final_whole_clip_robust_completed": 119,
               "final_whole_clip_robust_rollouts": 128}
    race.record_final(metrics)
    assert race.final_whole_clip == {"iteration": 100, "env_steps": 100_000, WHOLE_CLIP_METRIC: 0.9296875,
                                     "whole_clip_robust_completed": 119, "whole_clip_robust_rollouts": 128,
                                     "in_clock": False}
    record = race.to_json({}, None)
    assert record["final_whole_clip"]["in_clock"] is False and record["thresholds"][0]["status"] == "censored"
    assert "race: the final policy (iteration 100): robust whole-clip success 0.93 (119 of 128 rollouts), " \
           "evaluated after the clock stopped" in race.lines()
    seen = Race([Threshold(WHOLE_CLIP_METRIC, 0.9)], budget_s=150.0, launch_unix_s=100.0)
    seen.on_evaluation(_trainer(100), {"eval_success_rate": 0.99, WHOLE_CLIP_METRIC: 0.9296875}, now=260.0)
    seen.record_final(metrics)
    assert seen.final_whole_clip["in_clock"] is True
    none = Race([Threshold("eval_success_rate", 0.9)], budget_s=150.0)
    none.record_final({"iterations": 100, "final_eval_success_rate": 0.99})  # --no-whole-clip: nothing to keep
    assert none.final_whole_clip is None and "final_whole_clip" not in none.to_json({}, None)


def test_one_evaluation_suffices_with_sustain_1():
    race = _race(sustain=1)
    assert _feed(race, [(0.995, 30)]) == 50


@pytest.mark.parametrize("argv,message", [
    (["--budget-s", "-5"], "--budget-s must be a finite number of seconds > 0"),
    (["--budget-s", "nan"], "--budget-s must be a finite number of seconds > 0"),
    (["--success", "0.9,1.5"], "--success thresholds must lie in (0, 1]"),
    (["--sustain", "0"], "--sustain must be >= 1"),
    (["--whole-clip-success", "0.9,1.5"], "--whole-clip-success thresholds must lie in (0, 1]"),
    (["-m", "seed=0,1"], "not -m"),
    (["resume=true"], "resume is not raced"),
    (["--json", "no/such/folder/r.json"], "must name a file in an existing folder"),
])
def test_bad_race_options_are_one_line_exit_2(argv, message, capsys):
    with pytest.raises(SystemExit) as e:
        parse_args(argv)
    err = capsys.readouterr().err.strip()
    assert e.value.code == 2 and err.startswith("error: ") and message in err and len(err.splitlines()) == 1


def test_race_defaults_give_way_to_the_overrides():
    assert race_overrides(["seed=3"])[:3] == ["eval.every_iters=100", "eval.episodes_per_bin=16", "run_name=race"]
    # the recommended configuration (the confirmatory test's winner), unless the command chooses its own
    assert {"env=tracking", "sampler=adaptive_hybrid"} <= set(race_overrides(["seed=3"]))
    mine = race_overrides(["sampler=uniform", "env=beyondmimic"])
    assert "sampler=adaptive_hybrid" not in mine and "env=tracking" not in mine and mine[-2:] == ["sampler=uniform",
                                                                                                  "env=beyondmimic"]
    assert "sampler=adaptive_hybrid" in race_overrides(["sampler.gamma=0.7"])  # a parameter of the race's sampler
    assert "eval.every_iters=100" not in race_overrides(["eval.every_iters=10"])
    assert race_overrides(["run_name=mine"])[-1] == "run_name=mine" and "run_name=race" not in race_overrides(
        ["run_name=mine"])


@pytest.mark.slow
def test_a_tiny_race_on_the_cpu_stops_at_its_thresholds_and_writes_its_record(tmp_path, monkeypatch):
    from bmimic.race import main

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "race.json"
    args = ["--success", "0.01", "--mpkpe-rel-mm", "1000", "--no-whole-clip", "--json", str(out),
            *[a for a in TINY if not a.startswith("max_iterations")], "max_iterations=6", "eval.every_iters=1",
            f"hydra.run.dir={tmp_path / 'run'}", "logger=none"]
    assert main(args) == 0
    record = json.loads(out.read_text())
    assert record == json.loads((tmp_path / "run" / "race.json").read_text())
    assert record["stopped"] == "every threshold reached"
    assert [t["status"] for t in record["thresholds"]] == ["reached", "reached"]
    assert [e["iteration"] for e in record["evaluations"]] == [1, 2]  # sustained over 2, then stopped
    assert record["thresholds"][0]["iteration"] == 1
    assert record["startup_s"] > 0 and 0 < record["eval_overhead"] < 1
    assert record["machine"]["device"] == "cpu" and record["config"]["eval"]["episodes_per_bin"] == 16
    assert record["config"]["env"] == "tracking"  # the race's default env group, which no override names
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["iterations"] == 2  # the run itself ended where the race stopped, checkpoint and all
    assert (tmp_path / "run" / "checkpoints" / "model_2.pt").exists()


def _torchrun_race(tmp_path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={RANKS}",
           "-m", "bmimic.race", *args]
    return subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=900, env=cli_env())


@RANKS_GROUP
@pytest.mark.slow
def test_a_torchrun_race_on_three_cpu_ranks_is_one_race_that_rank_zero_writes(tmp_path):
    run, out = tmp_path / "run", tmp_path / "race.json"
    # verbose: every rank logs, so each says where it stopped
    done = _torchrun_race(tmp_path, "--success", "0.01", "--mpkpe-rel-mm", "1000", "--no-whole-clip", "--json", str(out),
                          *[a for a in TINY if not a.startswith("max_iterations")], "max_iterations=6",
                          "eval.every_iters=1", "eval.episodes_per_bin=1", "logger=none", "verbose=true",
                          f"hydra.run.dir={run}")
    log = done.stdout + done.stderr
    assert done.returncode == 0, log[-4000:]
    record = json.loads(out.read_text())
    assert record == json.loads((run / "race.json").read_text())
    assert (record["gpus"], record["num_envs_per_gpu"], record["num_envs_total"]) == (RANKS, 2, 2 * RANKS)
    assert record["stopped"] == "every threshold reached"
    assert [e["iteration"] for e in record["evaluations"]] == [1, 2]  # sustained over 2, then stopped
    assert record["evaluations"][-1]["env_steps"] == 2 * 8 * 2 * RANKS  # every rank's samples
    assert 0 <= record["rank_launch_spread_s"] < record["startup_s"]
    # Rank 0 alone evaluated and printed the race; every other rank stopped after the same iteration.
    assert log.count("race: success >= 0.01 at iteration 1") == 1 and log.count("eval at iteration") == 2, log[-4000:]
    assert log.count(f"one race over {RANKS} ranks") == 1
    stops = re.findall(r"rank (\d+) done: (\d+) iterations", log)
    assert sorted(stops) == [(str(r), "2") for r in range(1, RANKS)], log[-4000:]
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["iterations"] == 2 and metrics["env_steps"] == 2 * 8 * 2 * RANKS


@RANKS_GROUP
@pytest.mark.slow
@pytest.mark.parametrize("extra, message", [
    (["resume=true"], "resume is not raced"),
    (["-m", "seed=0,1"], "not -m"),
])
def test_a_torchrun_race_refuses_what_it_cannot_mean_in_one_line_and_writes_nothing(tmp_path, extra, message):
    run, out = tmp_path / "run", tmp_path / "race.json"
    done = _torchrun_race(tmp_path, "--json", str(out), *TINY, "logger=none", f"hydra.run.dir={run}", *extra)
    errors = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and message in errors[0], done.stderr[-3000:]
    # Every rank exits 2 (torchrun itself reports the failed ranks and exits non-zero).
    assert done.returncode != 0 and done.stderr.count("exitcode  : 2") + done.stderr.count("exitcode: 2") >= 1, \
        done.stderr[-3000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_tiny_race_evaluates_whole_clips_and_records_them(tmp_path, monkeypatch):
    """Whole clips at every evaluation (share 1, open from the first): a 2-iteration policy completes no
    whole clip, so the whole-clip thresholds are censored while the window ones are reached."""
    from bmimic.race import main

    monkeypatch.chdir(tmp_path)
    args = ["--success", "0.01", "--mpkpe-rel-mm", "1000", "--whole-clip-success", "0.5",
            *[a for a in TINY if not a.startswith(("max_iterations", "motion"))], "motion=easy_only", "motion.duration_s=7",
            "max_iterations=2", "eval.every_iters=1", "eval.whole_clip.rollouts=2", "eval.whole_clip.max_share=1.0",
            "eval.whole_clip.after_success=0.001", f"hydra.run.dir={tmp_path / 'run'}", "logger=none"]
    assert main(args) == 0
    record = json.loads((tmp_path / "run" / "race.json").read_text())
    assert [t["status"] for t in record["thresholds"]] == ["reached", "reached", "censored"]
    assert record["thresholds"][2]["metric"] == WHOLE_CLIP_METRIC
    measured = [e[WHOLE_CLIP_METRIC] for e in record["evaluations"]]
    assert len(measured) == 2 and all(0 <= m <= 1 for m in measured)
    final = record["final_whole_clip"]  # measured in the clock at the last evaluation: not evaluated again
    assert final["iteration"] == 2 and final["in_clock"] is True and final[WHOLE_CLIP_METRIC] == measured[-1]
    assert (tmp_path / "run" / "whole_clip.parquet").exists()


@pytest.mark.slow
def test_checkpoints_evaluated_after_a_tiny_race_decide_its_whole_clip_line(tmp_path, monkeypatch):
    """The whole chain of analysis.race_whole_clip: a race whose share rule leaves no room for whole clips
    (as on an H200 at 4096 envs), then `bmimic.eval CHECKPOINT --whole-clip` of each checkpoint, then the
    thresholds decided afterwards on the race's clock."""
    from analysis.race_whole_clip import main as rejudge_main
    from bmimic.eval import main as eval_main
    from bmimic.race import main

    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    args = ["--success", "0.01", "--mpkpe-rel-mm", "1000", "--whole-clip-success", "0.5",
            *[a for a in TINY if not a.startswith(("max_iterations", "motion"))], "motion=easy_only", "motion.duration_s=7",
            "max_iterations=2", "eval.every_iters=1", "ppo.save_interval=1", "eval.whole_clip.rollouts=2",
            "eval.whole_clip.max_share=1e-9", f"hydra.run.dir={run}", "logger=none"]
    assert main(args) == 0
    record = json.loads((run / "race.json").read_text())
    assert not any(WHOLE_CLIP_METRIC in e for e in record["evaluations"])  # no room in the clock
    assert record["final_whole_clip"]["iteration"] == 2 and record["final_whole_clip"]["in_clock"] is False
    for it in (1, 2):
        assert eval_main([str(run / "checkpoints" / f"model_{it}.pt"), "--whole-clip", "2", "--conditions", "robust"]) == 0
    out = tmp_path / "rejudged.json"
    assert rejudge_main([str(run), "--json", str(out)]) == 0
    rejudged = json.loads(out.read_text())
    measured = {e["iteration"]: e[WHOLE_CLIP_METRIC] for e in rejudged["evaluations"] if WHOLE_CLIP_METRIC in e}
    assert sorted(measured) == [1, 2] and all(0.0 <= v <= 1.0 for v in measured.values())
    assert rejudged["thresholds"][:2] == record["thresholds"][:2]  # the window lines stand as the race decided them
    line = rejudged["thresholds"][2]
    assert line["metric"] == WHOLE_CLIP_METRIC and line["status"] == ("reached" if min(measured.values()) >= 0.5
                                                                       else "censored")
    assert "MuJoCo-Warp" in rejudged["whole_clip_source"]
