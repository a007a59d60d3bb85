"""`TrackingState`: the quantities every term reads, computed once per simulator state from the
robot's bodies and the reference at each env's frame."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from bmimic.envs.bodies import TrackedBodies
from bmimic.envs.quat import (
    quat_apply,
    quat_apply_inverse,
    quat_conj,
    quat_error_magnitude,
    quat_mul,
    yaw_quat,
)
from bmimic.motion.reference import ReferenceMotion
from bmimic.sim import Simulator


@dataclass
class TrackingState:
    """Shapes [N, ...], B = tracked bodies; `ref_*` is the reference at each env's frame."""

    joint_pos: torch.Tensor
    joint_vel: torch.Tensor
    root_lin_vel_b: torch.Tensor
    root_ang_vel_b: torch.Tensor
    robot_body_pos: torch.Tensor
    robot_body_quat: torch.Tensor
    robot_body_lin_vel: torch.Tensor
    robot_body_ang_vel: torch.Tensor
    robot_anchor_pos: torch.Tensor
    robot_anchor_quat: torch.Tensor
    ref_joint_pos: torch.Tensor
    ref_joint_vel: torch.Tensor
    ref_body_pos: torch.Tensor
    ref_body_quat: torch.Tensor
    ref_body_lin_vel: torch.Tensor
    ref_body_ang_vel: torch.Tensor
    ref_anchor_pos: torch.Tensor
    ref_anchor_quat: torch.Tensor
    ref_body_pos_relative: torch.Tensor
    ref_body_quat_relative: torch.Tensor


def compute_state(sim: Simulator, ref: ReferenceMotion, bodies: TrackedBodies, frames: torch.Tensor) -> TrackingState:
    """The state of every env from the simulator's (fresh) kinematics and the reference at `frames`."""
    ids, a = bodies.ids, bodies.anchor
    f = frames.clamp(0, ref.num_frames - 1)
    root_quat = sim.qpos[:, 3:7]
    body_pos = sim.xpos[:, ids]
    body_quat = sim.xquat[:, ids]
    cvel = sim.cvel[:, ids]
    ang = cvel[..., 0:3]
    com = sim.subtree_com[:, bodies.root_body_id][:, None]
    lin = cvel[..., 3:6] + torch.cross(ang, body_pos - com, dim=-1)  # velocity of the body origin
    ref_pos = ref.body_pos[f]
    ref_quat = ref.body_quat[f]
    robot_anchor_pos, robot_anchor_quat = body_pos[:, a], body_quat[:, a]
    ref_anchor_pos, ref_anchor_quat = ref_pos[:, a], ref_quat[:, a]
    # Anchor-centred, yaw-aligned, height-preserving targets (BeyondMimic).
    delta_pos = torch.cat((robot_anchor_pos[:, :2], ref_anchor_pos[:, 2:3]), dim=-1)
    delta_rot = yaw_quat(quat_mul(robot_anchor_quat, quat_conj(ref_anchor_quat)))
    delta_rot_b = delta_rot[:, None].expand_as(ref_quat)
    rel_pos = delta_pos[:, None] + quat_apply(delta_rot_b, ref_pos - ref_anchor_pos[:, None])
    rel_quat = quat_mul(delta_rot_b, ref_quat)
    return TrackingState(
        joint_pos=sim.qpos[:, 7:],
        joint_vel=sim.qvel[:, 6:],
        root_lin_vel_b=quat_apply_inverse(root_quat, sim.qvel[:, 0:3]),
        root_ang_vel_b=sim.qvel[:, 3:6],
        robot_body_pos=body_pos,
        robot_body_quat=body_quat,
        robot_body_lin_vel=lin,
        robot_body_ang_vel=ang,
        robot_anchor_pos=robot_anchor_pos,
        robot_anchor_quat=robot_anchor_quat,
        ref_joint_pos=ref.joint_pos[f],
        ref_joint_vel=ref.joint_vel[f],
        ref_body_pos=ref_pos,
        ref_body_quat=ref_quat,
        ref_body_lin_vel=ref.body_lin_vel[f],
        ref_body_ang_vel=ref.body_ang_vel[f],
        ref_anchor_pos=ref_anchor_pos,
        ref_anchor_quat=ref_anchor_quat,
        ref_body_pos_relative=rel_pos,
        ref_body_quat_relative=rel_quat,
    )


def tracking_errors(state: TrackingState) -> torch.Tensor:
    """Every env's per-step tracking errors [4, N] (bmimic.sampling.base.ERROR_COMPONENTS): the mean over
    tracked bodies of the position (anchor-relative reference, m), orientation (rad) and linear-velocity
    (m/s) errors, and the largest body position error (m); what error-driven samplers learn from."""
    pos = (state.ref_body_pos_relative - state.robot_body_pos).norm(dim=-1)  # [N, bodies] m
    return torch.stack((
        pos.mean(-1),
        quat_error_magnitude(state.ref_body_quat_relative, state.robot_body_quat).mean(-1),
        (state.ref_body_lin_vel - state.robot_body_lin_vel).norm(dim=-1).mean(-1),
        pos.amax(-1),
    ))


__all__ = ["TrackingState", "compute_state", "tracking_errors"]
