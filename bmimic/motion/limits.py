"""What a motion may be before it is built or trained on: a size that fits the host (checked before any
work starts, so a typo'd duration is one line, not minutes of work and an exhausted host), and a
physically plausible reference (upright where it starts, feet near the ground), so that a file in the
wrong convention is refused instead of converted and trained upside down.
"""

from __future__ import annotations

import mujoco
import numpy as np

from bmimic.motion.segments import MotionDataError

MAX_GENERATED_S = 3600.0
"""Longest built-in motion generated: inverse kinematics takes about 0.13 s per second of motion on one
CPU core, so an hour already takes minutes before training starts (once; then it is cached)."""
WORKING_COPIES = 4
"""A motion's arrays are held about this many times while it is built (generation or resampling, the
cache file, the environment's reference on the device)."""


def check_motion_size(mjmodel: mujoco.MjModel, duration_s: float, fps: float, key: str,
                      generated: bool = False) -> None:
    """Refuse, before any work, a motion of `duration_s` at `fps` whose arrays would not fit in the
    host's available memory (or, `generated`, that would take more than MAX_GENERATED_S of motion to
    generate): one line naming `key` with the estimate, instead of minutes of work or an exhausted host."""
    from bmimic.runtime import available_memory_bytes

    frames = duration_s * fps
    if generated and not duration_s <= MAX_GENERATED_S:
        raise MotionDataError(f"{key}: {duration_s:g} s is longer than the {MAX_GENERATED_S:g} s a built-in motion "
                              f"may last (generating it would take about {0.13 * duration_s / 60:.3g} minutes); "
                              "use a shorter one or a motion file")
    floats = 2 * mjmodel.nv + 13 * (mjmodel.nbody - 1)  # joints' positions and velocities, bodies' states
    need = frames * floats * np.dtype(np.float32).itemsize * WORKING_COPIES
    free = available_memory_bytes()
    if not np.isfinite(need) or (free is not None and need > free):
        raise MotionDataError(f"{key}: {duration_s:g} s at {fps:g} Hz is {frames:.3g} frames, about "
                              f"{need / 2**30:.3g} GiB while it is built, but the host has "
                              f"{(free or 0) / 2**30:.1f} GiB available; use a shorter motion or a lower rate")


FEET_HEIGHT_M = (-0.10, 0.12)
"""Where the lower foot of a plausible reference is on most frames (median over frames): a standing G1's
ankles are 0.03-0.05 m above the ground; in 36 LAFAN1 clips (falls and jumps included) the median is
0.04-0.05 m, and read with the root quaternion in the wrong order (w first) 0.15-1.3 m."""
UPSIDE_DOWN_UP_Z = -0.5
"""The root's up axis points at most this far up (cosine of its tilt; -0.5: tilted more than 120 deg) at
the first frame of an upside-down reference; every LAFAN1 clip starts upright (1.0), and lying on the
back or side is about 0."""
FOOT_WORDS = ("ankle", "foot", "toe")
"""Body names that mark a foot (the G1's ankle links); without any, the lowest body stands in."""


JOINT_SPEED_P99_RADPS = 40.0
"""Fastest a plausible reference's fastest joint moves on 1% of its frames (99th percentile over frames of
the largest joint speed): 36 LAFAN1 clips at their 30 fps reach 5.9-20.1 rad/s; read at 4 times its
frame rate (a 7.5 fps clip taken for 30 fps) a clip moves 4 times faster. A single fast frame (a glitch
of the retarget: up to 37 rad/s in LAFAN1) does not count. A clip read at a lower rate than its own (120
fps taken for 30) is a slow but possible motion, which no check can tell."""

BODY_OFFSET_M = 0.05
"""Farthest a body's recorded position may lie from where the model puts it, given the root's recorded
pose and the joints, at the first frame (forward kinematics; arrays written in another quaternion
order or another model's body frames are far beyond it)."""


