"""Whole-body inverse kinematics for the built-in motions (CPU MuJoCo, damped least squares).

Per frame, the floating base and the leg joints are solved so that both feet reach their poses, the
whole-body centre of mass (x, y) sits over its target, and the pelvis reaches its height and
orientation; the waist and arm joints are given directly. Each frame starts from the previous
frame's solution, so a few Gauss-Newton steps suffice.
"""

from __future__ import annotations

import dataclasses
from typing import Sequence

import mujoco
import numpy as np

from bmimic.motion.math import quat_conjugate, quat_mul, quat_to_axis_angle
from bmimic.motion.model import free_joint_qposadr, joint_addresses
from bmimic.motion.segments import MotionDataError

# Rows of the task error vector, in order.
TASK_SLICES = {
    "foot0_pos": slice(0, 3),
    "foot0_ori": slice(3, 6),
    "foot1_pos": slice(6, 9),
    "foot1_ori": slice(9, 12),
    "com_xy": slice(12, 14),
    "pelvis_z": slice(14, 15),
    "pelvis_ori": slice(15, 18),
}
TASK_ROWS = 18


@dataclasses.dataclass(frozen=True)
class FootGeometry:
    """Sole and contact box of a foot, in the foot body's frame (from its collision geoms)."""

    sole_z_m: float
    """Height of the lowest collision point below the body origin when the foot is flat (positive)."""
    x_min_m: float
    x_max_m: float
    y_min_m: float
    y_max_m: float
    """Box spanned by the contact points (sphere centres, capsule end points, box corners) in x and y."""

    @property
    def centre(self) -> np.ndarray:
        return np.array([0.5 * (self.x_min_m + self.x_max_m), 0.5 * (self.y_min_m + self.y_max_m)])


def _geom_points(mjmodel: mujoco.MjModel, g: int) -> tuple[np.ndarray, float]:
    """Points in the body frame whose radius-inflation bounds the geom, and that radius."""
    pos, size, kind = mjmodel.geom_pos[g], mjmodel.geom_size[g], mjmodel.geom_type[g]
    flat = np.empty(9)
    mujoco.mju_quat2Mat(flat, mjmodel.geom_quat[g])
    rot = flat.reshape(3, 3)
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return pos[None], float(size[0])
    if kind in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
        axis = rot[:, 2] * size[1]
        return np.stack([pos - axis, pos + axis]), float(size[0])
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]) * size
        return pos + corners @ rot.T, 0.0
    raise MotionDataError(f"foot geom {mjmodel.geom(g).name!r} has a type the foot model does not handle")


def foot_geometry(mjmodel: mujoco.MjModel, body: str) -> FootGeometry:
    bid = mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_BODY, body)
    if bid < 0:
        raise MotionDataError(f"body {body!r} is not in the robot model")
    points, lows = [], []
    for g in range(mjmodel.ngeom):
        if mjmodel.geom_bodyid[g] != bid or not (mjmodel.geom_contype[g] or mjmodel.geom_conaffinity[g]):
            continue
        pts, radius = _geom_points(mjmodel, g)
        points.append(pts)
        lows.append(pts[:, 2].min() - radius)
    if not points:
        raise MotionDataError(f"body {body!r} has no collision geoms to stand on")
    pts = np.concatenate(points)
    return FootGeometry(
        sole_z_m=-float(min(lows)),
        x_min_m=float(pts[:, 0].min()),
        x_max_m=float(pts[:, 0].max()),
        y_min_m=float(pts[:, 1].min()),
        y_max_m=float(pts[:, 1].max()),
    )


@dataclasses.dataclass
class IKTargets:
    """Per-frame task targets (world frame)."""

    foot_pos: np.ndarray
    """[T, 2, 3] origins of the two foot bodies, m."""
    foot_quat: np.ndarray
    """[T, 2, 4] orientations of the two foot bodies (w, x, y, z)."""
    com_xy: np.ndarray
    """[T, 2] whole-body centre of mass x, y, m."""
    pelvis_z: np.ndarray
    """[T] pelvis origin height, m."""
    pelvis_quat: np.ndarray
    """[T, 4] pelvis orientation."""
    joint_pos: np.ndarray
    """[T, J] joints given directly (waist, arms), in the order of the solver's `fixed_joints`."""
    foot_ori_weight: np.ndarray | None = None
    """[T, 2] weight of each foot's orientation task (None: 1). A swing foot may tilt where its joint
    limits demand it, so its orientation is a soft task there; a planted foot's is a hard one."""


