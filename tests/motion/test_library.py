"""Motion libraries (bmimic.motion.library): entries, loading, and training on several clips."""

from __future__ import annotations

from types import SimpleNamespace

import pandas as pd
import pytest

from bmimic.motion.builtin import generate_builtin
from bmimic.motion.library import library_entries, load_library
from bmimic.motion.segments import MotionDataError
from bmimic.robot import load_mjmodel
from tests.conftest import TINY, train_in_process
from tests.motion.test_motion import _csv_rows, _write_csv


def _cfg(clips=None, glob=None, **kw):
    return SimpleNamespace(source="library", clips=clips, glob=glob, fps_in=30.0, assume_model_order=False, **kw)


@pytest.fixture(scope="module")
def model():
    return load_mjmodel()


@pytest.fixture(scope="module")
def files(tmp_path_factory, model):
    """Three small clips written by the test (never LAFAN1 data): a 3 s CSV, an 8 s npz and another npz."""
    d = tmp_path_factory.mktemp("clips")
    _write_csv(d / "sway.csv", _csv_rows(90))
    generate_builtin(model, "easy_only", seed=3, duration_s=8.0).save(d / "easy.npz")
    generate_builtin(model, "easy_only", seed=4, duration_s=7.0).save(d / "easy4.npz")
    return d


@pytest.mark.parametrize("clips, message", [
    ([{"path": "a.csv", "clip": "dance1_subject1"}], r"motion.clips\[0\]: needs exactly one of path, clip or builtin"),
    ([{"path": "a.csv"}, {"paht": "b.npz"}], r"motion.clips\[1\]: unknown key\(s\) \['paht'\]"),
    ([{"path": "a.csv", "weight": 0}], r"motion.clips\[0\].weight: must be > 0"),
    ([{"path": "a.csv", "start_s": 5, "end_s": 2}], r"motion.clips\[0\]: end_s 2.0 must be after start_s 5.0"),
    ([{"path": "x/a.csv"}, {"path": "y/a.npz"}], r"clip names must be unique, \['a'\] repeat"),
    ([42], r"motion.clips\[0\]: expected a mapping"),
    ([], r"a library needs at least one clip"),
])
def test_bad_entries_are_refused_in_one_line(clips, message):
    with pytest.raises(MotionDataError, match=message) as err:
        library_entries(_cfg(clips))
    assert "\n" not in str(err.value)


def test_entries_name_and_weight_their_clips():
    entries = library_entries(_cfg(["a/walk.csv", {"clip": "dance1_subject1", "weight": 2},
                                    {"builtin": "graded", "seed": 3, "duration_s": 21}]))
    assert [(e.name, e.source, e.weight) for e in entries] == [
        ("walk", "file", 1.0), ("dance1_subject1", "lafan", 2.0), ("graded_3", "builtin", 1.0)]


def test_glob_adds_the_matching_files_in_name_order(files, monkeypatch):
    monkeypatch.chdir(files)
    entries = library_entries(_cfg(glob="*.npz"))
    assert [e.name for e in entries] == ["easy", "easy4"]
    with pytest.raises(MotionDataError, match="motion.glob: 'none/\\*.npz' matches no .csv or .npz file"):
        library_entries(_cfg(glob="none/*.npz"))


def test_a_library_is_its_clips_back_to_back(files, model, tmp_path, monkeypatch):
    monkeypatch.chdir(files)
    cfg = _cfg([{"path": "sway.csv", "end_s": 2.0}, {"path": "easy.npz", "start_s": 1.0}, {"path": "easy4.npz"}])
    lib = load_library(cfg, model, tmp_path / "cache", None, 50.0)
    sizes = [100, 350, 350]  # 2 s of the CSV, 7 s of the first npz, 7 s of the second, at 50 Hz
    assert lib.clip_starts.tolist() == [0, 100, 450] and lib.num_frames == sum(sizes)
    # each clip keeps its segments (the CSV, which has none, gets one named after it)
    assert lib.segments[0].name == "sway" and lib.segments[0].end_s == pytest.approx(2.0)
    bad = _cfg([{"path": "sway.csv"}, {"path": "missing.npz"}])
    with pytest.raises(MotionDataError, match=r"^motion.clips\[1\].path: .*missing.npz: file not found$"):
        load_library(bad, model, tmp_path / "cache", None, 50.0)


@pytest.mark.slow  # trains through the command line (in this process)
def test_three_clips_train_and_evaluate_per_clip(files, model, tmp_path, monkeypatch):
    clips = "motion.clips=[{path: sway.csv}, {path: easy.npz}, {path: easy4.npz, weight: 2}]"
    run = train_in_process(tmp_path / "run", *[o for o in TINY if not o.startswith("motion=")], "motion=library",
                           clips, "sampler.clip_balance=clips", "eval.every_iters=2", "eval.episodes_per_bin=1",
                           cwd=files)
    ev = pd.read_parquet(run / "eval.parquet")
    assert set(ev["clip"]) == {"sway", "easy", "easy4"}
    # bins never span clips: every bin's edges lie inside its clip
    monkeypatch.chdir(files)
    lib = load_library(_cfg(["sway.csv", "easy.npz", "easy4.npz"]), model, tmp_path / "cache", None, 50.0)
    t = [*(lib.clip_starts / lib.fps).tolist(), lib.duration_s]
    bounds = {name: (t[k], t[k + 1]) for k, name in enumerate(["sway", "easy", "easy4"])}
    for row in ev.itertuples():
        lo, hi = bounds[row.clip]
        assert lo - 1e-9 <= row.bin_start_s < row.bin_end_s <= hi + 1e-9
    smp = pd.read_parquet(run / "sampler.parquet")
    last = smp[smp["iteration"] == smp["iteration"].max()]
    share = last.groupby("clip")["probability"].sum()
    assert share.to_dict() == pytest.approx({"sway": 0.25, "easy": 0.25, "easy4": 0.5})
