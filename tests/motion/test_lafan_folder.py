"""A folder of clips as a motion library (`motion=lafan_folder`, `motion.folder`, `motion.include` /
`motion.exclude`): which files become clips, one refusal line for every file that cannot be one, the
per-clip conversion cache, and (when the LAFAN1 data is here) the real folders."""

from __future__ import annotations

import re
import tarfile
from types import SimpleNamespace

import numpy as np
import pytest

from bmimic.motion.config import LAFAN_ENV, MotionConfig, load_motion
from bmimic.motion.library import library_entries, load_any, load_library
from bmimic.motion.motion import MotionDataError
from bmimic.robot import load_mjmodel
from tests.conftest import SHARED_MOTIONS, compose, run_train
from tests.motion.test_lafan import _assert_guides
from tests.motion.test_motion import _csv_rows, _write_csv

ARCHIVE_36 = SHARED_MOTIONS / "lafan1_g1_36.tar.xz"


def _cfg(folder, include=None, exclude=None, **kw):
    return SimpleNamespace(source="library", clips=None, glob=None, folder=None if folder is None else str(folder),
                           include=include, exclude=exclude, fps_in=30.0, assume_model_order=False, **kw)


@pytest.fixture(scope="module")
def model():
    return load_mjmodel()


@pytest.fixture
def folder(tmp_path):
    """Three clips of 3-4 s written by the test (LAFAN1 G1 CSV format, never LAFAN1 data), and files that are
    not clips: a note, a hidden file, a subfolder."""
    d = tmp_path / "g1"
    d.mkdir()
    for name, rows in (("walk1_subject2", 90), ("run1_subject5", 120), ("walk1_subject1", 105)):
        _write_csv(d / f"{name}.csv", _csv_rows(rows))
    (d / "README.md").write_text("not a clip\n")
    (d / ".walk1_subject1.csv.swp").write_text("an editor's swap file\n")
    (d / ".hidden.csv").write_text("1,2,3\n")
    (d / "sub").mkdir()
    _write_csv(d / "sub" / "deeper.csv", _csv_rows(90))
    return d


def test_every_csv_of_the_folder_is_a_clip_named_after_its_file_in_name_order(folder):
    entries = library_entries(_cfg(folder))
    assert [e.name for e in entries] == ["run1_subject5", "walk1_subject1", "walk1_subject2"]
    assert all(e.source == "file" and e.origin == "motion.folder" for e in entries)
    assert [e.value for e in entries] == [str(folder / f"{e.name}.csv") for e in entries]


@pytest.mark.parametrize("include, exclude, names", [
    (["walk*"], None, ["walk1_subject1", "walk1_subject2"]),
    ("walk*", None, ["walk1_subject1", "walk1_subject2"]),                  # one pattern as a string
    (None, ["*_subject2"], ["run1_subject5", "walk1_subject1"]),             # on the stem
    (None, ["walk1_subject2.csv"], ["run1_subject5", "walk1_subject1"]),     # or on the file name
    (["walk*", "run*"], ["*subject1"], ["run1_subject5", "walk1_subject2"]),
])
def test_include_and_exclude_patterns_select_files(folder, include, exclude, names):
    assert [e.name for e in library_entries(_cfg(folder, include, exclude))] == names


@pytest.mark.parametrize("make, message", [
    (lambda d: None, r"^motion.clips: a library needs at least one clip: .*motion.folder is not set \(motion=lafan_"),
    (lambda d: d / "nowhere", r"^motion.folder: .*nowhere is not a folder"),
    (lambda d: (d / "empty").mkdir() or d / "empty", r"^motion.folder: .*empty holds no .csv or .npz file$"),
])
def test_a_folder_that_gives_no_clip_is_refused_in_one_line(tmp_path, make, message):
    with pytest.raises(MotionDataError, match=message) as err:
        library_entries(_cfg(make(tmp_path)))
    assert "\n" not in str(err.value)


