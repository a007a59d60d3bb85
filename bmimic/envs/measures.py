"""What an evaluation measures at every step of an evaluation env (bmimic.envs.TrackingEnv in eval mode):
the tracking errors, each by the name bmimic.runs.schema.TRACKING_ERRORS declares with its unit and
label, and the policy's smoothness. The evaluators (bmimic.training.evaluator, whole_clip) stack them
per step in the schema's column order; sim2sim computes the same names from native MuJoCo
(bmimic.sim2sim.rollout.Rollout's `_e_<name>`)."""

from __future__ import annotations

from typing import Any, Callable

import torch

from bmimic.envs.quat import quat_error_magnitude
from bmimic.runs.schema import (
    ANCHOR_ORI_ERR_RAD,
    BODY_ORI_ERR_RAD,
    EE_POS_ERR_MM,
    ERROR_COLUMNS,
    JOINT_POS_ERR_RAD,
    JOINT_VEL_ERR_RADPS,
    MPKPE_MM,
    MPKPE_REL_MM,
)


def _mpkpe_mm(env) -> torch.Tensor:
    s = env.state
    return 1000.0 * (s.ref_body_pos - s.robot_body_pos).norm(dim=-1).mean(-1)


def _mpkpe_rel_mm(env) -> torch.Tensor:
    s = env.state
    ref_rel = s.ref_body_pos - s.ref_anchor_pos[:, None]
    rob_rel = s.robot_body_pos - s.robot_anchor_pos[:, None]
    return 1000.0 * (ref_rel - rob_rel).norm(dim=-1).mean(-1)


def _anchor_ori_err_rad(env) -> torch.Tensor:
    s, a = env.state, env.bodies.anchor
    return quat_error_magnitude(s.ref_body_quat[:, a], s.robot_body_quat[:, a])


def _body_ori_err_rad(env) -> torch.Tensor:
    s = env.state
    return quat_error_magnitude(s.ref_body_quat_relative, s.robot_body_quat).mean(-1)


def _joint_pos_err_rad(env) -> torch.Tensor:
    s = env.state
    return (s.ref_joint_pos - s.joint_pos).abs().mean(-1)


def _joint_vel_err_radps(env) -> torch.Tensor:
    s = env.state
    return (s.ref_joint_vel - s.joint_vel).abs().mean(-1)


def _ee_pos_err_mm(env) -> torch.Tensor:
    s, ee = env.state, env.bodies.end_effectors
    return 1000.0 * (s.ref_body_pos_relative[:, ee] - s.robot_body_pos[:, ee]).norm(dim=-1).mean(-1)


ERROR_TERMS: dict[str, Callable[[Any], torch.Tensor]] = {
    MPKPE_MM: _mpkpe_mm,
    MPKPE_REL_MM: _mpkpe_rel_mm,
    ANCHOR_ORI_ERR_RAD: _anchor_ori_err_rad,
    BODY_ORI_ERR_RAD: _body_ori_err_rad,
    JOINT_POS_ERR_RAD: _joint_pos_err_rad,
    JOINT_VEL_ERR_RADPS: _joint_vel_err_radps,
    EE_POS_ERR_MM: _ee_pos_err_mm,
}
"""How each tracking error (bmimic.runs.schema.TRACKING_ERRORS: name, unit, label) is computed from an
evaluation env's state, [N] per env; sim2sim computes the same names from native MuJoCo
(bmimic.sim2sim.rollout.Rollout's `_e_<name>`). Mean over tracked bodies (end-effectors for ee_pos),
global positions for mpkpe, anchor-relative ones for mpkpe_rel and the anchor-centred targets for ee_pos."""


def step_errors(env) -> torch.Tensor:
    """[N, len(ERROR_COLUMNS)] per-step tracking errors of the current state, in ERROR_COLUMNS' order."""
    return torch.stack([ERROR_TERMS[name](env) for name in ERROR_COLUMNS], dim=-1)


def smoothness(env, prev_joint_vel: torch.Tensor) -> torch.Tensor:
    """[N, len(SMOOTHNESS_COLUMNS)] the policy's action rate and joint acceleration this step."""
    action_rate = (env.actions - env.last_actions).square().sum(-1)
    joint_acc = ((env.state.joint_vel - prev_joint_vel).abs() / env.step_dt).mean(-1)
    return torch.stack((action_rate, joint_acc), dim=-1)


__all__ = ["ERROR_TERMS", "smoothness", "step_errors"]
