"""Your own motion (issue 75): the synthetic example clip is a CSV bmimic reads as documented, and a clip
whose frame rate cannot be right is refused in one line naming it."""

from __future__ import annotations

import numpy as np
import pytest

from bmimic.motion import convert, example
from bmimic.motion.config import MotionConfig, load_motion
from bmimic.motion.limits import JOINT_SPEED_P99_RADPS
from bmimic.motion.segments import MotionDataError
from bmimic.robot import load_mjmodel
from tests.conftest import SHARED_MOTIONS


@pytest.fixture(scope="module")
def model():
    return load_mjmodel("g1")


def test_the_example_clip_is_a_csv_of_the_documented_format(tmp_path, model, capsys):
    out = tmp_path / "my_clip.csv"
    assert example.main([str(out), "--seconds", "4", "--fps", "30"]) == 0
    assert f"motion.path={out}" in capsys.readouterr().out
    table = np.loadtxt(out, delimiter=",")
    assert table.shape == (120, 36)
    assert np.allclose(np.linalg.norm(table[:, 3:7], axis=1), 1.0, atol=1e-5)
    assert abs(table[0, 6]) > 0.9  # x y z w: the upright first frame's w is last
    motion = load_motion(MotionConfig(source="file", path=str(out), name="mine", fps_in=30.0), model,
                         cache_dir=tmp_path / "cache")
    assert motion.duration_s == pytest.approx(4.0, abs=0.05)
    # an existing file is replaced only with --force, and stays as it was otherwise
    before = out.read_bytes()
    assert example.main([str(out), "--seconds", "1"]) == 2
    assert "exists; pass --force" in capsys.readouterr().err and out.read_bytes() == before


def _fast_csv(path, rows: int = 90):
    """A standing G1 whose left knee swings 1.8 rad every frame: 54 rad/s at 30 fps, 5.4 at 3 fps."""
    table = np.zeros((rows, 36))
    table[:, 2], table[:, 6] = 0.79, 1.0
    knee = convert.CSV_JOINT_NAMES.index("left_knee_joint")
    table[:, 7 + knee] = 0.2 + 1.8 * (np.arange(rows) % 2)
    np.savetxt(path, table, delimiter=",", fmt="%.6f")
    return path


def test_a_clip_faster_than_any_human_is_refused_in_one_line(tmp_path, model, capsys):
    src, out = _fast_csv(tmp_path / "fast.csv"), tmp_path / "fast.npz"
    assert convert.main([str(src), str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: ") and str(src) in err and "frame rate" in err
    assert not out.exists()
    with pytest.raises(MotionDataError, match="motion.fps_in"):
        load_motion(MotionConfig(source="file", path=str(src), name="fast", fps_in=30.0), model, cache_dir=tmp_path / "c")
    # the same rows at their true rate (10 times slower) are a plausible reference
    assert convert.main([str(src), str(out), "--fps-in", "3"]) == 0


@pytest.mark.skipif(not (SHARED_MOTIONS / "dance1_subject1.csv").is_file(), reason="LAFAN1 clips not available")
def test_a_dance_read_at_6_times_its_frame_rate_is_refused(tmp_path, model):
    """Every 6th frame of the 30 fps dance is a 5 fps clip: read as 30 fps it dances 6 times too fast (at
    4 times, 38 rad/s, it passes: the check catches gross errors, not every wrong rate).
    (The other way, a 120 fps clip read as 30 fps, is a slow but possible motion: nothing can tell.)"""
    data = np.loadtxt(SHARED_MOTIONS / "dance1_subject1.csv", delimiter=",")[::6]
    np.savetxt(tmp_path / "d5.csv", data, delimiter=",", fmt="%.6f")
    assert convert.main([str(tmp_path / "d5.csv"), str(tmp_path / "ok.npz"), "--fps-in", "5"]) == 0
    assert convert.main([str(tmp_path / "d5.csv"), str(tmp_path / "bad.npz"), "--fps-in", "30"]) == 2
    assert not (tmp_path / "bad.npz").exists()
    assert JOINT_SPEED_P99_RADPS == 40.0  # the README and the error line quote it through LAFAN1's range