def test_an_unset_folder_says_where_to_get_the_data():
    with pytest.raises(MotionDataError) as err:
        library_entries(_cfg(None))
    _assert_guides(str(err.value), "motion=lafan_folder")


@pytest.mark.parametrize("include, exclude, message", [
    (["wlak*"], None, r"^motion.include: 'wlak\*' matches none of the 3 files \(run1_subject5.csv, "),
    (None, ["*subject9"], r"^motion.exclude: '\*subject9' matches none of the 3 files"),
    (["walk*"], ["walk*"], r"^motion.exclude: leaves none of the 3 files"),
    ([3], None, r"^motion.include: expected a pattern or a list of patterns"),
])
def test_a_pattern_that_matches_nothing_is_refused(folder, include, exclude, message):
    with pytest.raises(MotionDataError, match=message) as err:
        library_entries(_cfg(folder, include, exclude))
    assert "\n" not in str(err.value)


def test_patterns_without_a_folder_or_glob_are_refused():
    cfg = SimpleNamespace(source="library", clips=[{"path": "a.csv"}], glob=None, folder=None, include=["a*"],
                          exclude=None)
    with pytest.raises(MotionDataError, match=r"^motion.include/exclude: select among the files of motion.folder"):
        library_entries(cfg)


def test_clip_names_must_stay_unique(folder):
    np.savez(folder / "walk1_subject1.npz", x=np.zeros(1))
    with pytest.raises(MotionDataError, match=r"\['walk1_subject1'\] repeat; .*motion.exclude"):
        library_entries(_cfg(folder))


def _csv_text(rows: np.ndarray) -> str:
    return "\n".join(",".join(f"{v:.6f}" for v in r) for r in rows) + "\n"


def _rows_with_nan() -> np.ndarray:
    rows = _csv_rows(90)
    rows[40, 12] = np.nan
    return rows


BAD_FILES = {
    "wrong_columns": (lambda p: _write_csv(p, _csv_rows(90)[:, :35]), r"row 1, column 36: found 35 columns"),
    "nan": (lambda p: _write_csv(p, _rows_with_nan()), r"row 41, column 13: value nan is not finite"),
    "binary": (lambda p: p.write_bytes(b"\xff\xfe\x00\x81" * 64), r"cannot read as text"),
    "empty": (lambda p: p.write_text(""), r"file is empty"),
    "header": (lambda p: p.write_text(",".join(f"c{k}" for k in range(36)) + "\n" + _csv_text(_csv_rows(90))),
               r"row 1, column 1: 'c0' is not a number \(the file must have no header row\)"),
    "one_row": (lambda p: _write_csv(p, _csv_rows(1)), r"1 rows at 30.0 fps give fewer than 2 frames"),
    "too_short": (lambda p: _write_csv(p, _csv_rows(20)),
                  r"0.64 s is shorter than one time bin of sampler.bin_size_seconds=1 s; drop it "
                  r"\(motion.exclude=\[too_short\]\)"),
    "a_folder": (lambda p: p.mkdir(), r"file not found"),
    "bad_npz": (lambda p: p.with_suffix(".npz").write_bytes(b"not a zip"), r"not a readable npz file"),
}


@pytest.mark.parametrize("bad", sorted(BAD_FILES))
def test_a_bad_file_among_good_ones_is_refused_naming_it(folder, model, tmp_path, bad):
    """Never skipped: the whole library is refused in one line that names the file and what is wrong."""
    make, problem = BAD_FILES[bad]
    path = folder / f"{bad}.csv"
    make(path)
    name = path.with_suffix(".npz").name if bad == "bad_npz" else path.name
    with pytest.raises(MotionDataError) as err:
        load_any(_cfg(folder), model, cache_dir=tmp_path / "cache", bin_size_s=1.0, control_fps=50.0)
    message = str(err.value)
    assert "\n" not in message
    assert message.startswith(f"motion.folder: {folder / name}: "), message
    assert re.search(problem, message), message


