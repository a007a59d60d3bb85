"""What the commands say: the next steps after a sweep (one closing line; after a run:
tests/cli/test_interrupts.py, whose resumed run ends so), a log line
every few iterations where no terminal shows a progress bar, and an evaluation that sim2sim compared
against is never replaced silently."""

from __future__ import annotations

import json
import logging
import re

import pytest
from omegaconf import OmegaConf

from bmimic.eval import EarlierEvaluationError, keep_earlier
from bmimic.runs.folder import EVAL_DIR, EVAL_SUMMARY, SIM2SIM_DIR
from bmimic.sweeping.outcomes import OUTCOMES_ENV, SweepOutcomesCallback, record_job_outcome
from bmimic.training.logger import (
    LINES_PER_RUN,
    RunLogger,
    done_line,
    final_evaluation_line,
    line_every,
    pace_line,
)


@pytest.mark.parametrize(("iterations", "every"), [(1, 1), (4, 1), (50, 1), (51, 2), (101, 5), (1000, 20),
                                                   (3000, 100), (10000, 200)])
def test_log_lines_are_at_most_50_a_run_at_round_intervals(iterations, every):
    assert line_every(iterations) == every
    assert iterations / every <= LINES_PER_RUN and str(every)[0] in "125" and set(str(every)[1:]) <= {"0"}


def test_without_a_terminal_the_log_gets_lines_not_a_progress_bar(tmp_path, caplog, capsys):
    logger = RunLogger("none", tmp_path, "r", progress_bar=True)  # pytest's stderr is no terminal
    row = {"nonfinite_resets": 0, "out_of_bounds_resets": 0, "overflow_worlds": 0, "mean_episode_length": 10.0,
           "mean_reward": 0.5, "failure_rate": 0.1, "learning_rate": 1e-3, "fps": 100.0,
           "collection_time_s": 2.0, "learning_time_s": 0.5}
    with caplog.at_level(logging.INFO, logger="bmimic.training.logger"):
        logger.start(0, 120)
        for it in range(120):
            logger.iteration(it, row, 0)
        logger.close()
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("iteration ")]
    assert [int(re.match(r"iteration (\d+)/120", m).group(1)) for m in lines] == [*range(5, 121, 5)]
    # once, after the second iteration: its seconds times the 118 left (issue 75: an estimate from a measured iteration)
    assert [r.getMessage() for r in caplog.records if r.getMessage().startswith("pace: ")] == [
        "pace: 2.50 s per iteration; the 118 iterations left take about 5 min of training (evaluations come on top)"]
    assert "\r" not in capsys.readouterr().err  # no tqdm frames


def test_a_multirun_closes_with_one_line_naming_the_report(tmp_path, monkeypatch, capsys):
    sweep = tmp_path / "sweep"
    config = OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}})
    callback = SweepOutcomesCallback()
    callback.on_multirun_start(config)
    for n in range(3):
        record_job_outcome(sweep / f"job{n}", "done" if n else "done before")
    callback.on_multirun_end(config)
    out = capsys.readouterr().out.strip().splitlines()
    assert out == [f"3 jobs: 2 done, 1 done before -> {sweep}; next: bmimic-report {sweep}"]
    assert OUTCOMES_ENV not in __import__("os").environ


def test_the_commands_printed_paste_back_as_one_argument(tmp_path, capsys):
    import shlex

    from hydra.core.override_parser.overrides_parser import OverridesParser

    from bmimic.cli.common import override_arg

    sweep = tmp_path / "my sweeps" / "it's $HOME"
    config = OmegaConf.create({"hydra": {"sweep": {"dir": str(sweep)}}})
    callback = SweepOutcomesCallback()
    callback.on_multirun_start(config)
    record_job_outcome(sweep / "job0", "done")
    callback.on_multirun_end(config)
    line = capsys.readouterr().out.strip()
    assert shlex.split(line.split("next: ", 1)[1]) == ["bmimic-report", str(sweep)]
    # A resume hint: one shell word that Hydra reads back as the folder, `=` and `,` of a job folder included.
    parser = OverridesParser.create()
    for folder in (sweep / "motion=default,sampler=uniform" / "seed=0", tmp_path / "plain_run"):
        (word,) = shlex.split(override_arg("resume", folder))
        assert parser.parse_override(word).value() == str(folder)


def test_pyopengls_missing_accelerator_line_is_not_printed():
    import bmimic.render  # noqa: F401  (sets it before OpenGL is imported)

    assert logging.getLogger("OpenGL.acceleratesupport").getEffectiveLevel() >= logging.WARNING


def _evaluated(run, label="model_2"):
    (run / EVAL_DIR / label).mkdir(parents=True)
    # what bmimic.eval's summary holds at least (a summary without them is not replaced: test_foreign_out)
    (run / EVAL_DIR / label / EVAL_SUMMARY).write_text(json.dumps({"label": label, "checkpoint": f"{label}.pt",
                                                                   "eval_success_rate": 0.5}))
    return run / EVAL_DIR / label


def test_an_evaluation_sim2sim_compared_against_is_replaced_only_when_forced(tmp_path, caplog):
    out = _evaluated(tmp_path)
    keep_earlier(tmp_path / EVAL_DIR / "model_9", tmp_path, force=False)  # nothing there yet: fine
    with caplog.at_level(logging.WARNING, logger="bmimic.eval"):
        keep_earlier(out, tmp_path, force=False)  # no sim2sim result: replaced, but said so
    assert "replacing the earlier evaluation" in caplog.text
    gap = tmp_path / SIM2SIM_DIR / "bmimic_g1" / "model_2"
    gap.mkdir(parents=True)
    (gap / EVAL_SUMMARY).write_text("{}")
    with pytest.raises(EarlierEvaluationError, match=r"model_2: holds an earlier evaluation that sim2sim.*--out.*--force"):
        keep_earlier(out, tmp_path, force=False)
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="bmimic.eval"):
        keep_earlier(out, tmp_path, force=True)
    assert "sim2sim gap in" in caplog.text and "bmimic_g1" in caplog.text


def test_on_a_terminal_the_progress_bar_shows(tmp_path, monkeypatch):
    import sys

    monkeypatch.setattr(sys.stderr, "isatty", lambda: True, raising=False)
    logger = RunLogger("none", tmp_path, "r", progress_bar=True)
    assert logger.progress_bar
    logger.start(0, 3)
    assert logger._bar is not None  # tqdm's bar, redrawn on the terminal line
    logger.close()
    assert not RunLogger("none", tmp_path, "r", progress_bar=False).progress_bar


def test_the_closing_lines_say_what_runs_and_how_long_the_command_took(monkeypatch):
    import bmimic.cli.startup as startup

    assert pace_line(0.5, 60) == "pace: 0.50 s per iteration; the 60 iterations left take about 30 s of training (evaluations come on top)"
    assert "about 2.8 h" in pace_line(10.0, 1000)
    assert final_evaluation_line(True, False, True) == "final evaluation: the windows, then the whole clips"
    assert final_evaluation_line(False, False, False) == "final evaluation: none due (the last iteration's stands)"
    monkeypatch.setattr(startup, "STARTED_S", startup.time.monotonic() - 95.2)
    line = done_line({"iterations": 3, "wall_time_s": 53.4, "final_eval_failure_rate": 0.25}, "wall_time_s", "RUN", 0, 2)
    assert line.startswith("done: 3 iterations, 53 s of training in all (a resumed run's launches together; 95 s "
                           "this whole command), eval failure rate 0.250; "
                           "2 world-steps overflowed") and line.endswith(" -> RUN")
