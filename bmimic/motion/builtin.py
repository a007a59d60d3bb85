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
from typing import Callable

import mujoco
import numpy as np

from bmimic.motion.ik import TASK_SLICES, FootGeometry, IKTargets, WholeBodyIK, foot_geometry
from bmimic.motion.math import quat_from_euler_zyx, yaw_quat
from bmimic.motion.motion import (
    Motion,
    MotionDataError,
    Segment,
    free_joint_qposadr,
    kinematic_motion,
    model_joint_names,
)

GENERATOR_VERSION = "1"
"""Part of the cache key; bump whenever the generated trajectories change."""
FPS = 50.0
FEET = ("left_ankle_roll_link", "right_ankle_roll_link")
PELVIS = "pelvis"
LEG_JOINTS = tuple(
    f"{side}_{j}_joint"
    for side in ("left", "right")
    for j in ("hip_pitch", "hip_roll", "hip_yaw", "knee", "ankle_pitch", "ankle_roll")
)
UPPER_JOINTS = ("waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint") + tuple(
    f"{side}_{j}_joint"
    for side in ("left", "right")
    for j in (
        "shoulder_pitch",
        "shoulder_roll",
        "shoulder_yaw",
        "elbow",
        "wrist_roll",
        "wrist_pitch",
        "wrist_yaw",
    )
)
# Neutral pose: BeyondMimic's knees-bent stance for the legs, arms slightly out and bent.
NEUTRAL_LEGS = {"hip_pitch": -0.312, "knee": 0.669, "ankle_pitch": -0.363}
NEUTRAL_UPPER = {
    "left_shoulder_pitch_joint": 0.2,
    "right_shoulder_pitch_joint": 0.2,
    "left_shoulder_roll_joint": 0.2,
    "right_shoulder_roll_joint": -0.2,
    "left_elbow_joint": 0.6,
    "right_elbow_joint": 0.6,
}
U = {name: i for i, name in enumerate(UPPER_JOINTS)}
# Largest IK task error accepted (m or rad); beyond this a target was unreachable (a generator bug).
MAX_IK_ERROR = 2e-3
MAX_SWING_ERROR_M = 0.01
SWING_ORIENTATION_WEIGHT = 0.05
SWING_FLAT_HEIGHT_M = 0.03
"""A swing foot's orientation weight falls from 1 on the floor to SWING_ORIENTATION_WEIGHT at this height,
so it lands flat but may tilt in the air where the leg's joint limits demand it."""


