"""analysis.races: race JSONs written by bmimic.race's own record, read back into tidy tables, drawn,
and refused with one line when they are not race JSONs."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pandas as pd
import pytest

from analysis import AnalysisError
from analysis.races import (
    FINAL_WHOLE_CLIP,
    LINESTYLES,
    config_label,
    main,
    plot_races,
    race_evaluations,
    race_summary,
    race_thresholds,
    read_race,
    read_races,
    summary_markdown,
    whole_clip_markdown,
)
from bmimic.race import WHOLE_CLIP_METRIC, Race, Threshold
from bmimic.runs.atomic_io import atomic_write_json
from bmimic.runs.schema import ENV_STEPS, ITERATION, MPKPE_REL_MM

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


REPO = Path(__file__).resolve().parents[2]


def _race_json(path, successes, mpkpes, seed=0, overrides=(), num_envs=4096, gpu="NVIDIA H100 80GB HBM3",
               every=100, gpus=1):
    """A race fed `successes` / `mpkpes` at evaluations every `every` iterations (1 s per 10 iterations from
    a first iteration 20 s after launch), written as bmimic.race writes it (over `gpus` torchrun ranks,
    num_envs each, launched 0.5 s apart, when gpus > 1)."""
    race = Race([Threshold("eval_success_rate", 0.9), Threshold("eval_success_rate", 0.99),
                 Threshold("eval_mpkpe_rel_mm", 40.0)], budget_s=1e9, launch_unix_s=100.0)
    if gpus > 1:
        race.join_ranks([100.0 + 0.5 * r for r in range(gpus)])
    for i, (s, m) in enumerate(zip(successes, mpkpes, strict=True), start=1):
        it = i * every
        progress = SimpleNamespace(iteration=it, env_steps=num_envs * gpus * 24 * it, wall_time_s=it / 10)
        trainer = SimpleNamespace(run_dir="RUN", learn_started_unix_s=120.0, eval_time_s=0.5 * i, progress=progress)
        race.on_evaluation(trainer, {"eval_success_rate": s, "eval_mpkpe_rel_mm": m}, now=120.0 + it / 10)
    config = {"seed": seed, "sampler": "adaptive_hybrid", "num_envs": num_envs, "eval": {"every_iters": every},
              "overrides": ["motion=lafan_dance1_full", *overrides, f"seed={seed}", "hydra.run.dir=/tmp/x"]}
    machine = {"gpu": {"name": gpu}, "created": "2026-11-27T14:28:24+00:00"}
    atomic_write_json(path, race.to_json(config, machine))  # as bmimic.race writes it (NaN as null)
    return path


def test_evaluations_and_thresholds_read_back_as_planted(tmp_path):
    a = _race_json(tmp_path / "a.json", [0.5, 0.92, 0.95, 0.991, 0.995], [60, 45, 39, 38, 37],
                   overrides=["env=tracking"])
    b = _race_json(tmp_path / "b.json", [0.4, 0.8, 0.91], [70, 50, 45], seed=1)
    ev = race_evaluations(read_races([a, b]))
    assert len(ev) == 8 and sorted(ev["race"].unique()) == ["a", "b"]
    ra = ev[ev["race"] == "a"]
    assert ra[ITERATION].tolist() == [100, 200, 300, 400, 500]
    assert ra[ENV_STEPS].tolist() == [4096 * 24 * it for it in (100, 200, 300, 400, 500)]
    assert ra["wall_from_launch_s"].tolist() == pytest.approx([30, 40, 50, 60, 70])
    assert ra[MPKPE_REL_MM].tolist() == [60, 45, 39, 38, 37]
    assert set(ra["config"]) == {"env=tracking sampler=adaptive_hybrid num_envs=4096"}
    assert set(ev.loc[ev["race"] == "b", "config"]) == {"env=beyondmimic sampler=adaptive_hybrid num_envs=4096"}
    assert set(ev["gpu"]) == {"H100"} and set(ev["date"]) == {"2026-11-27"}

    th = race_thresholds(read_races([a, b])).set_index(["race", "metric", "threshold"])
    # success 0.9 held from iteration 200 (0.92, 0.95); 0.99 from 400; MPKPE <= 40 from 300
    assert th.loc[("a", "eval_success_rate", 0.9), ITERATION] == 200
    assert th.loc[("a", "eval_success_rate", 0.99), ITERATION] == 400
    assert th.loc[("a", "eval_success_rate", 0.99), "wall_from_launch_s"] == pytest.approx(60)
    assert th.loc[("a", "eval_mpkpe_rel_mm", 40.0), ITERATION] == 300
    # b: 0.9 met once (needs two in a row), never 0.99, never 40 mm: all censored, no time
    censored = th.loc["b"]
    assert (censored["status"] == "censored").all() and censored[ITERATION].isna().all()


def test_config_label_names_what_was_trained_and_drops_seed_logging_and_evaluation():
    cfg = {"sampler": "adaptive", "num_envs": 8192,
           "overrides": ["motion=m", "env=tracking", "num_envs=8192", "ppo.learning_rate=3e-4", "seed=2",
                         "eval.every_iters=100", "hydra.run.dir=/x", "logger=none", "+run_name=r"]}
    assert config_label(cfg) == "env=tracking sampler=adaptive num_envs=8192 ppo.learning_rate=3e-4"
    assert config_label({"sampler": "uniform", "num_envs": 4096, "overrides": []}) == (
        "env=beyondmimic sampler=uniform num_envs=4096")
    # A race records the env group it trained (its default env=tracking is in no override).
    assert config_label({"env": "tracking", "sampler": "adaptive_hybrid", "num_envs": 4096, "overrides": []}) == (
        "env=tracking sampler=adaptive_hybrid num_envs=4096")


def test_the_figure_draws_one_line_per_race_on_each_panel_styled_by_seed(tmp_path):
    paths = [_race_json(tmp_path / f"r{s}.json", [0.5, 0.9, 1.0], [60, 50, 40], seed=s) for s in (0, 1)]
    fig = plot_races(race_evaluations(read_races(paths)))
    axes = fig.axes
    assert len(axes) == 6  # failure and MPKPE against wall time, iterations and env steps
    for ax in axes:
        races = [ln for ln in ax.get_lines() if ln.get_marker() == "o"]
        assert len(races) == 2
        assert sorted(ln.get_linestyle() for ln in races) == sorted(LINESTYLES[:2])
    failure = [ln for ln in axes[0].get_lines() if ln.get_marker() == "o"][0].get_ydata()
    assert failure[-1] == pytest.approx(1e-3)  # success 1.0 drawn at the log axis' floor, not dropped
    assert axes[0].get_yscale() == "log"


def test_a_torchrun_race_reads_back_with_its_gpus_and_envs_per_gpu(tmp_path):
    one = _race_json(tmp_path / "one.json", [0.5, 0.92, 0.95], [60, 45, 39], num_envs=8192)
    four = _race_json(tmp_path / "four.json", [0.6, 0.93, 0.96], [55, 44, 38], num_envs=2048, gpus=4,
                      overrides=["num_envs=2048"])
    races = read_races([one, four])
    ev = race_evaluations(races).set_index("race")
    assert ev.loc["one", "gpus"].tolist() == [1] * 3 and ev.loc["four", "gpus"].tolist() == [4] * 3
    assert set(ev.loc["four", "num_envs_per_gpu"]) == {2048} and set(ev.loc["four", "num_envs_total"]) == {8192}
    assert set(ev.loc["one", "num_envs_per_gpu"]) == {8192} and set(ev.loc["one", "num_envs_total"]) == {8192}
    # the same total envs: the same env steps per iteration on both
    assert ev.loc["four", ENV_STEPS].tolist() == ev.loc["one", ENV_STEPS].tolist()
    th = race_thresholds(races)
    assert set(th.loc[th["race"] == "four", "gpus"]) == {4}
    table = summary_markdown(race_summary(races))
    rows = table.strip().splitlines()[2:]
    assert "| H100 |" in rows[0] and "| 4 x H100 |" in rows[1] and "num_envs=2048" in rows[1]
    fig = plot_races(race_evaluations(races))
    assert fig.axes[5].get_xlabel().startswith("env steps")  # bottom right; axes[2] is the failure panel above it
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert any("(4 x H100," in t for t in labels) and any("(H100," in t for t in labels)
    lines = [ln for ln in fig.axes[2].get_lines() if ln.get_marker() == "o"]  # the env-steps panel
    assert sorted(ln.get_xdata().tolist() for ln in lines)[0] == ev.loc["one", ENV_STEPS].tolist()


def test_the_cli_writes_the_tables_and_the_figure(tmp_path, capsys):
    paths = [_race_json(tmp_path / f"r{s}.json", [0.5, 0.9, 0.99, 0.995], [60, 45, 40, 39], seed=s) for s in (0, 1)]
    out = tmp_path / "curves"
    assert main([*map(str, paths), "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["race_curves.png", "race_evaluations.csv", "race_summary.csv",
                                                     "race_table.md", "race_thresholds.csv"]
    assert (out / "race_curves.png").read_bytes().startswith(PNG_MAGIC)
    assert len(pd.read_csv(out / "race_evaluations.csv")) == 8
    th = pd.read_csv(out / "race_thresholds.csv")
    assert len(th) == 6 and th[ITERATION].dropna().astype(int).tolist() == [200, 300, 300] * 2


@pytest.mark.parametrize("content, message", [
    (None, "no such file"),
    ("{not json", "not a readable JSON file"),
    ('{"kind": "bmimic-bench-1"}', "kind is 'bmimic-bench-1', expected 'bmimic-race-1'"),
    ('[1, 2]', "kind is 'list'"),
    ('{"kind": "bmimic-race-1", "config": {}, "evaluations": {}}', "'evaluations' is not a list"),
    ('{"kind": "bmimic-race-1", "evaluations": []}', "no 'config' object"),
    ('{"kind": "bmimic-race-1", "config": {}, "evaluations": [{"iteration": 1}]}', "evaluation 0 lacks env_steps"),
    ('{"kind": "bmimic-race-1", "config": {}, "evaluations": [{"iteration": "1x", "env_steps": 1, '
     '"wall_from_launch_s": 1, "success_rate": 0.5, "mpkpe_rel_mm": 40}]}', "evaluation 0: iteration is '1x'"),
    ('{"kind": "bmimic-race-1", "config": {}, "evaluations": [{"iteration": 1, "env_steps": 1, '
     '"wall_from_launch_s": true, "success_rate": 0.5, "mpkpe_rel_mm": 40}]}', "wall_from_launch_s is True"),
    ('{"kind": "bmimic-race-1", "config": {}, "evaluations": [], "thresholds": [{"threshold": "x"}]}',
     "'thresholds' must be a list of objects"),
    # issue 77: a measurement that is not finite (bmimic.race writes null for what it did not measure)
    ('{"kind": "bmimic-race-1", "config": {}, "evaluations": [{"iteration": 1, "env_steps": 1, '
     '"wall_from_launch_s": Infinity, "success_rate": NaN, "mpkpe_rel_mm": 40}]}', "holds the number Infinity"),
])
def test_bad_input_is_one_line_naming_the_file_and_writes_nothing(tmp_path, capsys, content, message):
    bad = tmp_path / "bad.json"
    if content is not None:
        bad.write_text(content)
    with pytest.raises(AnalysisError, match="bad.json"):
        read_race(bad)
    good = _race_json(tmp_path / "good.json", [0.5, 0.9], [60, 50])
    out = tmp_path / "curves"
    assert main([str(good), str(bad), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bad.json" in err and message in err
    assert not out.exists()


def test_an_out_path_that_is_a_file_is_refused_and_left_alone(tmp_path, capsys):
    good = _race_json(tmp_path / "good.json", [0.5, 0.9], [60, 50])
    out = tmp_path / "curves"
    out.write_text("keep me")
    assert main([str(good), "--out", str(out)]) == 2
    assert "is a file" in capsys.readouterr().err and out.read_text() == "keep me"


def test_the_summary_row_times_each_threshold_or_says_when_the_race_ended_without_it(tmp_path):
    a = _race_json(tmp_path / "a.json", [0.5, 0.92, 0.95, 0.991, 0.995], [60, 45, 39, 38, 37])
    b = _race_json(tmp_path / "b.json", [0.4, 0.8, 0.91], [70, 50, 45], seed=1)
    summary = race_summary(read_races([a, b])).set_index("race")
    # start-up: first iteration at 120 s, launch at 100 s; 0.1 s of training per iteration
    assert summary.loc["a", "startup_s"] == pytest.approx(20)
    assert summary.loc["a", "training_s_per_iteration"] == pytest.approx(0.1)
    assert summary.loc["a", "90% success"] == "40 s (it 200)"
    assert summary.loc["a", "99% success"] == "60 s (it 400)"
    assert summary.loc["a", "MPKPE <= 40 mm"] == "50 s (it 300)"
    assert summary.loc["b", "90% success"] == "> 50 s"  # b ended at 50 s from launch without it
    assert summary.loc["a", "stopped"] == "every threshold reached" and summary.loc["b", "last_success"] == 0.91
    table = summary_markdown(summary.reset_index())
    header, rule, row_a, row_b = table.strip().splitlines()
    assert header.split(" | ")[-1] == "success at the end |" and "99% success" in header
    assert "| 20 s | 0.100 |" in row_a and "60 s (it 400)" in row_a and row_b.endswith("| 0.910 |")


def test_the_committed_race_tables_rebuild_from_the_committed_race_jsons(tmp_path):
    """docs/bench/race_curves_<card>/race_table.md, the tables docs/benchmarks.md quotes, is a rebuild of
    that card's race JSONs beside it (docs/bench/*_<card>_race_*.json)."""
    bench = REPO / "docs" / "bench"
    folders = sorted(bench.glob("race_curves_*"))
    if not folders:
        pytest.skip("no committed race tables (docs/bench/race_curves_*)")
    for folder in folders:
        card = folder.name.removeprefix("race_curves_")
        paths = sorted(bench.glob(f"*_{card}_race_*.json"))
        assert main([*map(str, paths), "--out", str(tmp_path / folder.name)]) == 0
        rebuilt = (tmp_path / folder.name / "race_table.md").read_bytes()
        assert rebuilt == (folder / "race_table.md").read_bytes(), folder.name
        whole = tmp_path / folder.name / "whole_clip_table.md"  # written where a race was judged on the whole clip
        assert whole.exists() == (folder / whole.name).exists(), folder.name
        if whole.exists():
            assert whole.read_bytes() == (folder / whole.name).read_bytes(), folder.name


