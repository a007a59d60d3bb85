"""Observation terms (BeyondMimic notes section 3.3). Each returns Tensor[num_envs, dim]."""

from __future__ import annotations

import torch

from bmimic.envs.quat import first_two_columns, quat_apply_inverse, quat_conj, quat_mul

__all__ = [
    "motion_command", "motion_anchor_pos_b", "motion_anchor_ori_b", "robot_body_pos_b", "robot_body_ori_b",
    "base_lin_vel", "base_ang_vel", "joint_pos_rel", "joint_vel_rel", "last_action",
]


def motion_command(env) -> torch.Tensor:
    """Reference joint positions and velocities of the current frame (58)."""
    s = env.state
    return torch.cat((s.ref_joint_pos, s.ref_joint_vel), dim=-1)


def motion_anchor_pos_b(env) -> torch.Tensor:
    """Reference anchor position in the robot anchor's frame (3)."""
    s = env.state
    return quat_apply_inverse(s.robot_anchor_quat, s.ref_anchor_pos - s.robot_anchor_pos)


def motion_anchor_ori_b(env) -> torch.Tensor:
    """Reference anchor orientation relative to the robot anchor, first two matrix columns (6)."""
    s = env.state
    return first_two_columns(quat_mul(quat_conj(s.robot_anchor_quat), s.ref_anchor_quat))


def robot_body_pos_b(env) -> torch.Tensor:
    """Tracked robot body positions in the robot anchor's frame (3 per body)."""
    s = env.state
    anchor_q = s.robot_anchor_quat[:, None].expand_as(s.robot_body_quat)
    rel = quat_apply_inverse(anchor_q, s.robot_body_pos - s.robot_anchor_pos[:, None])
    return rel.reshape(env.num_envs, -1)


def robot_body_ori_b(env) -> torch.Tensor:
    """Tracked robot body orientations relative to the robot anchor, two matrix columns (6 per body)."""
    s = env.state
    anchor_q = s.robot_anchor_quat[:, None].expand_as(s.robot_body_quat)
    return first_two_columns(quat_mul(quat_conj(anchor_q), s.robot_body_quat)).reshape(env.num_envs, -1)


def base_lin_vel(env) -> torch.Tensor:
    """Pelvis linear velocity in the pelvis frame (3)."""
    return env.state.root_lin_vel_b


def base_ang_vel(env) -> torch.Tensor:
    """Pelvis angular velocity in the pelvis frame (3)."""
    return env.state.root_ang_vel_b


def joint_pos_rel(env) -> torch.Tensor:
    """Joint positions relative to the (per-world) default pose (29)."""
    return env.state.joint_pos - env.default_joint_pos


def joint_vel_rel(env) -> torch.Tensor:
    """Joint velocities (29)."""
    return env.state.joint_vel


def last_action(env) -> torch.Tensor:
    """The policy's last raw action (29)."""
    return env.actions
