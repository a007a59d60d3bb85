"""Termination terms (BeyondMimic notes section 3.5). Each returns BoolTensor[num_envs]."""

from __future__ import annotations

import torch

from bmimic.envs.quat import quat_apply_inverse

__all__ = ["time_out", "bad_anchor_pos_z_only", "bad_anchor_ori", "bad_motion_body_pos_z_only"]


def time_out(env) -> torch.Tensor:
    """The episode reached its length (a truncation, never a failure)."""
    return env.episode_length_buf >= env.max_episode_length


def bad_anchor_pos_z_only(env, threshold_m: float) -> torch.Tensor:
    s = env.state
    return (s.ref_anchor_pos[:, 2] - s.robot_anchor_pos[:, 2]).abs() > threshold_m


def bad_anchor_ori(env, threshold: float) -> torch.Tensor:
    """Difference of the projected-gravity z components (cosine of tilt), unitless."""
    s = env.state
    g = env.gravity_w.expand(env.num_envs, 3)
    ref_z = quat_apply_inverse(s.ref_anchor_quat, g)[:, 2]
    robot_z = quat_apply_inverse(s.robot_anchor_quat, g)[:, 2]
    return (ref_z - robot_z).abs() > threshold


def bad_motion_body_pos_z_only(env, threshold_m: float) -> torch.Tensor:
    """Any end effector (feet, hands) off its relative target height by more than the threshold."""
    s = env.state
    idx = env.bodies.end_effectors
    err = (s.ref_body_pos_relative[:, idx, 2] - s.robot_body_pos[:, idx, 2]).abs()
    return (err > threshold_m).any(dim=-1)