def test_an_excluded_bad_file_is_not_read(folder, model, tmp_path):
    BAD_FILES["nan"][0](folder / "broken.csv")
    motion = load_any(_cfg(folder, exclude=["broken"]), model, cache_dir=tmp_path / "cache", bin_size_s=1.0,
                      control_fps=50.0)
    assert len(motion.clip_starts) == 3


def test_each_clip_is_converted_once_and_cached_as_a_single_clip_is(folder, model, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    first = load_library(_cfg(folder), model, cache, None, 50.0, min_file_s=1.0)
    # n rows at 30 Hz span (n - 1) / 30 s: 199, 174 and 149 frames at 50 Hz, in name order
    assert first.clip_starts.tolist() == [0, 199, 373] and first.num_frames == 522
    assert len(list(cache.glob("*.npz"))) == 3  # one cache entry per clip
    import bmimic.motion.convert as convert

    def no_conversion(*args, **kwargs):
        raise AssertionError("converted again instead of read from the cache")

    monkeypatch.setattr(convert, "convert_csv", no_conversion)
    again = load_library(_cfg(folder), model, cache, None, 50.0, min_file_s=1.0)
    assert np.array_equal(again.body_pos_w, first.body_pos_w)
    # a clip of the folder, loaded on its own, reads the same cache entry
    one = load_motion(MotionConfig(source="file", path=str(folder / "walk1_subject1.csv")), model, cache_dir=cache)
    assert np.array_equal(one.joint_pos, first.joint_pos[199:373])


def test_the_option_composes_with_the_folder_of_data_lafan_dir(folder):
    cfg = compose(["motion=lafan_folder", f"data.lafan_dir={folder}", "motion.exclude=[run*]"])
    assert cfg.motion.source == "library" and cfg.motion.folder == str(folder)
    assert [e.name for e in library_entries(cfg.motion)] == ["walk1_subject1", "walk1_subject2"]


def test_cfg_job_prints_the_folder_option(folder):
    code, out = run_train("motion=lafan_folder", "--cfg", "job", env={LAFAN_ENV: str(folder)})
    assert code == 0, out[-2000:]
    assert "folder: ${data.lafan_dir}" in out and "name: lafan_folder" in out


def test_train_refuses_a_folder_with_a_bad_file_in_one_line_and_leaves_nothing(folder, tmp_path):
    BAD_FILES["wrong_columns"][0](folder / "dance9_subject9.csv")
    run = tmp_path / "run"
    code, out = run_train("motion=lafan_folder", "device=cpu", f"hydra.run.dir={run}", cwd=tmp_path,
                          env={LAFAN_ENV: str(folder)})
    assert code == 2, out[-3000:]
    assert "Traceback" not in out
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert errors == [f"error: motion.folder: {folder / 'dance9_subject9.csv'}: row 1, column 36: found 35 columns, "
                      "expected 36 (root xyz, root quaternion xyzw, 29 joints)"], out[-2000:]
    assert not run.exists()


def test_the_shared_lafan_folder_is_a_library_of_its_csv_files(tmp_path):
    csvs = sorted(p.stem for p in SHARED_MOTIONS.glob("*.csv")) if SHARED_MOTIONS.is_dir() else []
    if not csvs:
        pytest.skip(f"no LAFAN1 G1 clip in {SHARED_MOTIONS} (not shipped: CC BY-NC-ND); set BMIMIC_LAFAN_DIR")
    cfg = compose(["motion=lafan_folder", f"data.lafan_dir={SHARED_MOTIONS}"])
    # the archive and the README beside the clips are not clips
    assert [e.name for e in library_entries(cfg.motion)] == csvs


@pytest.mark.slow  # converts the 36 clips (about 30 s on 2 cores)
def test_the_36_clip_archive_is_one_library_of_8002_seconds(tmp_path, model):
    if not ARCHIVE_36.is_file():
        pytest.skip(f"{ARCHIVE_36} is absent (LAFAN1, CC BY-NC-ND: not shipped); it holds issue 45's 36 clips")
    with tarfile.open(ARCHIVE_36) as tar:
        tar.extractall(tmp_path / "data", filter="data")
    (folder,) = {p.parent for p in (tmp_path / "data").rglob("*.csv")}
    cfg = compose(["motion=lafan_folder", f"data.lafan_dir={folder}"])
    motion = load_any(cfg.motion, model, cache_dir=tmp_path / "cache", bin_size_s=1.0, control_fps=50.0)
    names = [e.name for e in library_entries(cfg.motion)]
    assert len(names) == 36 and names == sorted(names) and "fallAndGetUp1_subject1" in names
    # 240,054 rows at 30 Hz; each clip resampled to 50 Hz keeps the times before its last row
    assert len(motion.clip_starts) == 36 and motion.num_frames == 400_040
    from bmimic.sampling.layouts import make_layout

    layout = make_layout("time", motion.num_frames, motion.fps, 1.0, clip_starts=motion.clip_starts, clip_names=names)
    lengths = np.diff([*motion.clip_starts.tolist(), motion.num_frames])
    assert layout.num_bins == int(np.ceil(lengths / 50).sum()) == 8018


def test_a_clip_too_fast_to_simulate_is_named(folder):
    """A file with a jump (a root teleport of 50 m between two rows) converts, but no world could start
    on it: the library is refused naming the clip and when."""
    from bmimic.config import ConfigError, resolve_runtime
    from bmimic.task import build_task

    rows = _csv_rows(90)
    rows[60:, 0] += 50.0
    _write_csv(folder / "teleport.csv", rows)
    cfg = compose(["motion=lafan_folder", f"data.lafan_dir={folder}", "device=cpu"])
    resolve_runtime(cfg, "cpu")
    with pytest.raises(ConfigError, match=r"^motion: its body_lin_vel_w reaches .* in clip teleport at 1.9\d s, "
                                          r"above sim.max_abs_qvel"):
        build_task(cfg, "cpu")


def test_a_clip_is_named_after_its_file_even_when_the_cache_holds_its_content_under_another_name(folder, model,
                                                                                                 tmp_path):
    cache = tmp_path / "cache"
    load_motion(MotionConfig(source="file", path=str(folder / "walk1_subject1.csv")), model, cache_dir=cache)
    (folder / "walk1_subject1.csv").rename(folder / "walk9_subject9.csv")  # same content, another name
    motion = load_any(_cfg(folder), model, cache_dir=cache, bin_size_s=1.0, control_fps=50.0)
    assert [s.name for s in motion.segments] == ["run1_subject5", "walk1_subject2", "walk9_subject9"]


def test_a_clip_file_name_that_is_not_utf8_is_refused_before_training_in_one_line(folder, tmp_path):
    """Issue 77: a name the OS holds as bytes that are not UTF-8 (b'bad\\xff.csv') became a clip name and failed
    the run with a UnicodeEncodeError when its first table was written, after training had started."""
    import os
    import shutil
    import time

    shutil.copy(folder / "walk1_subject1.csv", os.fsencode(folder) + b"/bad\xff.csv")
    words = f"motion.folder: {folder}: the file name b'bad\\xff.csv' is not valid UTF-8"
    with pytest.raises(MotionDataError, match=re.escape(words)):
        library_entries(_cfg(folder))
    with pytest.raises(MotionDataError, match=re.escape("motion.glob: ")):
        library_entries(SimpleNamespace(**{**vars(_cfg(None)), "glob": str(folder / "*.csv")}))
    run = tmp_path / "run"
    t0 = time.monotonic()
    code, out = run_train("motion=lafan_folder", "device=cpu", "num_envs=2", f"hydra.run.dir={run}", cwd=tmp_path,
                          env={LAFAN_ENV: str(folder)})
    errors = [line for line in out.splitlines() if line.startswith("error:")]
    assert code == 2 and errors == [f"error: {words} (a clip is named after its file in the run's tables); rename it"], \
        out[-2000:]
    assert "Traceback" not in out and not run.exists() and time.monotonic() - t0 < 5