def test_a_whole_clip_threshold_gets_a_column_of_its_own(tmp_path):
    race = Race([Threshold("eval_success_rate", 0.9), Threshold(WHOLE_CLIP_METRIC, 0.9)], budget_s=1e9,
                launch_unix_s=100.0)
    for i, whole in enumerate((None, 0.92, None, 0.95), start=1):
        progress = SimpleNamespace(iteration=100 * i, env_steps=1000 * i, wall_time_s=10.0 * i)
        trainer = SimpleNamespace(run_dir="RUN", learn_started_unix_s=120.0, eval_time_s=0.5 * i, progress=progress)
        summary = {"eval_success_rate": 0.96, **({} if whole is None else {WHOLE_CLIP_METRIC: whole})}
        race.on_evaluation(trainer, summary, now=120.0 + 10.0 * i)
    path = tmp_path / "w.json"
    atomic_write_json(path, race.to_json({"seed": 0, "eval": {"every_iters": 100}}, {"gpu": {"name": "H100"}}))
    summary = race_summary(read_races([path]))
    assert summary.loc[0, "90% robust whole-clip success"] == "40 s (it 200)"  # launch at 100 s
    assert "90% robust whole-clip success" in summary_markdown(summary).splitlines()[0]


def test_the_whole_clip_table_gives_time_iteration_and_env_steps_and_the_final_judgement(tmp_path):
    race = Race([Threshold("eval_success_rate", 0.99), Threshold(WHOLE_CLIP_METRIC, 0.9),
                 Threshold(WHOLE_CLIP_METRIC, 0.95)], budget_s=1e9, sustain=1, launch_unix_s=100.0)
    race.join_ranks([100.0, 100.5])
    for i, (window, whole) in enumerate(((0.995, None), (0.999, 0.92), (1.0, 0.93)), start=1):
        progress = SimpleNamespace(iteration=100 * i, env_steps=196_608_000 * i, wall_time_s=10.0 * i)
        trainer = SimpleNamespace(run_dir="RUN", learn_started_unix_s=120.0, eval_time_s=0.5 * i, progress=progress)
        summary = {"eval_success_rate": window, **({} if whole is None else {WHOLE_CLIP_METRIC: whole})}
        race.on_evaluation(trainer, summary, now=120.0 + 10.0 * i)
    race.record_final_native(0.9453125, {"iterations": 300, "env_steps": 3 * 196_608_000})
    judged = tmp_path / "judged.json"
    atomic_write_json(judged, race.to_json({"seed": 1, "num_envs": 4096,
                                               "eval": {"every_iters": 100, "whole_clip": {"rollouts": 128}}},
                                              {"gpu": {"name": "NVIDIA H200"}, "created": "2026-11-29T21:00:00"}))
    plain = _race_json(tmp_path / "plain.json", [0.5, 0.95], [60.0, 45.0])  # no whole-clip line: no row
    table = whole_clip_markdown(read_races([judged, plain])).splitlines()
    assert len(table) == 3  # header, rule, the judged race alone
    header = [c.strip() for c in table[0].strip("|").split("|")]
    row = dict(zip(header, (c.strip() for c in table[2].strip("|").split("|")), strict=True))
    assert (row["GPUs"], row["envs per GPU"], row["seed"]) == ("2 x H200", "4096", "1")
    assert row["99% window success"] == "30 s (it 100, 1.97e8)"  # the clock starts at the earlier rank's launch
    assert row["90% robust whole-clip success"] == "40 s (it 200, 3.93e8)"
    assert row["95% robust whole-clip success"] == "> 50 s"  # 0.93 at the end: censored at the race's end
    # 121 of 128 rollouts: Wilson's 95% interval [0.891, 0.973] (the race recorded its rollouts per judgement)
    assert row[FINAL_WHOLE_CLIP] == "0.945 [0.891, 0.973] (native MuJoCo, it 300)"
    assert whole_clip_markdown(read_races([plain])) is None


def test_a_race_without_an_evaluation_cadence_draws_its_curves(tmp_path):
    """Found by the generated harness at 500 examples (issue 77): a race JSON whose config has no `eval`
    (an earlier bmimic's) made the colour key of its line missing (pandas keeps None as missing), a KeyError."""
    path = _race_json(tmp_path / "r.json", [0.5, 0.9], [60, 50])
    data = read_race(path)
    data["config"].pop("eval")
    atomic_write_json(path, data)
    fig = plot_races(race_evaluations(read_races([path])))
    assert len([ln for ln in fig.axes[0].get_lines() if ln.get_marker() == "o"]) == 1
    assert main([str(path), "--out", str(tmp_path / "out")]) == 0
