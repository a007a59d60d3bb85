"""Event terms: domain randomisation and pushes (BeyondMimic notes section 3.6).

Each is `f(env, envs, **params)`: `envs` is the Bool[num_envs] mask of the worlds it applies to now
(every world at start-up; the due worlds of an interval; the worlds starting an episode at a reset),
and the function writes all worlds with the mask applied, so shapes never depend on data. The
`event` decorator records the modes a function supports, the model fields it makes per-world
(the simulator allocates those per world) and the check of its parameters, which
`bmimic.envs.config.check_env` runs before anything is built. Startup terms run eagerly before the
step is captured and may do host work; interval and reset terms run inside the captured step.
"""

from __future__ import annotations

from typing import Any, Callable, Sequence

import mujoco
import torch

from bmimic import BmimicError
from bmimic.envs.quat import quat_apply_inverse

__all__ = ["randomize_foot_friction", "offset_body_com", "offset_default_joint_pos", "push_root_velocity"]


def event(modes: Sequence[str], model_fields: Sequence[str] = (), check: Callable[..., None] | None = None):
    """Mark an event function with the modes it supports, the model fields it randomises per world
    and its parameter check (raising ValueError("<param>: <problem>"))."""

    def mark(fn):
        fn.modes, fn.model_fields, fn.check_params = tuple(modes), tuple(model_fields), check
        return fn

    return mark


def _range(name: str, value: Any) -> None:
    value = list(value)
    if len(value) != 2 or not 0 < value[0] <= value[1]:
        raise ValueError(f"{name}: must be [low, high] with 0 < low <= high, got {value}")


def _half_widths(name: str, value: Any, length: int = 3) -> None:
    value = list(value) if length > 1 else [value]
    if len(value) != length or any(v < 0 for v in value):
        what = f"{length} half-widths" if length > 1 else "a half-width"
        raise ValueError(f"{name}: must be {what} >= 0, got {value if length > 1 else value[0]}")


def _check_friction(friction_range: Any) -> None:
    _range("friction_range", friction_range)


def _check_com(body: Any, offset_m: Any) -> None:
    if not isinstance(body, str) or not body:
        raise ValueError(f"body: must be a body name, got {body!r}")
    _half_widths("offset_m", offset_m)


def _check_default_joint(offset_rad: Any) -> None:
    _half_widths("offset_rad", offset_rad, 1)


def _check_push(lin_vel_mps: Any, ang_vel_radps: Any) -> None:
    _half_widths("lin_vel_mps", lin_vel_mps)
    _half_widths("ang_vel_radps", ang_vel_radps)


@event(modes=("startup",), model_fields=("geom_friction",), check=_check_friction)
def randomize_foot_friction(env, envs: torch.Tensor, friction_range: Sequence[float]) -> None:
    """Sliding friction of the feet's contact geoms, uniform in [low, high] per world: the geoms with
    contact priority (the soles, which govern their contacts), else the end effectors' colliding geoms."""
    mjm = env.sim.mjm
    feet = [g for g in range(mjm.ngeom) if mjm.geom_priority[g] > 0]
    if not feet:
        ee = set(int(i) for i in env.robot.end_effector_body_ids)
        feet = [g for g in range(mjm.ngeom) if int(mjm.geom_bodyid[g]) in ee and mjm.geom_contype[g]]
    ids = torch.as_tensor(feet, dtype=torch.long, device=env.device)
    n = env.num_envs
    lo, hi = friction_range
    mu = lo + (hi - lo) * torch.rand(n, 1, device=env.device)
    friction = env.sim.geom_friction
    friction[:, ids, 0] = torch.where(envs[:, None], mu.expand(n, len(ids)), friction[:, ids, 0])


@event(modes=("startup",), model_fields=("body_ipos",), check=_check_com)
def offset_body_com(env, envs: torch.Tensor, body: str, offset_m: Sequence[float]) -> None:
    """Move `body`'s centre of mass by a uniform offset per world (half-widths along x, y, z). Adds to
    the current value, hence startup only."""
    body_id = mujoco.mj_name2id(env.sim.mjm, mujoco.mjtObj.mjOBJ_BODY, body)
    if body_id < 0:
        raise BmimicError(f"env.events: offset_body_com names body {body!r}, which the robot model does not have")
    shift = env.uniform((env.num_envs, 3), list(offset_m)) * envs[:, None]
    env.sim.body_ipos[:, body_id] += shift


@event(modes=("startup",), check=_check_default_joint)
def offset_default_joint_pos(env, envs: torch.Tensor, offset_rad: float) -> None:
    """A per-world calibration offset, uniform in +-offset_rad, added to the default joint pose (the
    action offset and the joint observation's origin). Adds to the current value, hence startup only."""
    env.default_joint_pos += env.uniform((env.num_envs, env.num_actions), offset_rad) * envs[:, None]


@event(modes=("interval", "reset"), check=_check_push)
def push_root_velocity(env, envs: torch.Tensor, lin_vel_mps: Sequence[float], ang_vel_radps: Sequence[float]) -> None:
    """Add a uniform velocity change to the root: linear (world frame) and angular (drawn in the world
    frame, written in the free joint's body frame), half-widths along x, y, z."""
    n = env.num_envs
    dv = env.uniform((n, 3), list(lin_vel_mps))
    dw = quat_apply_inverse(env.sim.qpos[:, 3:7], env.uniform((n, 3), list(ang_vel_radps)))
    push = torch.cat((dv, dw), dim=-1) * envs[:, None]
    env.sim.qvel[:, 0:6] += push
