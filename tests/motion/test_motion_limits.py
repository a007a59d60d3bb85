"""A motion file in the wrong convention is refused, not converted and trained upside down; a motion
too large to build is refused before any work (issue 47)."""

from __future__ import annotations

import numpy as np
import pytest

from bmimic.motion import convert
from bmimic.motion.config import MotionConfig, load_motion
from bmimic.motion.limits import implausibility
from bmimic.motion.motion import Motion
from bmimic.motion.segments import MotionDataError
from bmimic.robot import load_mjmodel
from tests.conftest import SHARED_MOTIONS


@pytest.fixture(scope="module")
def model():
    return load_mjmodel("g1")


@pytest.fixture(scope="module")
def good(model, tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("limits")
    motion = load_motion(MotionConfig(source="builtin", builtin="easy_only", duration_s=7.0), model, cache_dir=folder)
    motion.save(folder / "good.npz")
    with np.load(folder / "good.npz") as f:
        return {k: f[k] for k in f.files}


def _npz(tmp_path, arrays: dict, **changes):
    path = tmp_path / "m.npz"
    np.savez(path, **{**arrays, **changes})
    return path


def _load(path, **cfg):
    return load_motion(MotionConfig(source="file", path=str(path), name="m", **cfg), load_mjmodel("g1"),
                       cache_dir=path.parent / "cache")


def test_a_plausible_motion_loads(good, tmp_path):
    assert _load(_npz(tmp_path, good)).num_frames == good["joint_pos"].shape[0]


@pytest.mark.parametrize("change, words", [
    (lambda d: {"body_quat_w": d["body_quat_w"][..., [1, 2, 3, 0]]}, "is body_quat_w in w x y z order?"),
    (lambda d: {"body_pos_w": d["body_pos_w"] + [0.0, 0.0, 1.0]}, "feet are 1.04 m above the ground"),
    (lambda d: {"body_pos_w": d["body_pos_w"] * 100.0}, "from where the root's pose and the joints put it"),
    (lambda d: {"body_pos_w": d["body_pos_w"] - [0.0, 0.0, 100.0]}, "m below the ground"),
])
def test_an_implausible_npz_is_refused_in_one_line_unless_accepted(good, tmp_path, caplog, change, words):
    path = _npz(tmp_path, good, **change(good))
    with pytest.raises(MotionDataError) as e:
        _load(path)
    text = str(e.value)
    assert "\n" not in text and str(path) in text and words in text and "motion.check_plausible=false" in text
    assert _load(path, check_plausible=False).num_frames >= 2
    assert any("used anyway (motion.check_plausible=false)" in r.getMessage() for r in caplog.records)


def _standing_csv(path, rows: int = 40, w_first: bool = False):
    table = np.zeros((rows, 36))
    table[:, 0], table[:, 2] = np.linspace(0, 0.3, rows), 0.79
    table[:, 3 if w_first else 6] = 1.0  # the identity rotation, its w written first or last
    np.savetxt(path, table, delimiter=",", fmt="%.6f")
    return path


def test_a_csv_with_its_quaternion_w_first_is_refused_by_convert(tmp_path, capsys):
    """The reproducer: a CSV written w x y z converted with exit status 0 and trained upside down."""
    src, out = _standing_csv(tmp_path / "wfirst.csv", w_first=True), tmp_path / "out.npz"
    assert convert.main([str(src), str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "upside down at the first frame" in err and "--allow-implausible" in err
    assert not out.exists()
    assert convert.main([str(src), str(out), "--allow-implausible"]) == 0 and out.exists()
    assert convert.main([str(_standing_csv(tmp_path / "ok.csv")), str(tmp_path / "ok.npz")]) == 0


@pytest.mark.skipif(not (SHARED_MOTIONS / "walk1_subject1.csv").is_file(), reason="LAFAN1 clips not available")
@pytest.mark.parametrize("clip", ["dance1_subject1", "walk1_subject1", "run1_subject2"])
def test_lafan_clips_are_plausible_and_refused_with_the_quaternion_w_first(model, tmp_path, clip):
    data = np.loadtxt(SHARED_MOTIONS / f"{clip}.csv", delimiter=",")[:600]
    np.savetxt(tmp_path / "ok.csv", data, delimiter=",", fmt="%.6f")
    assert implausibility(convert.convert_csv(tmp_path / "ok.csv", model), model) is None
    data[:, 3:7] = data[:, [6, 3, 4, 5]]
    np.savetxt(tmp_path / "w.csv", data, delimiter=",", fmt="%.6f")
    assert implausibility(convert.convert_csv(tmp_path / "w.csv", model), model) is not None


def test_a_motion_too_large_to_build_is_refused_before_any_work(model, good, tmp_path):
    with pytest.raises(MotionDataError, match=r"motion.duration_s: 1e\+06 s is longer than the 3600 s"):
        load_motion(MotionConfig(source="builtin", duration_s=1e6), model, cache_dir=tmp_path)
    with pytest.raises(MotionDataError, match=r"resampled to the control rate .* GiB while it is built"):
        load_motion(MotionConfig(source="file", path=str(_npz(tmp_path, good)), name="m"), model,
                    cache_dir=tmp_path, control_fps=1e12)
    assert not list(tmp_path.glob("cache*/*"))


def test_motion_load_keeps_working_without_a_model(good, tmp_path):
    motion = Motion.load(_npz(tmp_path, good), None)
    assert implausibility(motion) is None  # feet and uprightness need no model
