"""Motion container, npz I/O, name mapping, CSV conversion and its error messages."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bmimic.motion.config import MotionConfig, load_motion
from bmimic.motion.convert import CSV_JOINT_NAMES, convert_csv, main, output_times
from bmimic.motion.kinematics import kinematic_motion
from bmimic.motion.math import (
    angular_velocity_from_quats,
    axis_angle_to_quat,
    quat_mul,
    quat_rotate,
    quat_slerp,
    quat_to_axis_angle,
    quat_to_matrix,
    rotation_angle,
    yaw_quat,
)
from bmimic.motion.motion import NPZ_ARRAY_KEYS, Motion, MotionDataError, Segment
from bmimic.robot import load_mjmodel
from tests.conftest import SHARED_MOTIONS

MOTIONS = SHARED_MOTIONS
DANCE = MOTIONS / "dance1_subject1.csv"
NEUTRAL = {"hip_pitch": -0.312, "knee": 0.669, "ankle_pitch": -0.363}


def _need(path: Path) -> Path:
    if not path.is_file():
        pytest.skip(
            f"LAFAN1 clip {path.name} is absent (not shipped: CC BY-NC-ND); set BMIMIC_LAFAN_DIR to run this"
        )
    return path


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return load_mjmodel("g1")


@pytest.fixture(scope="module")
def dance(model) -> Motion:
    return convert_csv(_need(DANCE), model)


def _csv_rows(n: int = 12) -> np.ndarray:
    """A valid LAFAN1-format table: the neutral stance with a slow sway."""
    rows = np.zeros((n, 36))
    rows[:, 2] = 0.76
    rows[:, 6] = 1.0  # quaternion x, y, z, w
    for k, name in enumerate(CSV_JOINT_NAMES):
        for part, value in NEUTRAL.items():
            if name.endswith(f"{part}_joint"):
                rows[:, 7 + k] = value
    rows[:, 7 + CSV_JOINT_NAMES.index("waist_yaw_joint")] = 0.2 * np.sin(np.arange(n) / 5)
    return rows


def _write_csv(path: Path, rows: np.ndarray) -> Path:
    path.write_text("\n".join(",".join(f"{v:.6f}" for v in r) for r in rows) + "\n")
    return path


def _fk(model, row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Body positions and quaternions of one CSV row by plain MuJoCo forward kinematics."""
    data = mujoco.MjData(model)
    data.qpos[:3] = row[:3]
    data.qpos[3:7] = row[[6, 3, 4, 5]]
    for k, name in enumerate(CSV_JOINT_NAMES):
        data.joint(name).qpos[0] = row[7 + k]
    mujoco.mj_kinematics(model, data)
    return data.xpos[1:].copy(), data.xquat[1:].copy()


# ---------------------------------------------------------------------------------------------------
# quaternion math: known answers and invariants


def test_slerp_halfway_known_answer():
    q = quat_slerp(yaw_quat(0.0), yaw_quat(np.pi / 2), np.array(0.5))
    np.testing.assert_allclose(q, yaw_quat(np.pi / 4), atol=1e-12)
    # takes the short way when the second quaternion has the opposite sign
    q = quat_slerp(yaw_quat(0.0), -yaw_quat(np.pi / 2), np.array(0.5))
    np.testing.assert_allclose(q, yaw_quat(np.pi / 4), atol=1e-12)


def test_angular_velocity_of_constant_spin():
    dt, omega = 0.02, np.array([0.3, -1.2, 2.0])
    quats = axis_angle_to_quat(np.arange(50)[:, None] * dt * omega)
    np.testing.assert_allclose(angular_velocity_from_quats(quats, dt), np.tile(omega, (50, 1)), atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(-1.8, 1.8), min_size=3, max_size=3), st.lists(st.floats(-1, 1), min_size=3, max_size=3)
)
def test_axis_angle_round_trip_and_rotation(rotvec, vec):
    # |rotvec| < pi, where the rotation vector is unique
    rotvec, vec = np.array(rotvec), np.array(vec)
    q = axis_angle_to_quat(rotvec)
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12
    np.testing.assert_allclose(quat_to_axis_angle(q), rotvec, atol=1e-9)
    # composing with the inverse rotation gives back the vector
    back = quat_rotate(quat_mul(axis_angle_to_quat(-rotvec), q), vec)
    np.testing.assert_allclose(back, vec, atol=1e-9)


