"""`ReferenceMotion`: a motion as the simulation reads it, on the device.

Built once from a `Motion` for the bodies a robot tracks: the per-frame tensors (joints, tracked body
poses and velocities, the root state) and the clip boundaries. The training and evaluation
environments index it with each env's frame every step; play draws its ghost from it. A motion
library is several clips back to back on one time axis (`Motion.concatenate`): `clip_starts` and
`clip_ends` give each clip's frame range, and `frame_clip_end` maps every frame to the end of its
clip, where the environment resamples instead of running on into the next clip.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np
import torch

from bmimic.motion.motion import Motion
from bmimic.motion.segments import MotionDataError

if TYPE_CHECKING:
    from bmimic.robot.config import RobotInfo


class ReferenceMotion:
    """Device tensors of a `Motion` (float32; shapes below with T frames, J joints, B tracked bodies).

    joint_pos, joint_vel               [T, J]     rad, rad/s (model joint order)
    body_pos, body_quat                [T, B, 3|4] tracked bodies, world frame, quaternions w, x, y, z
    body_lin_vel, body_ang_vel         [T, B, 3]  world frame (velocity of the body origin)
    root_pos, root_quat                [T, 3|4]   the floating base (the model's first body)
    root_lin_vel, root_ang_vel         [T, 3]     world frame
    clip_starts, clip_ends             [C]        first frame and one past the last frame of each clip
    frame_clip_end                     [T]        one past the last frame of each frame's clip
    """

    def __init__(self, motion: Motion, tracked_bodies: Sequence[str], root_body: str, device: torch.device | str = "cpu") -> None:
        index = {n: i for i, n in enumerate(motion.body_names)}
        missing = [n for n in [*tracked_bodies, root_body] if n not in index]
        if missing:
            raise MotionDataError(f"motion: has no bodies named {missing}; it was made for another robot model")
        bodies, root = [index[n] for n in tracked_bodies], index[root_body]
        self.device = torch.device(device)
        self.motion = motion
        """The host motion (segments, names, fps)."""
        self.body_names = list(tracked_bodies)
        self.fps = motion.fps
        self.num_frames = motion.num_frames
        t = self._tensor
        self.joint_pos = t(motion.joint_pos)
        self.joint_vel = t(motion.joint_vel)
        self.body_pos = t(motion.body_pos_w[:, bodies])
        self.body_quat = t(motion.body_quat_w[:, bodies])
        self.body_lin_vel = t(motion.body_lin_vel_w[:, bodies])
        self.body_ang_vel = t(motion.body_ang_vel_w[:, bodies])
        self.root_pos = t(motion.body_pos_w[:, root])
        self.root_quat = t(motion.body_quat_w[:, root])
        self.root_lin_vel = t(motion.body_lin_vel_w[:, root])
        self.root_ang_vel = t(motion.body_ang_vel_w[:, root])
        starts = np.asarray(motion.clip_starts, dtype=np.int64)
        ends = np.append(starts[1:], motion.num_frames)
        self.clip_starts = torch.as_tensor(starts, device=self.device)
        self.clip_ends = torch.as_tensor(ends, device=self.device)
        self.frame_clip_end = torch.as_tensor(np.repeat(ends, ends - starts), device=self.device)

    @classmethod
    def for_robot(cls, motion: Motion, robot: RobotInfo, device: torch.device | str = "cpu") -> ReferenceMotion:
        """The reference of `motion` for a `bmimic.robot.RobotInfo`: its tracked bodies, in its order,
        and its root body (MuJoCo body ids start at 1; 0 is the world)."""
        names = list(robot.body_names)
        tracked = [names[int(i) - 1] for i in robot.tracked_body_ids]
        return cls(motion, tracked, names[0], device)

    def _tensor(self, x: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(x), dtype=torch.float32, device=self.device)

    @property
    def nbytes(self) -> int:
        """Bytes of the device tensors (one copy, shared by every env that reads it)."""
        return sum(int(v.numel() * v.element_size()) for v in vars(self).values() if isinstance(v, torch.Tensor))

    @property
    def duration_s(self) -> float:
        return self.motion.duration_s

    def qpos(self, frames: torch.Tensor) -> torch.Tensor:
        """Generalised positions of the reference at `frames` ([..., 7 + J]: root position, root
        quaternion, joints), as the model's qpos; for drawing the reference (play's ghost)."""
        return torch.cat((self.root_pos[frames], self.root_quat[frames], self.joint_pos[frames]), dim=-1)


__all__ = ["ReferenceMotion"]
