"""Building a `Motion` from generalised coordinates (shared by the CSV converter and the built-in
motions): velocities by finite differences, body states by MuJoCo forward kinematics."""

from __future__ import annotations

from typing import Sequence

import mujoco
import numpy as np

from bmimic.motion.math import angular_velocity_from_quats, quat_normalize, quat_rotate_inverse
from bmimic.motion.model import free_joint_qposadr, joint_addresses, model_body_names, model_joint_names
from bmimic.motion.motion import Motion
from bmimic.motion.segments import MotionDataError, Segment


def kinematic_motion(
    mjmodel: mujoco.MjModel,
    fps: float,
    root_pos: np.ndarray,
    root_quat: np.ndarray,
    joint_pos: np.ndarray,
    joint_names: Sequence[str],
    segments: Sequence[Segment] = (),
) -> Motion:
    """Velocities by finite differences and body states by MuJoCo forward kinematics.

    root_pos [T, 3] m, root_quat [T, 4] (w, x, y, z), joint_pos [T, J] rad for the named joints; joints
    of the model not named stay at qpos0. Joint and root linear velocities are central differences
    (np.gradient, one-sided at the ends); the root angular velocity comes from quaternion differences
    (world frame). Body velocities are those of the body origins (xpos) in the world frame, from
    `cvel`: v_origin = v_com - w x (subtree_com[root] - xpos).
    """
    names = list(joint_names)
    model_joints = model_joint_names(mjmodel)
    if sorted(names) != sorted(model_joints):
        raise MotionDataError(
            f"joints {sorted(set(model_joints) ^ set(names))} are not both in the data and in the robot model"
        )
    dt = 1.0 / float(fps)
    num = root_pos.shape[0]
    if num < 2:
        raise MotionDataError(f"a motion needs at least two frames, got {num}")
    root_quat = quat_normalize(np.asarray(root_quat, dtype=np.float64))
    root_pos = np.asarray(root_pos, dtype=np.float64)
    joint_pos = np.asarray(joint_pos, dtype=np.float64)
    root_lin_vel = np.gradient(root_pos, dt, axis=0)
    root_ang_vel = angular_velocity_from_quats(root_quat, dt)
    joint_vel = np.gradient(joint_pos, dt, axis=0)

    free_q, free_v = free_joint_qposadr(mjmodel)
    qadr, vadr = joint_addresses(mjmodel, joint_names)
    qpos = np.tile(mjmodel.qpos0, (num, 1))
    qvel = np.zeros((num, mjmodel.nv))
    qpos[:, free_q : free_q + 3] = root_pos
    qpos[:, free_q + 3 : free_q + 7] = root_quat
    qpos[:, qadr] = joint_pos
    qvel[:, free_v : free_v + 3] = root_lin_vel
    # MuJoCo's free joint takes its angular velocity in the body frame.
    qvel[:, free_v + 3 : free_v + 6] = quat_rotate_inverse(root_quat, root_ang_vel)
    qvel[:, vadr] = joint_vel

    nb = mjmodel.nbody - 1
    xpos = np.empty((num, nb, 3))
    xquat = np.empty((num, nb, 4))
    cvel = np.empty((num, nb, 6))
    com = np.empty((num, nb, 3))
    root_ids = mjmodel.body_rootid[1:]
    data = mujoco.MjData(mjmodel)
    for t in range(num):
        data.qpos[:] = qpos[t]
        data.qvel[:] = qvel[t]
        mujoco.mj_kinematics(mjmodel, data)
        mujoco.mj_comPos(mjmodel, data)
        mujoco.mj_comVel(mjmodel, data)
        xpos[t] = data.xpos[1:]
        xquat[t] = data.xquat[1:]
        cvel[t] = data.cvel[1:]
        com[t] = data.subtree_com[root_ids]
    ang = cvel[..., :3]
    lin = cvel[..., 3:] - np.cross(ang, com - xpos)

    order = [names.index(n) for n in model_joints]
    return Motion(
        fps=fps,
        joint_pos=joint_pos[:, order],
        joint_vel=joint_vel[:, order],
        body_pos_w=xpos,
        body_quat_w=xquat,
        body_lin_vel_w=lin,
        body_ang_vel_w=ang,
        joint_names=[names[i] for i in order],
        body_names=model_body_names(mjmodel),
        segments=list(segments),
    )
