"""The segments of the built-in motions, by difficulty level (`LEVELS`). Each fills a
`SegmentBuilder`; times are seconds from the segment's start."""

from __future__ import annotations

from typing import Callable

import numpy as np

from bmimic.motion.builtin_builder import SegmentBuilder, U


def _stand(b: SegmentBuilder) -> None:
    rng = b.rng
    f = rng.uniform(0.25, 0.45)
    env = b.envelope(0.8)
    wave = np.sin(2 * np.pi * f * b.t)
    b.pelvis_osc[:, 0] = -rng.uniform(0.01, 0.025) * 0.5 * (1 - np.cos(2 * np.pi * f * b.t)) * env
    b.upper[:, U["left_shoulder_pitch_joint"]] += rng.uniform(0.05, 0.2) * wave * env
    b.upper[:, U["right_shoulder_pitch_joint"]] -= rng.uniform(0.05, 0.2) * wave * env
    b.upper[:, U["waist_yaw_joint"]] += rng.uniform(0.05, 0.15) * np.sin(np.pi * f * b.t) * env


def _arm_wave(b: SegmentBuilder) -> None:
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


def _torso_twist(b: SegmentBuilder) -> None:
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


def _squat(b: SegmentBuilder) -> None:
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


def _weight_shift(b: SegmentBuilder) -> None:
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


def _step_in_place(b: SegmentBuilder) -> None:
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


def _single_leg_swing(b: SegmentBuilder) -> None:
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


def _kick(b: SegmentBuilder) -> None:
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


def _fast_turn(b: SegmentBuilder) -> None:
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


SegmentFn = Callable[[SegmentBuilder], None]
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
