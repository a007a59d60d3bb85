"""Whole-clip evaluation from the command line (issue 44): `python -m bmimic.eval --whole-clip` on a
tiny trained run (its tables and printed report), its bad input refused in one line with exit status 2
and nothing written, and training that evaluates whole clips on a cadence and at its end."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pandas as pd
import pytest

from bmimic import eval as bm_eval
from bmimic.runs.folder import WHOLE_CLIP_FILES, table_path
from bmimic.runs.schema import (
    CLIP_TIME_S,
    CONDITION,
    ITERATION,
    WHOLE_CLIP_COLUMNS,
    WHOLE_CLIP_FAILURE_COLUMNS,
    WHOLE_CLIP_SURVIVAL_COLUMNS,
    whole_clip_key,
)
from tests.conftest import REPO, run_train, train_in_process

TINY = ["motion=easy_only", "motion.duration_s=7", "sampler.bin_size_seconds=1.0", "num_envs=2",
        "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2", "eval.horizon_s=0.2", "logger=none", "progress_bar=false"]


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    return train_in_process(tmp_path_factory.mktemp("runs") / "tiny", *TINY, "max_iterations=1", cwd=REPO)


def _digest(folder: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        h.update(str(p.relative_to(folder)).encode())
        if p.is_file():
            h.update(p.read_bytes())
    return h.hexdigest()


def test_eval_whole_clip_writes_its_tables_and_report(tiny_run, capsys):
    assert bm_eval.main([str(tiny_run), "--whole-clip", "2", "--device", "cpu"]) == 0
    printed = capsys.readouterr().out
    out = tiny_run / "eval" / "model_1" / "whole_clip"
    clips_file, survival_file, failures_file, summary_file = (out / name for name in WHOLE_CLIP_FILES)
    clips, survival, failures = (pd.read_csv(f) for f in (clips_file, survival_file, failures_file))
    summary = json.loads(summary_file.read_text())
    assert list(clips.columns[: len(WHOLE_CLIP_COLUMNS)]) == list(WHOLE_CLIP_COLUMNS)
    assert list(survival.columns) == list(WHOLE_CLIP_SURVIVAL_COLUMNS)
    assert list(failures.columns) == list(WHOLE_CLIP_FAILURE_COLUMNS)
    assert clips[CONDITION].tolist() == ["nominal", "robust"] and clips["rollouts"].tolist() == [1, 2]
    assert (clips["completed"] + clips["failures"]).tolist() == [1, 2]
    assert (clips["transient_failures"] + clips["later_failures"]).tolist() == clips["failures"].tolist()
    assert len(failures) == int(clips["failures"].sum())
    last = survival.groupby(CONDITION).tail(1)
    assert last[CLIP_TIME_S].tolist() == [6.98, 6.98]
    assert last["tracking_frac"].tolist() == clips["success_rate"].tolist()
    for condition in ("nominal", "robust"):
        assert summary[whole_clip_key(condition, "rollouts")] == int(clips.loc[clips[CONDITION] == condition,
                                                                                "rollouts"].sum())
    assert summary["rollouts_per_clip"] == {"nominal": 1, "robust": 2} and summary[ITERATION] == 1
    assert "nominal (1 rollout(s) per clip):" in printed and "within 1 s of the start" in printed
    assert not list(out.glob(".*.tmp-*"))


@pytest.mark.parametrize("args,message", [
    (["--whole-clip", "0"], "--whole-clip 0: the rollouts per clip must be >= 1"),
    (["--whole-clip", "-3"], "--whole-clip -3: the rollouts per clip must be >= 1"),
    (["--whole-clip", "--conditions", "nominal,windy"], "--conditions: unknown condition 'windy' (known: nominal, robust)"),
    (["--whole-clip", "--condition", "robust,robust"], "--conditions: name each condition once"),
    (["--conditions", "robust"], "--conditions: only with --whole-clip"),
    (["eval.whole_clip.rollouts=0", "--whole-clip"], "eval.whole_clip.rollouts: must be >= 1, got 0"),
    (["eval.whole_clip.conditions=[windy]", "--whole-clip"], "eval.whole_clip.conditions: unknown condition 'windy'"),
    (["eval.whole_clip.max_clip_s=5", "--whole-clip"],
     "eval.whole_clip.max_clip_s: clip 'easy_only' is 6.98 s long, longer than the 5 s a whole-clip evaluation holds"),
])
def test_bad_whole_clip_input_is_one_line_exit_2_and_writes_nothing(tiny_run, args, message, capsys):
    before = _digest(tiny_run)
    assert bm_eval.main([str(tiny_run), *args, "--device", "cpu"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0]
    assert _digest(tiny_run) == before


def test_training_evaluates_whole_clips_on_its_cadence_and_at_the_end(tmp_path):
    """Windows every iteration, whole clips every 2 and at the end (3 iterations): rows at 2 and 3, the
    final ones in metrics.json; training's episode limit (0.3 s) does not cut the rollouts."""
    run = train_in_process(tmp_path / "run", *TINY, "max_iterations=3", "eval.every_iters=1", "env.episode_length_s=0.3",
                           "eval.whole_clip.every_iters=2", "eval.whole_clip.at_end=true",
                           "eval.whole_clip.conditions=[nominal]", cwd=REPO)
    clips = pd.read_parquet(table_path(run, "whole_clip"))
    assert clips[ITERATION].tolist() == [2, 3] and (clips["rollouts"] == 1).all()
    assert (clips["completed"] + clips["failures"] == 1).all()
    survival = pd.read_parquet(table_path(run, "whole_clip_survival"))
    assert sorted(survival[ITERATION].unique()) == [2, 3]
    failures = pd.read_parquet(table_path(run, "whole_clip_failures"))
    assert len(failures) == int(clips["failures"].sum()) and (failures["failure_time_s"] > 0.3).all()
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics[f"final_{whole_clip_key('nominal', 'success_rate')}"] == float(clips["success_rate"].iloc[-1])


def test_training_refuses_a_clip_it_cannot_hold_before_writing_its_run(tmp_path):
    code, out = run_train(*TINY, "max_iterations=1", "eval.whole_clip.at_end=true", "eval.whole_clip.max_clip_s=5",
                          f"hydra.run.dir={tmp_path / 'run'}", cwd=REPO)
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and "eval.whole_clip.max_clip_s" in errors[0]
    assert not (tmp_path / "run").exists() or not any((tmp_path / "run").iterdir())