class WholeBodyIK:
    """Damped least squares over the free joint and the leg joints; the other joints are set."""

    def __init__(
        self,
        mjmodel: mujoco.MjModel,
        feet: Sequence[str],
        pelvis: str,
        solved_joints: Sequence[str],
        fixed_joints: Sequence[str],
        damping: float = 1e-3,
        weights: dict[str, float] | None = None,
    ) -> None:
        self.model = mjmodel
        self.data = mujoco.MjData(mjmodel)
        self.feet = [mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_BODY, f) for f in feet]
        self.pelvis = mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_BODY, pelvis)
        if min(self.feet + [self.pelvis]) < 0:
            raise MotionDataError(f"bodies {list(feet) + [pelvis]} are not all in the robot model")
        self.free_q, free_v = free_joint_qposadr(mjmodel)
        solved_q, solved_v = joint_addresses(mjmodel, solved_joints)
        self.fixed_q, _ = joint_addresses(mjmodel, fixed_joints)
        self.dofs = np.concatenate([np.arange(free_v, free_v + 6), solved_v])
        self.solved_q = solved_q
        jids = [mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_JOINT, n) for n in solved_joints]
        self.low = np.where(mjmodel.jnt_limited[jids], mjmodel.jnt_range[jids, 0], -np.inf)
        self.high = np.where(mjmodel.jnt_limited[jids], mjmodel.jnt_range[jids, 1], np.inf)
        w = {"foot_pos": 1.0, "foot_ori": 0.5, "com": 1.0, "pelvis_z": 1.0, "pelvis_ori": 0.3}
        w.update(weights or {})
        self.row_weights = np.concatenate(
            [
                np.full(3, w["foot_pos"]),
                np.full(3, w["foot_ori"]),
                np.full(3, w["foot_pos"]),
                np.full(3, w["foot_ori"]),
                np.full(2, w["com"]),
                np.full(1, w["pelvis_z"]),
                np.full(3, w["pelvis_ori"]),
            ]
        )
        self.damping = damping
        nv = mjmodel.nv
        self._jacp = np.zeros((3, nv))
        self._jacr = np.zeros((3, nv))
        self._jac = np.zeros((TASK_ROWS, nv))

    def _residual(self, targets: IKTargets, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Task error e (target - current) and its Jacobian J (de/dv = -J) at the current data."""
        m, d = self.model, self.data
        mujoco.mj_kinematics(m, d)
        mujoco.mj_comPos(m, d)
        err = np.empty(TASK_ROWS)
        row = 0
        for k, body in enumerate(self.feet):
            err[row : row + 3] = targets.foot_pos[t, k] - d.xpos[body]
            rot_err = quat_mul(targets.foot_quat[t, k], quat_conjugate(d.xquat[body]))
            err[row + 3 : row + 6] = quat_to_axis_angle(rot_err)
            mujoco.mj_jacBody(m, d, self._jacp, self._jacr, body)
            self._jac[row : row + 3] = self._jacp
            self._jac[row + 3 : row + 6] = self._jacr
            row += 6
        err[row : row + 2] = targets.com_xy[t] - d.subtree_com[self.pelvis, :2]
        mujoco.mj_jacSubtreeCom(m, d, self._jacp, self.pelvis)
        self._jac[row : row + 2] = self._jacp[:2]
        row += 2
        mujoco.mj_jacBody(m, d, self._jacp, self._jacr, self.pelvis)
        err[row] = targets.pelvis_z[t] - d.xpos[self.pelvis, 2]
        self._jac[row] = self._jacp[2]
        err[row + 1 : row + 4] = quat_to_axis_angle(
            quat_mul(targets.pelvis_quat[t], quat_conjugate(d.xquat[self.pelvis]))
        )
        self._jac[row + 1 : row + 4] = self._jacr
        return err, self._jac[:, self.dofs]

    def solve(
        self,
        targets: IKTargets,
        qpos_init: np.ndarray,
        first_iterations: int = 100,
        iterations: int = 6,
        tolerance: float = 1e-6,
    ) -> tuple[np.ndarray, np.ndarray]:
        """qpos [T, nq] and the remaining task errors [T, TASK_ROWS] (m or rad; rows as in TASK_SLICES)."""
        m, d = self.model, self.data
        num = targets.pelvis_z.shape[0]
        qpos_out = np.empty((num, m.nq))
        errors = np.empty((num, TASK_ROWS))
        d.qpos[:] = qpos_init
        dv = np.zeros(m.nv)
        lam = self.damping**2 * np.eye(self.dofs.size)
        ori_w = targets.foot_ori_weight if targets.foot_ori_weight is not None else np.ones((num, 2))
        for t in range(num):
            d.qpos[self.fixed_q] = targets.joint_pos[t]
            w = self.row_weights.copy()
            w[3:6] *= ori_w[t, 0]
            w[9:12] *= ori_w[t, 1]
            for _ in range(first_iterations if t == 0 else iterations):
                err, jac = self._residual(targets, t)
                if np.abs(err).max() < tolerance:
                    break
                jw = jac.T * w
                dv[:] = 0.0
                dv[self.dofs] = np.linalg.solve(jw @ jac + lam, jw @ err)
                mujoco.mj_integratePos(m, d.qpos, dv, 1.0)
                d.qpos[self.solved_q] = np.clip(d.qpos[self.solved_q], self.low, self.high)
            errors[t], _ = self._residual(targets, t)
            qpos_out[t] = d.qpos
        return qpos_out, errors