@settings(max_examples=50, deadline=None)
@given(
    st.lists(st.floats(-1.8, 1.8), min_size=3, max_size=3), st.lists(st.floats(-1.8, 1.8), min_size=3, max_size=3),
    st.lists(st.floats(-1, 1), min_size=3, max_size=3),
)
def test_rotation_matrix_and_angle_agree_with_the_quaternion(rotvec_a, rotvec_b, vec):
    # sim2sim measures orientation error as the angle between rotation matrices
    qa, qb = axis_angle_to_quat(np.array(rotvec_a)), axis_angle_to_quat(np.array(rotvec_b))
    ma = quat_to_matrix(qa)
    np.testing.assert_allclose(ma @ np.array(vec), quat_rotate(qa, np.array(vec)), atol=1e-9)
    np.testing.assert_allclose(ma.T @ ma, np.eye(3), atol=1e-9)
    # the angle of the relative rotation a^-1 b, |axis-angle| in [0, pi]
    relative = quat_to_axis_angle(quat_mul(qa * np.array([1, -1, -1, -1]), qb))
    np.testing.assert_allclose(rotation_angle(ma, quat_to_matrix(qb)), np.linalg.norm(relative), atol=1e-6)


def test_rotation_angle_known_answer():
    quarter_turn_z = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])
    assert rotation_angle(np.eye(3), quat_to_matrix(quarter_turn_z)) == pytest.approx(np.pi / 2)
    assert rotation_angle(np.eye(3), np.diag([1.0, -1.0, -1.0])) == pytest.approx(np.pi)


def test_quaternion_helpers_import_without_mujoco():
    # sim2sim sets MuJoCo's GL backend before mujoco is first imported, after reading these helpers
    code = "import sys, bmimic.motion.math, bmimic.motion; sys.exit('mujoco' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


def test_output_times_match_beyondmimic_arange():
    for n, fin, fout in [(3945, 30, 50), (31, 30, 50), (2, 30, 50), (100, 60, 50), (7, 30, 30)]:
        expected = np.arange(0, (n - 1) / fin, 1 / fout)
        assert len(output_times(n, fin, fout)) == len(expected)


# ---------------------------------------------------------------------------------------------------
# conversion of the real clips


