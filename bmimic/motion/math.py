"""Vectorised quaternion helpers in numpy (w, x, y, z order, Hamilton product), and the time grid
of a resampled motion (`output_times`).

Every function broadcasts over leading dimensions; the last axis is the quaternion (4) or vector (3).
"""

from __future__ import annotations

import numpy as np

from bmimic.motion.segments import MotionDataError


def quat_normalize(q: np.ndarray) -> np.ndarray:
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v by unit quaternions q."""
    w = q[..., :1]
    u = q[..., 1:]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_rotate_inverse(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v by the inverse of unit quaternions q (world -> body frame)."""
    return quat_rotate(quat_conjugate(q), v)


def quat_to_axis_angle(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, angle in [0, pi]) of unit quaternions."""
    # q and -q are the same rotation; take the one with w >= 0 so the angle is the short way round.
    q = np.where(q[..., :1] < 0.0, -q, q)
    sin_half = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., :1])
    # angle / sin(angle/2) -> 2 as angle -> 0; guard the division there.
    small = sin_half < 1e-9
    scale = np.where(small, 2.0, angle / np.where(small, 1.0, sin_half))
    return q[..., 1:] * scale


def axis_angle_to_quat(rotvec: np.ndarray) -> np.ndarray:
    angle = np.linalg.norm(rotvec, axis=-1, keepdims=True)
    half = 0.5 * angle
    small = angle < 1e-9
    # sin(a/2)/a -> 1/2 as a -> 0.
    k = np.where(small, 0.5, np.sin(half) / np.where(small, 1.0, angle))
    return np.concatenate([np.cos(half), rotvec * k], axis=-1)


def quat_from_euler_zyx(roll: np.ndarray | float, pitch: np.ndarray | float, yaw: np.ndarray | float) -> np.ndarray:
    """Quaternion of R = Rz(yaw) Ry(pitch) Rx(roll) (extrinsic x, y, z; intrinsic z, y', x'')."""
    roll, pitch, yaw = np.broadcast_arrays(
        np.asarray(roll, float), np.asarray(pitch, float), np.asarray(yaw, float)
    )
    cr, sr = np.cos(0.5 * roll), np.sin(0.5 * roll)
    cp, sp = np.cos(0.5 * pitch), np.sin(0.5 * pitch)
    cy, sy = np.cos(0.5 * yaw), np.sin(0.5 * yaw)
    return np.stack(
        [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ],
        axis=-1,
    )


def quat_slerp(q0: np.ndarray, q1: np.ndarray, blend: np.ndarray) -> np.ndarray:
    """Spherical interpolation from q0 (blend 0) to q1 (blend 1) along the shorter arc."""
    blend = np.asarray(blend, dtype=float)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0.0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_theta = np.sin(theta)
    # Nearly parallel quaternions: slerp degenerates to lerp (then renormalise).
    near = sin_theta < 1e-6
    safe = np.where(near, 1.0, sin_theta)
    w0 = np.where(near, 1.0 - blend, np.sin((1.0 - blend) * theta) / safe)
    w1 = np.where(near, blend, np.sin(blend * theta) / safe)
    return quat_normalize(w0 * q0 + w1 * q1)


def angular_velocity_from_quats(quat: np.ndarray, dt: float) -> np.ndarray:
    """World-frame angular velocity [T, 3] of an orientation track [T, 4] sampled every dt.

    Central differences: axis-angle(q[t+1] q[t-1]^-1) / (2 dt); one-sided at both ends.
    """
    num = quat.shape[0]
    if num < 2:
        return np.zeros((num, 3))
    omega = np.empty((num, 3))
    if num > 2:
        delta = quat_mul(quat[2:], quat_conjugate(quat[:-2]))
        omega[1:-1] = quat_to_axis_angle(delta) / (2.0 * dt)
    omega[0] = quat_to_axis_angle(quat_mul(quat[1], quat_conjugate(quat[0]))) / dt
    omega[-1] = quat_to_axis_angle(quat_mul(quat[-1], quat_conjugate(quat[-2]))) / dt
    return omega


def yaw_quat(yaw: np.ndarray | float) -> np.ndarray:
    """Quaternion of a rotation by yaw about the world z axis."""
    yaw = np.asarray(yaw, dtype=float)
    zeros = np.zeros_like(yaw)
    return np.stack([np.cos(0.5 * yaw), zeros, zeros, np.sin(0.5 * yaw)], axis=-1)


MAX_FRAMES = 10**7
"""Most frames a resampled motion may have (55 h at 50 Hz, tens of GB): more means a frame rate is wrong."""


def output_times(num_in: int, fps_in: float, fps_out: float) -> np.ndarray:
    """t = 0, 1/fps_out, ... strictly below the input duration (N-1)/fps_in, as BeyondMimic's script.
    Raises MotionDataError (one line) when that is more than MAX_FRAMES frames (a rate of 1e-300 Hz)."""
    duration = (num_in - 1) / fps_in
    # Count k with k / fps_out < duration; the epsilon keeps an exact multiple from sneaking in.
    count = duration * fps_out - 1e-9
    if not count <= MAX_FRAMES:  # also NaN and infinity
        raise MotionDataError(f"{num_in} frames at {fps_in:g} fps resampled to {fps_out:g} Hz would make "
                              f"{count:.3g} frames ({duration:.3g} s), more than {MAX_FRAMES}: check the frame rates "
                              "(motion.fps_in, the file's fps, sim.timestep_s x sim.decimation)")
    num_out = int(np.ceil(count))
    return np.arange(max(num_out, 0)) / fps_out


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of unit quaternions (w, x, y, z)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    m = np.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), axis=-1)
    return m.reshape(m.shape[:-1] + (3, 3))


def rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in [0, pi] of the rotation between rotation matrices a and b ([..., 3, 3])."""
    cos = 0.5 * (np.einsum("...ij,...ij->...", a, b) - 1.0)  # (trace(a^T b) - 1) / 2
    return np.arccos(np.clip(cos, -1.0, 1.0))
