"""The building blocks of the built-in motions (`bmimic.motion.builtin`): the joint groups and the
neutral stance read from the robot model, keyframed tracks, and the builder that lays out one
segment's per-frame targets in its stance frame.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np

from bmimic.motion.ik import FootGeometry, foot_geometry

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
    feet = (foot_geometry(mjmodel, FEET[0]), foot_geometry(mjmodel, FEET[1]))
    xpos = np.stack([data.body(f).xpos for f in FEET])
    mid = xpos[:, :2].mean(axis=0)
    return Stance(
        pelvis_z_m=float(feet[0].sole_z_m - xpos[0, 2]),
        foot_offset_m=xpos[:, :2] - mid,
        feet=feet,
    )


def rot2(yaw: np.ndarray) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)


class SegmentBuilder:
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
        xy = frame[:2] + rot2(frame[2]) @ self.stance.foot_offset_m[foot]
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
            xy = pose[:, :2] + np.einsum("ij,tj->ti", rot2(yaw0), off[:, :2])
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
