"""The robot's bodies as the MDP reads them: device index tensors resolved once from the model and
the robot config, with the checks that the two agree."""

from __future__ import annotations

import mujoco
import numpy as np
import torch

from bmimic import BmimicError
from bmimic.robot import RobotInfo


class TrackedBodies:
    """Tracked bodies (`ids`, MuJoCo body ids in config order), the anchor and end effectors as
    positions in that order, the root of the robot's tree, and the contact lookup tables."""

    def __init__(self, mjm: mujoco.MjModel, robot: RobotInfo, device: torch.device | str) -> None:
        nj = len(robot.joint_names)
        if mjm.jnt_type[0] != mujoco.mjtJoint.mjJNT_FREE or not np.array_equal(robot.qpos_adr, np.arange(7, 7 + nj)):
            raise BmimicError("robot model: expected a free joint followed by the actuated hinges in qpos")
        if mjm.nu != nj:
            raise BmimicError(f"robot model: {mjm.nu} actuators for {nj} joints; expected one per joint")
        tracked = [int(i) for i in robot.tracked_body_ids]
        if int(robot.anchor_body_id) not in tracked:
            raise BmimicError("robot.anchor_body must be one of robot.tracked_bodies")
        if any(int(i) not in tracked for i in robot.end_effector_body_ids):
            raise BmimicError("robot.end_effector_bodies must all be in robot.tracked_bodies")
        self.ids = torch.as_tensor(tracked, dtype=torch.long, device=device)
        self.anchor = tracked.index(int(robot.anchor_body_id))
        """Position of the anchor body among the tracked bodies."""
        self.end_effectors = torch.as_tensor([tracked.index(int(i)) for i in robot.end_effector_body_ids],
                                             dtype=torch.long, device=device)
        """Positions of the end effectors among the tracked bodies."""
        self.root_body_id = int(mjm.body_rootid[tracked[0]])
        """Root body of the robot tree: MuJoCo's cvel is expressed about subtree_com of this body."""
        undesired = np.zeros(mjm.nbody, dtype=bool)
        undesired[1:] = True  # any robot body except the end effectors (and the world)
        undesired[np.asarray(robot.end_effector_body_ids, dtype=int)] = False
        self.undesired = torch.as_tensor(undesired, device=device)
        """Bool[nbody]: a contact touching one of these bodies is an undesired contact."""
        self.geom_body = torch.as_tensor(mjm.geom_bodyid, dtype=torch.long, device=device)
        """Long[ngeom]: the body of each geom."""


__all__ = ["TrackedBodies"]
