"""Reference-state initialisation: put envs at the reference state of a frame, with the uniform
noise of `env.reset` when training (BeyondMimic's RSI)."""

from __future__ import annotations

import torch

from bmimic.envs.config import ResetConfig
from bmimic.envs.noise import UniformNoise
from bmimic.envs.quat import quat_apply_inverse, quat_from_euler_xyz, quat_mul
from bmimic.motion.reference import ReferenceMotion
from bmimic.sim import Simulator


def write_reference_state(sim: Simulator, ref: ReferenceMotion, mask: torch.Tensor, frames: torch.Tensor,
                          noise: ResetConfig | None = None, uniform: UniformNoise | None = None,
                          soft_joint_limits: torch.Tensor | None = None) -> None:
    """Write qpos/qvel of the masked envs: the reference at `frames`, plus (with `noise`) uniform
    offsets of the root pose and velocity and of the joints, clipped to the soft joint limits.
    Masked `torch.where` writes over every env; kinematics must be recomputed afterwards."""
    pos = ref.root_pos[frames]
    quat = ref.root_quat[frames]
    lin = ref.root_lin_vel[frames]
    ang_w = ref.root_ang_vel[frames]
    q = ref.joint_pos[frames]
    qd = ref.joint_vel[frames]
    if noise is not None:
        assert uniform is not None and soft_joint_limits is not None, "reset noise needs uniform and the limits"
        n = frames.shape[0]
        pos = pos + uniform((n, 3), list(noise.root_pos_range_m))
        rpy = uniform((n, 3), list(noise.root_rot_range_rad))
        quat = quat_mul(quat_from_euler_xyz(rpy[:, 0], rpy[:, 1], rpy[:, 2]), quat)
        lin = lin + uniform((n, 3), list(noise.root_lin_vel_range_mps))
        ang_w = ang_w + uniform((n, 3), list(noise.root_ang_vel_range_radps))
        q = q + uniform(q.shape, noise.joint_pos_range_rad)
        q = torch.minimum(torch.maximum(q, soft_joint_limits[:, 0]), soft_joint_limits[:, 1])
    qpos = torch.cat((pos, quat, q), dim=-1)
    qvel = torch.cat((lin, quat_apply_inverse(quat, ang_w), qd), dim=-1)  # free-joint angular vel is local
    m = mask[:, None]
    sim.qpos[:] = torch.where(m, qpos, sim.qpos)
    sim.qvel[:] = torch.where(m, qvel, sim.qvel)


__all__ = ["write_reference_state"]