def implausibility(motion, mjmodel: mujoco.MjModel | None = None) -> str | None:
    """Why the reference `motion` (bmimic.motion.Motion, in `mjmodel`'s order when given) cannot be a
    humanoid on the ground, or None: its root upside down at the first frame (a motion starts at rest,
    upright), its feet far from the ground on most frames, or (given the model) body positions that do
    not follow from the root's pose and the joints. These are what a quaternion read in the wrong order
    (w x y z for the CSV's x y z w, or x y z w in an npz's w x y z), a root position in other units or
    a wrong height offset produce; joint ranges are checked where the motion is read (bmimic.motion.npz,
    convert)."""
    pos, quat = np.asarray(motion.body_pos_w), np.asarray(motion.body_quat_w)
    if pos.ndim != 3 or pos.shape[0] < 1 or quat.shape[:2] != pos.shape[:2]:
        return None
    offset = _kinematic_offset(motion, mjmodel) if mjmodel is not None else None
    if offset is not None and offset[0] > BODY_OFFSET_M:
        return (f"body {offset[1]!r} is {offset[0]:.2f} m from where the root's pose and the joints put it at the first "
                "frame (is body_quat_w in w x y z order?)")
    _, x, y, _ = quat[0, 0]
    up_z = 1.0 - 2.0 * (x * x + y * y)  # the world z of the root's own z axis
    if up_z < UPSIDE_DOWN_UP_Z:
        return (f"its root ({motion.body_names[0]}) is upside down at the first frame (tilted "
                f"{np.degrees(np.arccos(np.clip(up_z, -1, 1))):.0f} deg from upright)")
    joints = np.asarray(getattr(motion, "joint_pos", np.zeros((0, 0))))
    if joints.ndim == 2 and joints.shape[0] > 2 and joints.shape[1] > 0:
        # from the positions, not joint_vel: its central differences halve a speed that flips each frame
        vel = np.diff(joints, axis=0) * float(motion.fps)
        speed = float(np.percentile(np.abs(vel).max(axis=1), 99))
        if speed > JOINT_SPEED_P99_RADPS:
            return (f"its fastest joint moves at {speed:.0f} rad/s on 1% of its frames, faster than any human (LAFAN1's "
                    f"clips: 6-20 rad/s): is the frame rate right (motion.fps_in, convert's --fps-in)?")
    feet = [i for i, name in enumerate(motion.body_names) if any(word in str(name) for word in FOOT_WORDS)]
    lowest = pos[:, feet or slice(None), 2].min(axis=1)
    height = float(np.median(lowest))
    low, high = FEET_HEIGHT_M
    if not low <= height <= high:
        where = "above" if height > 0 else "below"
        return (f"its {'feet are' if feet else 'lowest body is'} {abs(height):.2f} m {where} the ground on most "
                f"frames (median; a standing G1's are 0.05 m)")
    return None


def _kinematic_offset(motion, mjmodel: mujoco.MjModel) -> tuple[float, str] | None:
    """(largest distance, its body) between the first frame's recorded body positions and forward
    kinematics from its root pose and joints; None when the model and the motion do not share the
    root's free joint, the joints and the bodies by name."""
    if mjmodel.njnt < 1 or mjmodel.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE:
        return None
    data = mujoco.MjData(mjmodel)
    data.qpos[:] = mjmodel.qpos0
    data.qpos[0:3], data.qpos[3:7] = motion.body_pos_w[0, 0], motion.body_quat_w[0, 0]
    for k, name in enumerate(motion.joint_names):
        jid = mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_JOINT, str(name))
        if jid < 0:
            return None
        data.qpos[mjmodel.jnt_qposadr[jid]] = motion.joint_pos[0, k]
    mujoco.mj_kinematics(mjmodel, data)
    ids = [mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_BODY, str(name)) for name in motion.body_names]
    if min(ids, default=-1) < 0:
        return None
    distance = np.linalg.norm(data.xpos[ids] - motion.body_pos_w[0], axis=-1)
    worst = int(np.argmax(distance))
    return float(distance[worst]), str(motion.body_names[worst])


def check_plausible(motion, source: str, flag: str, mjmodel: mujoco.MjModel | None = None) -> None:
    """Refuse (MotionDataError naming `source`) a reference for which implausibility() says why; `flag`
    is the setting that accepts it anyway."""
    why = implausibility(motion, mjmodel)
    if why is not None and "frame rate" in why:
        raise MotionDataError(f"{source}: {why}; fix the rate, or {flag} to use it anyway")
    if why is not None:
        raise MotionDataError(f"{source}: {why}: not a plausible reference (is the root quaternion x y z w, as "
                              f"the CSV expects, and the root position in metres?); fix the file, or {flag} to "
                              "use it anyway")
