"""A committed record names its clips' folder as $BMIMIC_LAFAN_DIR (analysis.compact): evaluating it reads that
folder from a `data.lafan_dir=` override or the environment, in every key below it (motion.folder too), as a
resume from its state does (the library's sitting 3 found bmimic.eval refusing the folder it had just trained on)."""

from __future__ import annotations

import shutil

import pytest

from bmimic.evaluation.saved_run import RunLoadError, load_run_config
from bmimic.runs.folder import DATA_FOLDER_NAME
from tests.conftest import REPO

RECORD = REPO / "docs" / "results" / "lafan36_whole" / "runs" / "motion=lafan_folder,sampler=adaptive_hybrid" / "seed=0"
pytestmark = pytest.mark.skipif(not (RECORD / ".hydra" / "config.yaml").is_file(), reason="no committed library record")


@pytest.fixture
def record(tmp_path):
    shutil.copytree(RECORD, tmp_path / "run")
    return tmp_path / "run"


def test_the_clips_folder_comes_from_the_environment(record, tmp_path, monkeypatch):
    (tmp_path / "clips").mkdir()
    monkeypatch.setenv("BMIMIC_LAFAN_DIR", str(tmp_path / "clips"))
    cfg = load_run_config(record)
    assert cfg.motion.folder == cfg.data.lafan_dir == str(tmp_path / "clips")


def test_an_override_of_the_folder_wins_and_reaches_the_motion(record, tmp_path, monkeypatch):
    (tmp_path / "here").mkdir()
    monkeypatch.setenv("BMIMIC_LAFAN_DIR", str(tmp_path / "elsewhere"))  # not a folder: the override decides
    cfg = load_run_config(record, [f"data.lafan_dir={tmp_path / 'here'}"])
    assert cfg.motion.folder == cfg.data.lafan_dir == str(tmp_path / "here")


def test_without_a_folder_the_record_is_left_as_it_is_and_a_missing_folder_is_named(record, tmp_path, monkeypatch):
    monkeypatch.delenv("BMIMIC_LAFAN_DIR", raising=False)
    assert load_run_config(record).motion.folder == DATA_FOLDER_NAME  # a motion of its own needs none
    monkeypatch.setenv("BMIMIC_LAFAN_DIR", str(tmp_path / "nowhere"))
    with pytest.raises(RunLoadError, match=r"clips of \$BMIMIC_LAFAN_DIR .*nowhere'.*not a folder"):
        load_run_config(record)
