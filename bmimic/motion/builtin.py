"""Built-in reference motions, generated in code so training runs without any downloaded data.

"graded" (the default) is about 30 s of segments of rising difficulty, in cycles of
easy (standing, arm waves, torso twists) -> medium (squats, weight shifts, stepping in place) ->
hard (single-leg balance with a leg swing, a quick kick, a fast stepping turn). "easy_only" repeats
the easy segments (for quick tests). A seed varies amplitudes, frequencies, sides and the order within
each difficulty level; `duration_s` stretches the segments or repeats the cycle.

Every segment starts and ends in the same neutral stance, with smooth (C2) ramps, so segments join
without jumps. Per-frame targets (feet, whole-body centre of mass over the support feet, pelvis
height and orientation, waist and arm angles) are solved by `WholeBodyIK` on the robot model, then
turned into a `Motion` by finite differences and forward kinematics like a converted clip.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from bmimic.motion.builtin_builder import (
    FEET,
    FPS,
    LEG_JOINTS,
    NEUTRAL_LEGS,
    PELVIS,
    UPPER_JOINTS,
    SegmentBuilder,
    Stance,
    neutral_stance,
    rot2,
)
from bmimic.motion.builtin_segments import LEVELS, SegmentFn
from bmimic.motion.ik import TASK_SLICES, IKTargets, WholeBodyIK
from bmimic.motion.kinematics import kinematic_motion
from bmimic.motion.math import quat_from_euler_zyx, yaw_quat
from bmimic.motion.model import free_joint_qposadr, model_joint_names
from bmimic.motion.motion import Motion
from bmimic.motion.segments import MotionDataError, Segment

GENERATOR_VERSION = "1"
"""Part of the cache key; bump whenever the generated trajectories change."""
# Largest IK task error accepted (m or rad); beyond this a target was unreachable (a generator bug).
MAX_IK_ERROR = 2e-3
MAX_SWING_ERROR_M = 0.01
BUILTIN_MOTIONS: dict[str, tuple[str, ...]] = {
    "graded": ("easy", "medium", "hard"),
    "easy_only": ("easy",),
}
MIN_SCALE = 0.7
"""Segments may shrink to 70% of their nominal duration; shorter ones cannot fit their steps."""


@dataclasses.dataclass
class Plan:
    """Per-frame targets of a built-in motion before inverse kinematics."""

    segments: list[Segment]
    targets: IKTargets
    contact: np.ndarray
    """[T, 2] whether the left/right foot is planted."""
    stance: Stance


def build_plan(
    mjmodel: mujoco.MjModel, name: str = "graded", seed: int = 0, duration_s: float = 30.0
) -> Plan:
    """Lay out the segments and their per-frame targets (deterministic for a seed)."""
    if name not in BUILTIN_MOTIONS:
        raise MotionDataError(
            f"motion.builtin: unknown built-in motion {name!r}; choose from {sorted(BUILTIN_MOTIONS)}"
        )
    levels = BUILTIN_MOTIONS[name]
    nominal = sum(d for level in levels for _, _, d in LEVELS[level])
    cycles = max(1, int(round(duration_s / nominal)))
    scale = duration_s / (cycles * nominal)
    if scale < MIN_SCALE:
        raise MotionDataError(
            f"motion.duration_s: {duration_s} s is too short for built-in {name!r} "
            f"(needs >= {MIN_SCALE * nominal:.1f} s)"
        )
    rng = np.random.default_rng(seed)
    layout: list[tuple[str, str, SegmentFn, float]] = []
    for _ in range(cycles):
        for level in levels:
            for i in rng.permutation(len(LEVELS[level])):
                seg_name, fn, dur = LEVELS[level][i]
                layout.append((seg_name, level, fn, dur * scale))
    bounds = np.round(np.cumsum([0.0] + [d for *_, d in layout]) * FPS).astype(int)
    bounds[-1] = int(round(duration_s * FPS))

    stance = neutral_stance(mjmodel)
    frame = np.zeros(3)
    parts, segments = [], []
    for (seg_name, level, fn, _), a, z in zip(layout, bounds[:-1], bounds[1:], strict=True):
        builder = SegmentBuilder(stance, frame, (z - a) / FPS, rng)
        fn(builder)
        part = builder.render()
        part["pelvis_yaw"] = part["foot_yaw"].mean(axis=1)
        parts.append(part)
        segments.append(Segment(seg_name, a / FPS, z / FPS, level))
        frame = builder.end_frame
    plan = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return Plan(segments=segments, targets=_ik_targets(plan, stance), contact=plan["contact"], stance=stance)


def _ik_targets(plan: dict[str, np.ndarray], stance: Stance) -> IKTargets:
    foot_yaw = plan["foot_yaw"]
    centres = np.stack(
        [
            plan["foot_pos"][:, k, :2] + np.einsum("tij,j->ti", rot2(foot_yaw[:, k]), stance.feet[k].centre)
            for k in range(2)
        ],
        axis=1,
    )
    w = plan["weight"][:, None]
    pelvis = plan["pelvis"]
    return IKTargets(
        foot_pos=plan["foot_pos"],
        foot_quat=quat_from_euler_zyx(0.0, plan["foot_pitch"], foot_yaw),
        com_xy=(1.0 - w) * centres[:, 0] + w * centres[:, 1],
        pelvis_z=stance.pelvis_z_m + pelvis[:, 0],
        pelvis_quat=quat_from_euler_zyx(pelvis[:, 1], pelvis[:, 2], plan["pelvis_yaw"]),
        joint_pos=plan["upper"],
        foot_ori_weight=plan["foot_ori_weight"],
    )


def _check_ik(name: str, plan: Plan, errors: np.ndarray) -> None:
    """Planted feet, centre of mass and pelvis must be met; a swing foot may be off a little in the air."""
    assert plan.targets.foot_ori_weight is not None  # the built-in plans weigh every foot orientation
    planted = plan.targets.foot_ori_weight >= 1.0
    bad = np.zeros(errors.shape)
    for k in range(2):
        pos, ori = (
            np.abs(errors[:, TASK_SLICES[f"foot{k}_pos"]]),
            np.abs(errors[:, TASK_SLICES[f"foot{k}_ori"]]),
        )
        bad[:, k] = np.where(
            planted[:, k], np.maximum(pos.max(1), ori.max(1)) / MAX_IK_ERROR, pos.max(1) / MAX_SWING_ERROR_M
        )
    bad[:, 2] = np.abs(errors[:, TASK_SLICES["com_xy"].start :]).max(1) / MAX_IK_ERROR
    if bad.max() > 1.0:
        t = int(bad.max(1).argmax())
        seg = next(s.name for s in plan.segments if s.start_s <= t / FPS < s.end_s + 1e-9)
        raise MotionDataError(
            f"built-in {name!r}: inverse kinematics missed its targets at t = {t / FPS:.2f} s "
            f"(segment {seg}): errors {np.round(errors[t], 4).tolist()}"
        )


def generate_builtin(
    mjmodel: mujoco.MjModel, name: str = "graded", seed: int = 0, duration_s: float = 30.0
) -> Motion:
    """The built-in motion `name` at 50 Hz in model order, with its segment manifest."""
    plan = build_plan(mjmodel, name, seed, duration_s)
    solver = WholeBodyIK(mjmodel, FEET, PELVIS, LEG_JOINTS, UPPER_JOINTS)
    free = free_joint_qposadr(mjmodel)[0]
    qpos0 = mjmodel.qpos0.copy()
    qpos0[free : free + 3] = (0.0, 0.0, plan.targets.pelvis_z[0])
    qpos0[free + 3 : free + 7] = yaw_quat(0.0)
    for side in ("left", "right"):
        for j, v in NEUTRAL_LEGS.items():
            qpos0[mjmodel.joint(f"{side}_{j}_joint").qposadr[0]] = v
    qpos, errors = solver.solve(plan.targets, qpos0)
    _check_ik(name, plan, errors)
    joints = model_joint_names(mjmodel)
    adr = [mjmodel.joint(j).qposadr[0] for j in joints]
    root_pos, root_quat = qpos[:, free : free + 3], qpos[:, free + 3 : free + 7]
    return kinematic_motion(mjmodel, FPS, root_pos, root_quat, qpos[:, adr], joints, plan.segments)
