"""The embedded default motion is kinematically sound, deterministic per seed, and labelled."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from bmimic.motion.builtin import FEET, build_plan, generate_builtin
from bmimic.motion.config import MotionConfig, load_motion
from bmimic.motion.motion import MotionDataError
from bmimic.robot import load_mjmodel

PENETRATION_TOL_M = 0.005
SLIDE_TOL_M = 0.01


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return load_mjmodel("g1")


@pytest.fixture(scope="module")
def graded(model):
    return generate_builtin(model, "graded", seed=0, duration_s=30.0), build_plan(model, "graded", 0, 30.0)


def _cross2(a, b) -> np.ndarray:
    """z of the cross product of 2-D vectors (np.cross on 2-D vectors is deprecated)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _hull_contains(points: np.ndarray, p: np.ndarray) -> bool:
    """Point in the convex hull of 2-D points (Andrew's monotone chain, counter-clockwise)."""
    pts = sorted(map(tuple, points))

    def half(seq):
        out = []
        for q in seq:
            while len(out) >= 2 and _cross2(np.subtract(out[-1], out[-2]), np.subtract(q, out[-2])) <= 0:
                out.pop()
            out.append(q)
        return out[:-1]

    hull = np.array(half(pts) + half(pts[::-1]))
    edges = np.roll(hull, -1, axis=0) - hull
    return bool(np.all(_cross2(edges, p - hull) >= -1e-12))


def _foot_points(model, body: int) -> tuple[np.ndarray, np.ndarray]:
    """Collision sphere centres and radii of a foot, in the body frame (the G1's soles are spheres)."""
    geoms = [
        g
        for g in range(model.ngeom)
        if model.geom_bodyid[g] == body and (model.geom_contype[g] or model.geom_conaffinity[g])
    ]
    assert geoms and all(model.geom_type[g] == mujoco.mjtGeom.mjGEOM_SPHERE for g in geoms)
    return model.geom_pos[geoms], model.geom_size[geoms, 0]


def kinematic_report(model, motion, contact):
    """Lowest foot point, largest stance slide, frames with the COM outside the support polygon."""
    data = mujoco.MjData(model)
    feet = [model.body(f).id for f in FEET]
    local = [_foot_points(model, b) for b in feet]
    bi = [motion.body_names.index(f) for f in FEET]
    joint_adr = [model.joint(j).qposadr[0] for j in motion.joint_names]
    lowest, outside = np.inf, []
    for t in range(motion.num_frames):
        data.qpos[:3] = motion.body_pos_w[t, 0]
        data.qpos[3:7] = motion.body_quat_w[t, 0]
        data.qpos[joint_adr] = motion.joint_pos[t]
        mujoco.mj_kinematics(model, data)
        mujoco.mj_comPos(model, data)
        support = []
        for k, body in enumerate(feet):
            rot = data.xmat[body].reshape(3, 3)
            pts = data.xpos[body] + local[k][0] @ rot.T
            lowest = min(lowest, float((pts[:, 2] - local[k][1]).min()))
            if contact[t, k]:
                support.append(pts[:, :2])
        if not _hull_contains(np.concatenate(support), data.subtree_com[1, :2]):
            outside.append(t)
    slide = 0.0
    for k in range(2):
        c = np.concatenate([[False], contact[:, k], [False]]).astype(int)
        for a, b in zip(np.flatnonzero(np.diff(c) == 1), np.flatnonzero(np.diff(c) == -1), strict=True):
            pos = motion.body_pos_w[a:b, bi[k]]
            slide = max(slide, float(np.abs(pos - pos[0]).max()))
    return lowest, slide, outside


def test_graded_motion_is_kinematically_sound(model, graded):
    motion, plan = graded
    assert motion.fps == 50.0 and motion.num_frames == 1500 and motion.duration_s == 30.0
    assert motion.body_names[0] == "pelvis" and len(motion.joint_names) == 29
    assert all(np.isfinite(getattr(motion, k)).all() for k in ("joint_pos", "body_pos_w", "body_lin_vel_w"))
    lowest, slide, outside = kinematic_report(model, motion, plan.contact)
    assert lowest > -PENETRATION_TOL_M
    assert slide < SLIDE_TOL_M
    assert outside == []
    # every frame has a planted foot; planted feet touch the floor (within 5 mm)
    assert plan.contact.any(axis=1).all()