def smootherstep(x: np.ndarray) -> np.ndarray:
    """0 -> 1 with zero first and second derivatives at both ends."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (x * (6.0 * x - 15.0) + 10.0)


class Track:
    """Keyframed value: `to(t, v)` moves from the previous keyframe to v by t (smootherstep)."""

    def __init__(self, value) -> None:
        self.times = [0.0]
        self.values = [np.atleast_1d(np.asarray(value, dtype=float))]

    @property
    def last(self) -> np.ndarray:
        return self.values[-1]

    def to(self, t: float, value) -> Track:
        if t < self.times[-1] - 1e-9:
            raise ValueError(f"keyframe at {t} s is before the previous one at {self.times[-1]} s")
        self.times.append(float(t))
        self.values.append(np.atleast_1d(np.asarray(value, dtype=float)))
        return self

    def hold(self, t: float) -> Track:
        return self.to(max(t, self.times[-1]), self.last)

    def __call__(self, times: np.ndarray) -> np.ndarray:
        kt = np.asarray(self.times)
        kv = np.stack(self.values)
        i = np.clip(np.searchsorted(kt, times, side="right") - 1, 0, len(kt) - 1)
        j = np.minimum(i + 1, len(kt) - 1)
        span = np.maximum(kt[j] - kt[i], 1e-12)
        s = np.where(j > i, smootherstep((times - kt[i]) / span), 0.0)
        return kv[i] + (kv[j] - kv[i]) * s[:, None]


@dataclasses.dataclass(frozen=True)
class Stance:
    """Robot-specific figures of the neutral stance, read from the model."""

    pelvis_z_m: float
    """Pelvis height with the neutral legs and flat feet on the floor."""
    foot_offset_m: np.ndarray
    """[2, 2] x, y of each foot origin relative to the stance frame (midway between the feet)."""
    feet: tuple[FootGeometry, FootGeometry]
    """Sole and contact box of the left and right foot."""


def neutral_stance(mjmodel: mujoco.MjModel) -> Stance:
    data = mujoco.MjData(mjmodel)
    data.qpos[:] = mjmodel.qpos0
    for side in ("left", "right"):
        for j, v in NEUTRAL_LEGS.items():
            data.joint(f"{side}_{j}_joint").qpos[0] = v
    data.qpos[:3] = 0.0
    data.qpos[3:7] = (1.0, 0.0, 0.0, 0.0)
    mujoco.mj_kinematics(mjmodel, data)
    feet = tuple(foot_geometry(mjmodel, f) for f in FEET)
    xpos = np.stack([data.body(f).xpos for f in FEET])
    mid = xpos[:, :2].mean(axis=0)
    return Stance(
        pelvis_z_m=float(feet[0].sole_z_m - xpos[0, 2]),
        foot_offset_m=xpos[:, :2] - mid,
        feet=feet,
    )


def _rot2(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


class _SegmentBuilder:
    """Targets of one segment, in its stance frame (x, y, yaw), as keyframe tracks plus oscillations."""

    def __init__(self, stance: Stance, frame: np.ndarray, duration_s: float, rng: np.random.Generator):
        self.stance, self.frame, self.rng = stance, frame.copy(), rng
        self.duration = duration_s
        self.t = np.arange(int(round(duration_s * FPS))) / FPS
        n = self.t.size
        self.weight = Track(0.5)  # centre of mass between the left (0) and right (1) foot centres
        self.foot = [Track(self.home_pose(k, frame)) for k in range(2)]  # world x, y, yaw
        self.lift = [Track([0.0, 0.0, 0.0]) for _ in range(2)]  # stance-frame dx, dy, dz of a swing
        self.foot_pitch = [Track(0.0) for _ in range(2)]
        self.foot_osc = np.zeros((2, n, 3))
        self.pelvis = Track([0.0, 0.0, 0.0])  # dz, roll, pitch
        self.pelvis_osc = np.zeros((n, 3))
        self.weight_osc = np.zeros(n)  # added to the weight track
        self.upper = np.tile([NEUTRAL_UPPER.get(j, 0.0) for j in UPPER_JOINTS], (n, 1))
        self.end_frame = frame.copy()

    def home_pose(self, foot: int, frame: np.ndarray) -> np.ndarray:
        xy = frame[:2] + _rot2(frame[2]) @ self.stance.foot_offset_m[foot]
        return np.array([xy[0], xy[1], frame[2]])

    def envelope(self, ramp_s: float, start_s: float = 0.0, end_s: float | None = None) -> np.ndarray:
        end_s = self.duration if end_s is None else end_s
        return smootherstep((self.t - start_s) / ramp_s) * smootherstep((end_s - self.t) / ramp_s)

    def shift(self, t0: float, dur: float, weight: float) -> None:
        self.weight.hold(t0).to(t0 + dur, weight)

    def step(self, foot: int, t0: float, dur: float, pose: np.ndarray, height: float) -> None:
        """Lift the foot at t0, put it down at `pose` (world x, y, yaw) at t0 + dur."""
        self.foot[foot].hold(t0).to(t0 + dur, pose)
        lift = self.lift[foot]
        lift.hold(t0).to(t0 + 0.5 * dur, [0.0, 0.0, height]).to(t0 + dur, [0.0, 0.0, 0.0])

    def render(self) -> dict[str, np.ndarray]:
        t = self.t
        yaw0 = self.frame[2]
        foot_pos, foot_yaw, contact, ori_weight = [], [], [], []
        for k in range(2):
            pose = self.foot[k](t)
            off = self.lift[k](t) + self.foot_osc[k]
            xy = pose[:, :2] + np.einsum("ij,tj->ti", _rot2(yaw0), off[:, :2])
            z = self.stance.feet[k].sole_z_m + off[:, 2]
            foot_pos.append(np.column_stack([xy, z]))
            foot_yaw.append(pose[:, 2])
            contact.append(off[:, 2] <= 1e-9)
            ori_weight.append(np.clip(1.0 - off[:, 2] / SWING_FLAT_HEIGHT_M, SWING_ORIENTATION_WEIGHT, 1.0))
        return {
            "weight": self.weight(t)[:, 0] + self.weight_osc,
            "foot_pos": np.stack(foot_pos, 1),
            "foot_yaw": np.stack(foot_yaw, 1),
            "foot_pitch": np.stack([p(t)[:, 0] for p in self.foot_pitch], 1),
            "contact": np.stack(contact, 1),
            "foot_ori_weight": np.stack(ori_weight, 1),
            "pelvis": self.pelvis(t) + self.pelvis_osc,
            "upper": self.upper,
        }


# ---------------------------------------------------------------------------------------------------
# Segments. Each fills a builder; times are seconds from the segment's start.


def _stand(b: _SegmentBuilder) -> None:
    rng = b.rng
    f = rng.uniform(0.25, 0.45)
    env = b.envelope(0.8)
    wave = np.sin(2 * np.pi * f * b.t)
    b.pelvis_osc[:, 0] = -rng.uniform(0.01, 0.025) * 0.5 * (1 - np.cos(2 * np.pi * f * b.t)) * env
    b.upper[:, U["left_shoulder_pitch_joint"]] += rng.uniform(0.05, 0.2) * wave * env
    b.upper[:, U["right_shoulder_pitch_joint"]] -= rng.uniform(0.05, 0.2) * wave * env
    b.upper[:, U["waist_yaw_joint"]] += rng.uniform(0.05, 0.15) * np.sin(np.pi * f * b.t) * env


def _arm_wave(b: _SegmentBuilder) -> None:
    rng = b.rng
    sides = [("left", 1.0), ("right", -1.0)]
    choice = rng.integers(3)
    if choice < 2:
        sides = [sides[choice]]
    env = b.envelope(0.8)
    f = rng.uniform(1.0, 1.6)
    for side, sign in sides:
        raise_rad = rng.uniform(1.1, 1.5)
        amp = rng.uniform(0.35, 0.55)
        phase = rng.uniform(0, 2 * np.pi)
        b.upper[:, U[f"{side}_shoulder_roll_joint"]] += sign * (raise_rad - 0.2) * env
        b.upper[:, U[f"{side}_shoulder_yaw_joint"]] += sign * 0.3 * env
        b.upper[:, U[f"{side}_elbow_joint"]] += env * (0.3 + amp * np.sin(2 * np.pi * f * b.t + phase))
        b.upper[:, U[f"{side}_wrist_roll_joint"]] += env * 0.3 * np.sin(2 * np.pi * f * b.t + phase)
    b.upper[:, U["waist_roll_joint"]] += 0.08 * (1 if choice == 1 else -1 if choice == 0 else 0) * env


def _torso_twist(b: _SegmentBuilder) -> None:
    rng = b.rng
    f = rng.uniform(0.3, 0.55)
    env = b.envelope(1.0)
    wave = np.sin(2 * np.pi * f * b.t)
    b.upper[:, U["waist_yaw_joint"]] += rng.uniform(0.35, 0.7) * wave * env
    b.upper[:, U["waist_roll_joint"]] += rng.uniform(0.0, 0.12) * np.sin(4 * np.pi * f * b.t) * env
    b.upper[:, U["waist_pitch_joint"]] += rng.uniform(0.0, 0.15) * env
    swing = rng.uniform(0.2, 0.5)
    b.upper[:, U["left_shoulder_pitch_joint"]] += swing * wave * env
    b.upper[:, U["right_shoulder_pitch_joint"]] -= swing * wave * env


def _squat(b: _SegmentBuilder) -> None:
    rng = b.rng
    depth = rng.uniform(0.1, 0.18)
    period = rng.uniform(1.8, 2.6)
    count = max(1, int((b.duration - 0.6) // period))
    period = min(period, (b.duration - 0.6) / count)
    t0 = 0.5 * (b.duration - count * period)
    active = (b.t >= t0) & (b.t <= t0 + count * period)
    down = np.where(active, 0.5 * (1 - np.cos(2 * np.pi * (b.t - t0) / period)), 0.0)
    b.pelvis_osc[:, 0] = -depth * down
    b.pelvis_osc[:, 2] = 1.6 * depth * down  # lean forward as the hips go back
    reach = rng.uniform(0.5, 1.0)
    for side in ("left", "right"):
        b.upper[:, U[f"{side}_shoulder_pitch_joint"]] -= reach * down
        b.upper[:, U[f"{side}_elbow_joint"]] -= 0.4 * reach * down


def _weight_shift(b: _SegmentBuilder) -> None:
    rng = b.rng
    f = rng.uniform(0.3, 0.5)
    amp = rng.uniform(0.3, 0.42)
    env = b.envelope(1.0)
    sign = rng.choice([-1.0, 1.0])
    wave = np.sin(2 * np.pi * f * b.t) * env * sign
    b.weight_osc = amp * wave
    b.pelvis_osc[:, 1] = -0.06 * wave  # roll the pelvis towards the loaded foot
    b.pelvis_osc[:, 0] = -rng.uniform(0.0, 0.03) * env
    b.upper[:, U["left_shoulder_roll_joint"]] += 0.2 * np.clip(wave, 0, None)
    b.upper[:, U["right_shoulder_roll_joint"]] -= 0.2 * np.clip(-wave, 0, None)


def _step_in_place(b: _SegmentBuilder) -> None:
    rng = b.rng
    shift, swing = rng.uniform(0.4, 0.55), rng.uniform(0.45, 0.65)
    height = rng.uniform(0.06, 0.1)
    n = max(2, int((b.duration - 1.0) // (shift + swing)))
    # In a short segment the two steps speed up rather than being dropped.
    squeeze = min(1.0, (b.duration - 1.0) / (n * (shift + swing)))
    shift, swing = shift * squeeze, swing * squeeze
    t = 0.5 * (b.duration - n * (shift + swing) - 0.5)
    stance = int(rng.integers(2))
    for _ in range(n):
        b.shift(t, shift, float(stance))
        swing_foot = 1 - stance
        b.step(swing_foot, t + shift, swing, b.foot[swing_foot].last, height)
        t += shift + swing
        stance = swing_foot
    b.shift(t, 0.5, 0.5)


def _single_leg_swing(b: _SegmentBuilder) -> None:
    rng = b.rng
    stance = int(rng.integers(2))
    swing = 1 - stance
    outward = 1.0 if swing == 0 else -1.0  # +y is outward for the left foot
    lift, height = 0.5, rng.uniform(0.12, 0.2)
    # At least 0.8 s of swinging; a short segment shortens the weight shifts instead.
    shift = min(rng.uniform(0.7, 0.9), 0.5 * (b.duration - 0.2 - 2 * lift - 0.8))
    swing_time = b.duration - 2 * (shift + lift) - 0.2
    t = 0.1
    b.shift(t, shift, float(stance))
    t += shift
    b.lift[swing].hold(t).to(t + lift, [0.0, 0.04 * outward, height])
    t += lift
    ts, te = t, t + swing_time
    b.lift[swing].hold(te).to(te + lift, [0.0, 0.0, 0.0])
    b.shift(te + lift, shift, 0.5)
    f = rng.uniform(0.5, 0.8)
    env = b.envelope(0.4, ts, te) * ((b.t > ts) & (b.t < te))
    b.foot_osc[swing, :, 0] = rng.uniform(0.12, 0.2) * np.sin(2 * np.pi * f * (b.t - ts)) * env
    b.foot_osc[swing, :, 1] = outward * rng.uniform(0.0, 0.06) * np.sin(4 * np.pi * f * (b.t - ts)) ** 2 * env
    arms = b.envelope(0.8)
    b.upper[:, U["left_shoulder_roll_joint"]] += rng.uniform(0.5, 0.9) * arms
    b.upper[:, U["right_shoulder_roll_joint"]] -= rng.uniform(0.5, 0.9) * arms


def _kick(b: _SegmentBuilder) -> None:
    rng = b.rng
    stance = int(rng.integers(2))
    kick = 1 - stance
    chamber = [-0.03, 0.0, rng.uniform(0.15, 0.2)]
    extend = [rng.uniform(0.28, 0.38), 0.0, rng.uniform(0.2, 0.28)]
    moves = [0.35, rng.uniform(0.15, 0.2), 0.1, 0.25, 0.35]  # chamber, kick, hold, retract, put down
    shift = min(rng.uniform(0.5, 0.6), 0.5 * (b.duration - 0.1 - sum(moves)))
    phases = [shift, *moves, shift]
    t = 0.5 * (b.duration - sum(phases))
    b.shift(t, shift, float(stance))
    t += shift
    lift, pitch = b.lift[kick], b.foot_pitch[kick]
    lift.hold(t).to(t + phases[1], chamber)
    t += phases[1]
    lift.to(t + phases[2], extend)
    pitch.hold(t).to(t + phases[2], -0.3)  # toes up as the leg extends
    t += phases[2] + phases[3]
    lift.hold(t).to(t + phases[4], chamber)
    pitch.hold(t).to(t + phases[4], 0.0)
    t += phases[4]
    lift.to(t + phases[5], [0.0, 0.0, 0.0])
    t += phases[5]
    b.shift(t, shift, 0.5)
    arms = b.envelope(0.6)
    b.upper[:, U["left_shoulder_roll_joint"]] += 0.5 * arms
    b.upper[:, U["right_shoulder_roll_joint"]] -= 0.5 * arms


def _fast_turn(b: _SegmentBuilder) -> None:
    rng = b.rng
    direction = rng.choice([-1.0, 1.0])
    step_angle = np.deg2rad(rng.uniform(25.0, 35.0))
    shift, swing = rng.uniform(0.34, 0.4), rng.uniform(0.3, 0.36)
    # Quick steps: the centre of mass goes only to the inner part of each stance foot (still inside it).
    inset = 0.06
    pair = 2 * (shift + swing)
    n = min(4, max(1, int((b.duration - 0.8) // pair)))
    lead = 0 if direction > 0 else 1  # turning left (counter-clockwise) opens with the left foot
    t = 0.5 * (b.duration - n * pair - 0.35)
    frame = b.frame.copy()
    for _ in range(n):
        frame = frame + np.array([0.0, 0.0, direction * step_angle])
        for foot in (lead, 1 - lead):
            b.shift(t, shift, inset + (1 - 2 * inset) * (1 - foot))
            b.step(foot, t + shift, swing, b.home_pose(foot, frame), rng.uniform(0.05, 0.07))
            t += shift + swing
    b.shift(t, 0.35, 0.5)
    b.end_frame = frame
    arms = b.envelope(0.5)
    for side in ("left", "right"):
        b.upper[:, U[f"{side}_elbow_joint"]] += 0.5 * arms


SegmentFn = Callable[[_SegmentBuilder], None]
LEVELS: dict[str, list[tuple[str, SegmentFn, float]]] = {
    # (name, builder, nominal duration in s)
    "easy": [("stand", _stand, 3.0), ("arm_wave", _arm_wave, 3.5), ("torso_twist", _torso_twist, 3.5)],
    "medium": [
        ("squat", _squat, 3.5),
        ("weight_shift", _weight_shift, 3.0),
        ("step_in_place", _step_in_place, 3.5),
    ],
    "hard": [
        ("single_leg_swing", _single_leg_swing, 4.0),
        ("kick", _kick, 3.0),
        ("fast_turn", _fast_turn, 3.0),
    ],
}
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
        builder = _SegmentBuilder(stance, frame, (z - a) / FPS, rng)
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
            plan["foot_pos"][:, k, :2] + np.einsum("tij,j->ti", _rot2(foot_yaw[:, k]), stance.feet[k].centre)
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
