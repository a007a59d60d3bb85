"""LAFAN1 data paths: one key (data.lafan_dir, default $BMIMIC_LAFAN_DIR), clip names relative to it,
and one line that says what is missing, where to get it and what to set."""

from __future__ import annotations

import pytest

from bmimic.motion.config import LAFAN_ENV, lafan_clip_path
from bmimic.motion.motion import MotionDataError
from tests.conftest import CONF, SHARED_MOTIONS, compose, run_train

# option -> (clip, window start_s, end_s; None = the whole clip)
OPTIONS = {
    "lafan_dance1": ("dance1_subject1", 0.0, 60.0),
    "lafan_dance1_full": ("dance1_subject1", None, None),
    "lafan_walk1": ("walk1_subject1", 0.0, 60.0),
    "lafan_walk1_full": ("walk1_subject1", None, None),
    "lafan_run1": ("run1_subject2", 0.0, 60.0),
    "lafan_run1_full": ("run1_subject2", None, None),
    "lafan_fall1_full": ("fallAndGetUp1_subject1", None, None),
}


def _assert_guides(message: str, *fragments: str) -> None:
    assert "\n" not in message
    for part in ("huggingface.co/datasets/unitreerobotics/LAFAN1_Retargeting_Dataset", "g1/", LAFAN_ENV,
                 "data.lafan_dir", *fragments):
        assert part in message, (part, message)


def test_every_lafan_option_is_listed():
    singles = [p.stem for p in (CONF / "motion").glob("lafan_*.yaml")
               if not p.stem.startswith(("lafan_library", "lafan_folder"))]
    assert sorted(singles) == sorted(OPTIONS)


def test_the_40_clip_library_is_10000_bins_of_the_three_clips(monkeypatch):
    """motion=lafan_library40 (issue 20's benchmark): 40 windows of 15 s inside the three clips
    (dance1 131.5 s, walk1 256.9 s, run1 237.8 s), so 10,000 bins at sampler.bin_size_seconds=0.06."""
    from bmimic.motion.library import library_entries

    monkeypatch.setenv(LAFAN_ENV, "/data/lafan/g1")
    entries = library_entries(compose(["motion=lafan_library40"]).motion)
    length_s = {"dance1_subject1": 131.5, "walk1_subject1": 256.9, "run1_subject2": 237.8}
    assert len(entries) == 40 and len({e.name for e in entries}) == 40
    assert all(e.end_s - e.start_s == 15 and 0 <= e.start_s and e.end_s <= length_s[e.value] for e in entries)
    assert round(sum(e.end_s - e.start_s for e in entries) / 0.06) == 10_000


def test_the_lafan_library_lists_the_three_study_clips_in_full(monkeypatch):
    from bmimic.motion.library import library_entries

    monkeypatch.setenv(LAFAN_ENV, "/data/lafan/g1")
    cfg = compose(["motion=lafan_library"])
    entries = library_entries(cfg.motion)
    assert [(e.name, e.source, e.start_s, e.end_s) for e in entries] == [
        ("dance1_subject1", "lafan", None, None), ("walk1_subject1", "lafan", None, None),
        ("run1_subject2", "lafan", None, None)]


@pytest.mark.parametrize("option", sorted(OPTIONS))
def test_lafan_options_name_a_clip_and_a_window(option, monkeypatch):
    monkeypatch.setenv(LAFAN_ENV, "/data/lafan/g1")
    cfg = compose([f"motion={option}"])
    clip, start_s, end_s = OPTIONS[option]
    assert (cfg.motion.name, cfg.motion.source, cfg.motion.clip) == (option, "lafan", clip)
    assert (cfg.motion.start_s, cfg.motion.end_s, cfg.motion.fps_in) == (start_s, end_s, 30.0)
    assert cfg.data.lafan_dir == "/data/lafan/g1"


def test_lafan_dir_defaults_to_the_environment_variable(monkeypatch):
    monkeypatch.delenv(LAFAN_ENV, raising=False)
    assert compose([]).data.lafan_dir is None
    monkeypatch.setenv(LAFAN_ENV, "/somewhere/g1")
    assert compose([]).data.lafan_dir == "/somewhere/g1"
    assert compose(["data.lafan_dir=/elsewhere"]).data.lafan_dir == "/elsewhere"


def test_clip_path_resolves_names_relative_to_the_folder(tmp_path, monkeypatch):
    (tmp_path / "g1").mkdir()
    clip = tmp_path / "g1" / "walk1_subject1.csv"
    clip.write_text("")
    assert lafan_clip_path("walk1_subject1", tmp_path / "g1") == clip
    assert lafan_clip_path("walk1_subject1.csv", str(tmp_path / "g1")) == clip
    monkeypatch.chdir(tmp_path)  # a relative folder is taken from where the command started
    assert lafan_clip_path("walk1_subject1", "g1") == clip


def test_missing_folder_or_clip_is_one_guiding_line(tmp_path):
    with pytest.raises(MotionDataError) as unset:
        lafan_clip_path("dance1_subject1", None)
    _assert_guides(str(unset.value), "dance1_subject1.csv", "not set")
    with pytest.raises(MotionDataError) as no_folder:
        lafan_clip_path("dance1_subject1", tmp_path / "nowhere")
    _assert_guides(str(no_folder.value), str(tmp_path / "nowhere"), "not a folder")
    with pytest.raises(MotionDataError) as no_clip:
        lafan_clip_path("dance1_subject1", tmp_path)
    _assert_guides(str(no_clip.value), "dance1_subject1.csv", str(tmp_path))


def test_train_without_the_data_says_what_to_do(tmp_path):
    code, out = run_train("motion=lafan_walk1", "device=cpu", f"hydra.run.dir={tmp_path / 'run'}", cwd=tmp_path,
                          env={LAFAN_ENV: None})
    assert code == 2, out[-3000:]
    assert "Traceback" not in out
    last = out.strip().splitlines()[-1]
    assert last.startswith("error: LAFAN1 clip walk1_subject1.csv: data.lafan_dir is not set")
    _assert_guides(last)


@pytest.mark.parametrize("option", sorted(OPTIONS))
def test_lafan_windows_fit_the_real_clips(option):
    clip, start_s, end_s = OPTIONS[option]
    if not (SHARED_MOTIONS / f"{clip}.csv").is_file():
        pytest.skip(f"LAFAN1 clip {clip}.csv is absent (not shipped: CC BY-NC-ND); set BMIMIC_LAFAN_DIR to run this")
    path = lafan_clip_path(clip, SHARED_MOTIONS)
    with path.open() as f:
        length_s = sum(1 for _ in f) / 30.0
    assert length_s > 120  # every option's clip is minutes long; a window takes its first minute
    assert end_s is None or end_s <= length_s