def test_joint_limits_respected(model, graded):
    motion, _ = graded
    for k, name in enumerate(motion.joint_names):
        low, high = model.jnt_range[model.joint(name).id]
        assert low - 1e-6 <= motion.joint_pos[:, k].min() and motion.joint_pos[:, k].max() <= high + 1e-6, (
            name
        )


def test_motion_is_smooth(graded):
    motion, _ = graded
    # smooth ramps between segments: no jumps in joint angles or pelvis position between frames
    assert np.abs(np.diff(motion.joint_pos, axis=0)).max() < 0.25
    assert np.linalg.norm(np.diff(motion.body_pos_w[:, 0], axis=0), axis=-1).max() < 0.03


def test_segments_cover_duration_in_graded_order(graded):
    motion, plan = graded
    segs = motion.segments
    assert segs[0].start_s == 0.0 and segs[-1].end_s == pytest.approx(motion.duration_s)
    assert all(a.end_s == pytest.approx(b.start_s) for a, b in zip(segs, segs[1:], strict=False))
    rank = {"easy": 0, "medium": 1, "hard": 2}
    assert [rank[s.difficulty] for s in segs] == sorted(rank[s.difficulty] for s in segs)
    assert {s.name for s in segs} == {
        "stand",
        "arm_wave",
        "torso_twist",
        "squat",
        "weight_shift",
        "step_in_place",
        "single_leg_swing",
        "kick",
        "fast_turn",
    }
    # difficulty shows in the plan: easy segments keep both feet down, hard ones stand on one leg
    single = ~plan.contact.all(axis=1)
    for s in segs:
        frames = slice(int(round(s.start_s * 50)), int(round(s.end_s * 50)))
        if s.difficulty == "easy":
            assert not single[frames].any(), s.name
        if s.difficulty == "hard":
            assert single[frames].mean() > 0.2, s.name


def test_deterministic_per_seed_and_varies_with_seed(model):
    a = generate_builtin(model, "easy_only", seed=3, duration_s=10.0)
    b = generate_builtin(model, "easy_only", seed=3, duration_s=10.0)
    c = generate_builtin(model, "easy_only", seed=4, duration_s=10.0)
    np.testing.assert_array_equal(a.body_pos_w, b.body_pos_w)
    assert a.segments == b.segments
    assert np.abs(a.joint_pos - c.joint_pos).max() > 0.05
    p0, p1 = build_plan(model, "graded", 0, 30.0), build_plan(model, "graded", 1, 30.0)
    np.testing.assert_array_equal(p0.targets.foot_pos, build_plan(model, "graded", 0, 30.0).targets.foot_pos)
    assert np.abs(p0.targets.joint_pos - p1.targets.joint_pos).max() > 0.05


def test_duration_scales_the_motion(model):
    for duration, cycles in ((22.5, 1), (60.0, 2), (40.0, 1)):
        plan = build_plan(model, "graded", 0, duration)
        assert plan.targets.pelvis_z.shape[0] == int(round(duration * 50))
        assert plan.segments[-1].end_s == pytest.approx(duration)
        assert len(plan.segments) == 9 * cycles
    with pytest.raises(MotionDataError, match="too short"):
        build_plan(model, "graded", 0, 10.0)
    with pytest.raises(MotionDataError, match="unknown built-in"):
        build_plan(model, "salsa", 0, 30.0)


def test_load_motion_generates_once_then_uses_cache(model, tmp_path):
    cfg = MotionConfig(
        name="easy", source="builtin", builtin="easy_only", seed=2, duration_s=10.0, start_s=1.0
    )
    first = load_motion(cfg, model, cache_dir=tmp_path)
    cached = list(tmp_path.glob("builtin-easy_only-*.npz"))
    assert len(cached) == 1 and first.num_frames == 450
    stamp = cached[0].stat().st_mtime_ns
    again = load_motion(cfg, model, cache_dir=tmp_path)
    assert cached[0].stat().st_mtime_ns == stamp
    np.testing.assert_array_equal(again.body_pos_w, first.body_pos_w)
    assert again.segments == first.segments and again.segments[0].start_s == 0.0


@pytest.mark.slow
@pytest.mark.parametrize("seed, duration", [(1, 30.0), (2, 30.0), (3, 60.0), (4, 22.5)])
def test_other_seeds_and_durations_are_sound(model, seed, duration):
    motion = generate_builtin(model, "graded", seed, duration)
    plan = build_plan(model, "graded", seed, duration)
    lowest, slide, outside = kinematic_report(model, motion, plan.contact)
    assert lowest > -PENETRATION_TOL_M and slide < SLIDE_TOL_M and outside == []
