"""`python -m bmimic.race`: the stopping rule on planted evaluation sequences (sustained thresholds,
the first of the sustained evaluations timed, censoring at the wall budget), refusals in one line,
and one tiny end-to-end race on the CPU."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from bmimic.race import Race, Threshold, parse_args, race_overrides
from tests.conftest import TINY


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


def test_one_evaluation_suffices_with_sustain_1():
    race = _race(sustain=1)
    assert _feed(race, [(0.995, 30)]) == 50


@pytest.mark.parametrize("argv,message", [
    (["--budget-s", "-5"], "--budget-s must be a finite number of seconds > 0"),
    (["--budget-s", "nan"], "--budget-s must be a finite number of seconds > 0"),
    (["--success", "0.9,1.5"], "--success thresholds must lie in (0, 1]"),
    (["--sustain", "0"], "--sustain must be >= 1"),
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
    assert "eval.every_iters=100" not in race_overrides(["eval.every_iters=10"])
    assert race_overrides(["run_name=mine"])[-1] == "run_name=mine" and "run_name=race" not in race_overrides(
        ["run_name=mine"])


@pytest.mark.slow
def test_a_tiny_race_on_the_cpu_stops_at_its_thresholds_and_writes_its_record(tmp_path, monkeypatch):
    from bmimic.race import main

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "race.json"
    args = ["--success", "0.01", "--mpkpe-rel-mm", "1000", "--json", str(out),
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
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    assert metrics["iterations"] == 2  # the run itself ended where the race stopped, checkpoint and all
    assert (tmp_path / "run" / "checkpoints" / "model_2.pt").exists()
