"""The robot model as motions see it: joint and body names in MuJoCo order, joint addresses, and
the joint-limit check. Motions are mapped to a model by these names, never by position."""

from __future__ import annotations

from typing import Sequence

import mujoco
import numpy as np

from bmimic.motion.segments import MotionDataError


def model_joint_names(mjmodel: mujoco.MjModel) -> list[str]:
    """Names of the model's hinge and slide joints in MuJoCo order (the free joint is left out)."""
    free = mujoco.mjtJoint.mjJNT_FREE
    return [mjmodel.joint(j).name for j in range(mjmodel.njnt) if mjmodel.jnt_type[j] != free]


def model_body_names(mjmodel: mujoco.MjModel) -> list[str]:
    """Names of the model's bodies in MuJoCo order without the world body."""
    return [mjmodel.body(b).name for b in range(1, mjmodel.nbody)]


def free_joint_qposadr(mjmodel: mujoco.MjModel) -> tuple[int, int]:
    """qpos and qvel addresses of the robot's floating-base (free) joint."""
    for j in range(mjmodel.njnt):
        if mjmodel.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            return int(mjmodel.jnt_qposadr[j]), int(mjmodel.jnt_dofadr[j])
    raise MotionDataError("the robot model has no free joint; motions need a floating base")


def joint_addresses(mjmodel: mujoco.MjModel, joint_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """qpos and qvel addresses of the named joints (raises if a name is not in the model)."""
    qpos_adr, dof_adr = [], []
    for name in joint_names:
        jid = mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise MotionDataError(f"joint '{name}' is not in the robot model")
        qpos_adr.append(mjmodel.jnt_qposadr[jid])
        dof_adr.append(mjmodel.jnt_dofadr[jid])
    return np.asarray(qpos_adr, dtype=np.int64), np.asarray(dof_adr, dtype=np.int64)


def find_joint_limit_violation(
    joint_pos: np.ndarray, joint_names: Sequence[str], mjmodel: mujoco.MjModel, tolerance_rad: float = 0.1
) -> tuple[int, int, float, float, float] | None:
    """First (frame, joint index, value, low, high) where a limited joint leaves its range by more than
    `tolerance_rad`, or None."""
    low = np.full(len(joint_names), -np.inf)
    high = np.full(len(joint_names), np.inf)
    for k, name in enumerate(joint_names):
        jid = mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid >= 0 and mjmodel.jnt_limited[jid]:
            low[k], high[k] = mjmodel.jnt_range[jid]
    bad = (joint_pos < low - tolerance_rad) | (joint_pos > high + tolerance_rad)
    if not bad.any():
        return None
    frame, joint = np.argwhere(bad)[0]
    return int(frame), int(joint), float(joint_pos[frame, joint]), float(low[joint]), float(high[joint])