def test_converted_bodies_equal_fk_of_csv_rows(model, dance):
    rows = np.loadtxt(DANCE, delimiter=",")
    assert dance.fps == 50 and dance.num_frames == len(np.arange(0, (len(rows) - 1) / 30, 1 / 50))
    assert dance.body_names[0] == "pelvis" and len(dance.body_names) == model.nbody - 1
    # t = k/10 s is input row 3k and output frame 5k
    for k in (0, 1, 7, 123, 500, (dance.num_frames - 1) // 5):
        pos, quat = _fk(model, rows[3 * k])
        np.testing.assert_allclose(dance.body_pos_w[5 * k], pos, atol=1e-4)
        dots = np.abs(np.sum(dance.body_quat_w[5 * k] * quat, axis=-1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-5)


def test_converted_velocities_match_finite_differences(dance):
    dt = 1 / dance.fps
    lin_fd = np.gradient(dance.body_pos_w.astype(np.float64), dt, axis=0)
    # The root is differentiated directly: the same numbers.
    np.testing.assert_allclose(dance.body_lin_vel_w[:, 0], lin_fd[:, 0], atol=1e-3)
    # Other bodies: J(q) dq/dt and d/dt FK(q) differ only by O(dt^2) terms, which mocap jerks make
    # large at a few frames; a wrong frame, sign or point would be off by ~100% everywhere.
    speed = np.linalg.norm(dance.body_lin_vel_w, axis=-1)
    rel = np.linalg.norm(dance.body_lin_vel_w - lin_fd, axis=-1) / (speed + 0.05)
    assert np.median(rel) < 0.005 and np.percentile(rel, 99) < 0.1
    ang_fd = np.stack(
        [angular_velocity_from_quats(dance.body_quat_w[:, b].astype(np.float64), dt) for b in range(30)], 1
    )
    spin = np.linalg.norm(dance.body_ang_vel_w, axis=-1)
    rel = np.linalg.norm(dance.body_ang_vel_w - ang_fd, axis=-1) / (spin + 0.1)
    assert np.median(rel) < 0.005 and np.percentile(rel, 99) < 0.1
    np.testing.assert_allclose(
        dance.joint_vel, np.gradient(dance.joint_pos.astype(np.float64), dt, axis=0), atol=1e-3
    )


def test_window_equals_slice_of_full_clip(model, dance, tmp_path):
    cfg = MotionConfig(name="dance", source="file", path=str(DANCE), start_s=10.0, end_s=20.0)
    win = load_motion(cfg, model, cache_dir=tmp_path)
    assert win.num_frames == 500 and win.duration_s == pytest.approx(10.0)
    for key in NPZ_ARRAY_KEYS:
        np.testing.assert_array_equal(getattr(win, key), getattr(dance, key)[500:1000])
    assert win.segments == [Segment("dance1_subject1", 0.0, 10.0, "unknown")]
    assert len(list(tmp_path.glob("*.npz"))) == 1  # converted once and cached
    again = load_motion(cfg, model, cache_dir=tmp_path)
    np.testing.assert_array_equal(again.body_pos_w, win.body_pos_w)


def test_frames_option_selects_rows(model, tmp_path):
    rows = np.loadtxt(_need(DANCE), delimiter=",")
    part = convert_csv(DANCE, model, frames=(31, 330))
    assert part.num_frames == len(np.arange(0, 299 / 30, 1 / 50))
    pos, _ = _fk(model, rows[30])
    np.testing.assert_allclose(part.body_pos_w[0], pos, atol=1e-4)
    pos, _ = _fk(model, rows[30 + 3 * 20])
    np.testing.assert_allclose(part.body_pos_w[100], pos, atol=1e-4)


def test_cli_writes_npz_that_loads(model, tmp_path, capsys):
    src = _write_csv(tmp_path / "sway.csv", _csv_rows(60))
    out = tmp_path / "sway.npz"
    assert main([str(src), str(out), "--fps-in", "30", "--fps-out", "50"]) == 0
    motion = Motion.load(out, model)
    assert motion.num_frames == len(np.arange(0, 59 / 30, 1 / 50))
    assert motion.joint_names == [model.joint(j).name for j in range(1, model.njnt)]
    assert "wrote" in capsys.readouterr().out


# ---------------------------------------------------------------------------------------------------
# malformed input: every case names file, row and column


def _bad(kind: str) -> tuple[str, np.ndarray | None]:
    rows = _csv_rows()
    text = None
    if kind == "columns":
        text = "\n".join(",".join(map(str, r[: (35 if i == 1 else 36)])) for i, r in enumerate(rows))
    elif kind == "text":
        lines = [",".join(map(str, r)) for r in rows]
        cells = lines[2].split(",")
        cells[4] = "abc"
        lines[2] = ",".join(cells)
        text = "\n".join(lines)
    elif kind == "header":
        text = ",".join(f"c{i}" for i in range(36)) + "\n" + "\n".join(",".join(map(str, r)) for r in rows)
    elif kind == "empty":
        text = "\n\n"
    elif kind == "nan":
        rows[1, 7] = np.nan
    elif kind == "inf":
        rows[4, 0] = np.inf
    elif kind == "quat":
        rows[1, 3:7] = (0.0, 0.0, 0.0, 0.99)
    elif kind == "limit":
        rows[1, 7 + CSV_JOINT_NAMES.index("left_knee_joint")] = 3.2
    elif kind == "short":
        rows = rows[:1]
    elif kind == "huge":  # finite, so the reader takes it; float32, which stores the motion, cannot
        rows[2, 0] = 1e39
    return text, rows


MALFORMED = [
    # kind, convert kwargs, fragments the message must contain
    ("columns", {}, ["row 2, column 36", "35 columns"]),
    ("text", {}, ["row 3, column 5", "'abc' is not a number"]),
    ("header", {}, ["row 1, column 1", "header"]),
    ("empty", {}, ["file is empty"]),
    ("nan", {}, ["row 2, column 8", "not finite"]),
    ("inf", {}, ["row 5, column 1", "not finite"]),
    ("quat", {}, ["row 2, column 4", "norm 0.99"]),
    ("limit", {}, ["row 2, column 11", "left_knee_joint", "outside its range"]),
    ("short", {}, ["fewer than 2 frames"]),
    ("huge", {}, ["body_pos_w at frame", "beyond float32's range"]),  # resampled: frame and value move
    ("ok", {"fps_out": 0.0}, ["fps_in and fps_out must be positive"]),
    ("ok", {"fps_in": -30.0}, ["fps_in and fps_out must be positive"]),
    ("missing", {}, ["file not found"]),
]


@pytest.mark.parametrize(
    "kind, kwargs, fragments", MALFORMED, ids=[f"{m[0]}-{i}" for i, m in enumerate(MALFORMED)]
)
def test_malformed_csv_is_refused_with_location(model, tmp_path, capsys, kind, kwargs, fragments):
    path = tmp_path / f"{kind}.csv"
    if kind != "missing":
        text, rows = _bad(kind)
        if text is not None:
            path.write_text(text)
        else:
            _write_csv(path, rows)
    with pytest.raises(MotionDataError) as err:
        convert_csv(path, model, **kwargs)
    message = str(err.value)
    assert message.startswith(str(path)) and "\n" not in message
    for fragment in fragments:
        assert fragment in message
    # the CLI prints one line and exits with 2
    argv = [str(path), str(tmp_path / "out.npz")]
    for key, flag in (("fps_in", "--fps-in"), ("fps_out", "--fps-out")):
        if key in kwargs:
            argv += [flag, str(kwargs[key])]
    assert main(argv) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}")
    assert not (tmp_path / "out.npz").exists()


def test_frames_out_of_range_is_refused(model, tmp_path):
    path = _write_csv(tmp_path / "ok.csv", _csv_rows(12))
    with pytest.raises(MotionDataError, match="--frames 5 40"):
        convert_csv(path, model, frames=(5, 40))


def test_clip_shorter_than_two_bins_is_refused(model, tmp_path):
    path = _write_csv(tmp_path / "short.csv", _csv_rows(40))  # 1.3 s
    cfg = MotionConfig(name="short", source="file", path=str(path))
    with pytest.raises(MotionDataError, match="shorter than two time bins"):
        load_motion(cfg, model, cache_dir=tmp_path / "cache", bin_size_s=1.0)
    assert load_motion(cfg, model, cache_dir=tmp_path / "cache", bin_size_s=0.5).num_frames == 65


def test_load_motion_config_errors(model, tmp_path):
    with pytest.raises(MotionDataError, match="motion.path: required"):
        load_motion(MotionConfig(source="file"), model, cache_dir=tmp_path)
    with pytest.raises(MotionDataError, match="motion.source"):
        load_motion(MotionConfig(source="web"), model, cache_dir=tmp_path)
    with pytest.raises(MotionDataError, match="file not found"):
        load_motion(MotionConfig(source="file", path=str(tmp_path / "nope.csv")), model, cache_dir=tmp_path)


# ---------------------------------------------------------------------------------------------------
# npz: names decide the mapping; nameless or mismatched files are refused


@pytest.fixture(scope="module")
def small(model) -> Motion:
    rows = _csv_rows(40)
    rows[:, 0] = np.linspace(0.0, 0.3, 40)
    return kinematic_motion(
        model,
        50.0,
        rows[:, :3],
        rows[:, [6, 3, 4, 5]],
        rows[:, 7:],
        CSV_JOINT_NAMES,
        [Segment("sway", 0, 0.8, "easy")],
    )


def _rewrite(src: Path, dst: Path, **changes) -> Path:
    with np.load(src) as data:
        content = {k: data[k] for k in data.files}
    for key, value in changes.items():
        if value is None:
            content.pop(key)
        else:
            content[key] = value
    np.savez(dst, **content)
    return dst


def test_npz_round_trip(model, small, tmp_path):
    small.save(tmp_path / "m.npz")
    back = Motion.load(tmp_path / "m.npz", model)
    for key in NPZ_ARRAY_KEYS:
        np.testing.assert_array_equal(getattr(back, key), getattr(small, key))
    assert back.segments == small.segments and back.fps == 50.0 and list(back.clip_starts) == [0]
    assert not list(tmp_path.glob("*.tmp"))


def test_npz_in_another_body_order_is_mapped_by_name(model, small, tmp_path):
    small.save(tmp_path / "m.npz")
    perm = np.random.default_rng(0).permutation(len(small.body_names))
    jperm = np.random.default_rng(1).permutation(len(small.joint_names))
    changes = {k: getattr(small, k)[:, perm] for k in NPZ_ARRAY_KEYS if k.startswith("body")}
    changes.update({k: getattr(small, k)[:, jperm] for k in ("joint_pos", "joint_vel")})
    changes["body_names"] = np.array(small.body_names)[perm]
    changes["joint_names"] = np.array(small.joint_names)[jperm]
    back = Motion.load(_rewrite(tmp_path / "m.npz", tmp_path / "perm.npz", **changes), model)
    for key in NPZ_ARRAY_KEYS:
        np.testing.assert_array_equal(getattr(back, key), getattr(small, key))


def test_npz_with_wrong_names_is_refused(model, small, tmp_path):
    small.save(tmp_path / "m.npz")
    names = list(small.body_names)
    names[names.index("torso_link")] = "torso"
    bad = _rewrite(tmp_path / "m.npz", tmp_path / "bad.npz", body_names=np.array(names))
    with pytest.raises(MotionDataError, match=r"bad.npz: .*missing bodies \['torso_link'\]"):
        Motion.load(bad, model)


def test_npz_without_names_is_refused_unless_assumed(model, small, tmp_path):
    small.save(tmp_path / "m.npz")
    nameless = _rewrite(tmp_path / "m.npz", tmp_path / "mjlab.npz", body_names=None, joint_names=None)
    with pytest.raises(MotionDataError, match="assume_model_order=True"):
        Motion.load(nameless, model)
    back = Motion.load(nameless, model, assume_model_order=True)
    np.testing.assert_array_equal(back.body_pos_w, small.body_pos_w)

    # Isaac Lab's breadth-first file: 40 bodies, no names; refused even when the order is "assumed"
    pad = {
        k: np.concatenate([getattr(small, k)] * 2, axis=1)[:, :40]
        for k in NPZ_ARRAY_KEYS
        if k.startswith("body")
    }
    isaac = _rewrite(nameless, tmp_path / "isaac.npz", **pad)
    for assume in (False, True):
        with pytest.raises(MotionDataError, match="40 bodies.*Isaac Lab"):
            Motion.load(isaac, model, assume_model_order=assume)


def test_npz_with_missing_key_or_bad_quaternion_is_refused(model, small, tmp_path):
    small.save(tmp_path / "m.npz")
    with pytest.raises(MotionDataError, match="missing key.*body_ang_vel_w"):
        Motion.load(_rewrite(tmp_path / "m.npz", tmp_path / "a.npz", body_ang_vel_w=None), model)
    quat = small.body_quat_w.copy()
    quat[3, 5] *= 2.0
    with pytest.raises(MotionDataError, match="frame 3 has norm 2"):
        Motion.load(_rewrite(tmp_path / "m.npz", tmp_path / "b.npz", body_quat_w=quat), model)
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(MotionDataError, match="not a readable npz"):
        Motion.load(tmp_path / "junk.npz", model)


# ---------------------------------------------------------------------------------------------------
# windows and libraries


def test_window_clips_and_shifts_segments(small):
    motion = dataclasses.replace(
        small, segments=[Segment("a", 0.0, 0.3, "easy"), Segment("b", 0.3, 0.8, "hard")]
    )
    win = motion.window(0.2, 0.5)
    assert win.num_frames == 15
    assert win.segments == [
        Segment("a", 0.0, pytest.approx(0.1), "easy"),
        Segment("b", pytest.approx(0.1), 0.3, "hard"),
    ]
    np.testing.assert_array_equal(win.joint_pos, motion.joint_pos[10:25])
    with pytest.raises(MotionDataError, match="window"):
        motion.window(0.5, 2.0)


def test_concatenate_builds_a_library(small):
    lib = Motion.concatenate([small, small.window(0.0, 0.5)])
    assert lib.num_frames == 65 and list(lib.clip_starts) == [0, 40]
    assert [s.start_s for s in lib.segments] == [0.0, pytest.approx(0.8)]
    np.testing.assert_array_equal(lib.body_pos_w[40:], small.body_pos_w[:25])
    win = lib.window(0.6, 1.2)
    assert list(win.clip_starts) == [0, 10]
    with pytest.raises(MotionDataError, match="share fps"):
        Motion.concatenate([small, dataclasses.replace(small, fps=30.0)])


def test_reference_motion_holds_the_tracked_bodies_and_clip_boundaries(small):
    """The device view of a two-clip library: tracked bodies in the requested order, the root's state,
    and every frame mapped to the end of its own clip."""
    import torch

    from bmimic.motion.reference import ReferenceMotion

    lib = Motion.concatenate([small, small.window(0.0, 0.5)])  # clips [0, 40) and [40, 65)
    tracked = [lib.body_names[5], lib.body_names[2]]
    ref = ReferenceMotion(lib, tracked, lib.body_names[0])
    assert ref.num_frames == 65 and ref.fps == lib.fps and ref.body_names == tracked
    assert ref.clip_starts.tolist() == [0, 40] and ref.clip_ends.tolist() == [40, 65]
    assert ref.frame_clip_end.tolist() == [40] * 40 + [65] * 25
    np.testing.assert_array_equal(ref.body_pos[:, 0].numpy(), lib.body_pos_w[:, 5])
    np.testing.assert_array_equal(ref.body_quat[:, 1].numpy(), lib.body_quat_w[:, 2])
    np.testing.assert_array_equal(ref.root_lin_vel.numpy(), lib.body_lin_vel_w[:, 0])
    frames = torch.tensor([3, 41])
    qpos = ref.qpos(frames).numpy()
    assert qpos.shape == (2, 7 + len(lib.joint_names))
    np.testing.assert_array_equal(qpos[:, :3], lib.body_pos_w[[3, 41], 0])
    np.testing.assert_array_equal(qpos[:, 3:7], lib.body_quat_w[[3, 41], 0])
    np.testing.assert_array_equal(qpos[:, 7:], lib.joint_pos[[3, 41]])
    with pytest.raises(MotionDataError, match="no bodies named"):
        ReferenceMotion(lib, ["no_such_body"], lib.body_names[0])


def test_resample_known_answers():
    """Linear tracks stay linear, orientations follow the slerp, the grid ends before the last frame."""
    from bmimic.motion.motion import Motion, MotionDataError, Segment

    t = np.arange(5) / 10.0  # 5 frames at 10 fps, 0..0.4 s
    yaw = t * (np.pi / 2) / 0.4  # 0..90 degrees about z
    quat = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], axis=-1)[:, None]
    m = Motion(fps=10, joint_pos=t[:, None], joint_vel=np.ones((5, 1)), body_pos_w=np.stack([t, 2 * t, 0 * t], -1)[:, None],
               body_quat_w=quat, body_lin_vel_w=np.zeros((5, 1, 3)), body_ang_vel_w=np.zeros((5, 1, 3)),
               joint_names=["j"], body_names=["b"], segments=[Segment("all", 0.0, 0.5, "easy")])
    r = m.resample(40)
    times = np.arange(16) / 40.0  # strictly below the last frame's 0.4 s
    assert r.fps == 40 and r.num_frames == 16
    np.testing.assert_allclose(r.joint_pos[:, 0], times, atol=1e-6)
    np.testing.assert_allclose(r.body_pos_w[:, 0, 1], 2 * times, atol=1e-6)
    half = r.body_quat_w[8, 0]  # t = 0.2 s: 45 degrees
    np.testing.assert_allclose(half, [np.cos(np.pi / 8), 0, 0, np.sin(np.pi / 8)], atol=1e-6)
    assert r.segments == [Segment("all", 0.0, 0.4, "easy")]
    assert m.resample(10) is m
    lib = Motion.concatenate([m, m])
    with pytest.raises(MotionDataError, match="2 clips"):
        lib.resample(40)


def test_a_value_beyond_float32_is_refused_where_it_is_not_called_not_finite():
    t = np.linspace(0.0, 1.0, 5)
    joint_pos = t[:, None].copy()
    joint_pos[2, 0] = -1e39
    with pytest.raises(MotionDataError, match=r"^joint_pos at frame 2 is -1e\+39, beyond float32's range"):
        Motion(fps=10, joint_pos=joint_pos, joint_vel=np.ones((5, 1)), body_pos_w=np.zeros((5, 1, 3)),
               body_quat_w=np.tile([1.0, 0.0, 0.0, 0.0], (5, 1, 1)), body_lin_vel_w=np.zeros((5, 1, 3)),
               body_ang_vel_w=np.zeros((5, 1, 3)), joint_names=["j"], body_names=["b"])
