"""Robot configuration (conf/robot/*.yaml) and its resolution into per-joint arrays.

`RobotConfig` is the schema of a robot's numbers (motor classes, PD design, action scale, default pose,
tracked bodies), which conf/robot/<name>.yaml holds (BeyondMimic's G1: conf/robot/g1.yaml). `resolve_robot` turns it, together with a compiled `MjModel`, into a
`RobotInfo` of numpy arrays in model joint order, which the simulator and the environment consume.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Dict, List, Optional

import numpy as np
from omegaconf import MISSING

from bmimic import BmimicError

if TYPE_CHECKING:
    import mujoco


class RobotModelError(BmimicError, ValueError):
    """A robot model or robot config is unusable (bad file, wrong joints, unmatched names)."""


@dataclass
class ActuatorClassConfig:
    """One motor class: the joints it drives and its reflected inertia and torque limit."""

    name: str = ""
    """Motor name, for messages and readability (e.g. "7520_14")."""
    joints: List[str] = field(default_factory=list)
    """Regular expressions matched in full against joint names; every joint must match exactly one class."""
    armature: float = 0.0
    """Reflected rotor inertia in kg m^2, set as the joint armature and used to derive the PD gains."""
    effort_limit_nm: float = 0.0
    """Peak torque in Nm: actuator force range is +-this value; also sets the action scale."""


@dataclass
class RobotConfig:
    """A robot model and its actuation. Every value comes from conf/robot/<name>.yaml (a robot's numbers
    live there only; `bmimic.robot.registry.robot_config` reads one outside Hydra)."""

    name: str = MISSING
    """Built-in robot: its body is bmimic/robot/models/<name>.py (`bmimic.robot.registry`)."""
    mjcf_path: Optional[str] = None
    """Optional user MJCF (e.g. the Menagerie G1 with meshes); must have the 29 G1 hinge joints by name."""
    actuator_classes: List[ActuatorClassConfig] = MISSING
    """Motor classes; each joint must match exactly one class."""
    natural_frequency_hz: float = MISSING
    """PD natural frequency f: Kp = armature * (2 pi f)^2."""
    damping_ratio: float = MISSING
    """PD damping ratio zeta: Kd = 2 zeta armature (2 pi f)."""
    action_scale_factor: float = MISSING
    """Action scale per joint = factor * effort_limit / Kp (target = default + scale * action)."""
    soft_joint_limit_factor: float = MISSING
    """Soft joint limits are the hard range shrunk by this factor about its midpoint."""
    default_root_height_m: float = MISSING
    """Pelvis height of the default (knees-bent) pose."""
    default_joint_pos: Dict[str, float] = MISSING
    """Default pose: joint-name regex -> angle in rad; unmatched joints are 0, a joint may match one key only."""
    anchor_body: str = MISSING
    """Body whose pose anchors the reference motion to the robot."""
    tracked_bodies: List[str] = MISSING
    """Bodies whose pose and velocity are tracked (rewards, critic observations), in this order."""
    end_effector_bodies: List[str] = MISSING
    """Bodies checked by the end-effector height termination."""
    foot_friction: float = MISSING
    """Sliding friction of the built-in G1's foot contact geoms (they have priority over the floor)."""


@dataclass(frozen=True, eq=False)
class RobotInfo:
    """Per-joint and per-body arrays of a robot, in model joint order (actuator i drives joint i)."""

    joint_names: tuple
    """The 29 actuated hinge joints in model (depth-first) order."""
    body_names: tuple
    """Robot bodies in model order (world body excluded)."""
    kp: np.ndarray
    """Position gain per joint in Nm/rad."""
    kd: np.ndarray
    """Damping gain per joint in Nm s/rad."""
    armature: np.ndarray
    """Joint armature in kg m^2."""
    effort_limit: np.ndarray
    """Actuator torque limit in Nm."""
    action_scale: np.ndarray
    """Joint target = default_joint_pos + action_scale * action, in rad per unit action."""
    default_joint_pos: np.ndarray
    """Default pose in rad."""
    joint_limits: np.ndarray
    """Hard joint range (29, 2) in rad."""
    soft_joint_limits: np.ndarray
    """Soft joint range (29, 2) in rad (hard range shrunk about its midpoint)."""
    qpos_adr: np.ndarray
    """Index of each joint in qpos."""
    dof_adr: np.ndarray
    """Index of each joint in qvel."""
    anchor_body_id: int
    """MuJoCo body id of the anchor body."""
    tracked_body_ids: np.ndarray
    """MuJoCo body ids of the tracked bodies, in config order."""
    end_effector_body_ids: np.ndarray
    """MuJoCo body ids of the end-effector bodies, in config order."""
    default_root_height_m: float
    """Pelvis height of the default pose."""


def pd_gains(armature: np.ndarray, cfg: RobotConfig) -> tuple[np.ndarray, np.ndarray]:
    """Kp, Kd from armature: a critically designed second-order joint at the configured frequency."""
    omega = 2.0 * math.pi * cfg.natural_frequency_hz
    kp = armature * omega**2
    kd = 2.0 * cfg.damping_ratio * armature * omega
    return kp, kd


def joint_actuator_params(cfg: RobotConfig, joint_names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Armature and effort limit of each joint from the single actuator class that matches it."""
    armature = np.zeros(len(joint_names))
    effort = np.zeros(len(joint_names))
    for i, joint in enumerate(joint_names):
        matches = [c for c in cfg.actuator_classes if any(re.fullmatch(p, joint) for p in c.joints)]
        if len(matches) != 1:
            names = [c.name or f"#{cfg.actuator_classes.index(c)}" for c in matches]
            raise RobotModelError(
                f"robot.actuator_classes: joint {joint!r} matches {len(matches)} classes {names}, needs exactly one")
        armature[i] = matches[0].armature
        effort[i] = matches[0].effort_limit_nm
        if armature[i] <= 0 or effort[i] <= 0:
            raise RobotModelError(
                f"robot.actuator_classes[{matches[0].name!r}]: armature and effort_limit_nm must be > 0")
    return armature, effort


def default_joint_positions(cfg: RobotConfig, joint_names: list[str]) -> np.ndarray:
    """Default angle of each joint from `cfg.default_joint_pos` (regex keys; unmatched joints are 0)."""
    pos = np.zeros(len(joint_names))
    used = set()
    for i, joint in enumerate(joint_names):
        keys = [k for k in cfg.default_joint_pos if re.fullmatch(k, joint)]
        if len(keys) > 1:
            raise RobotModelError(f"robot.default_joint_pos: joint {joint!r} matches several keys {keys}")
        if keys:
            pos[i] = float(cfg.default_joint_pos[keys[0]])
            used.add(keys[0])
    unused = sorted(set(cfg.default_joint_pos) - used)
    if unused:
        raise RobotModelError(f"robot.default_joint_pos: keys {unused} match no joint of the model")
    return pos


def hinge_joint_names(model: mujoco.MjModel) -> list[str]:
    """Names of the model's hinge joints in model order."""
    import mujoco

    return [model.joint(j).name for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]


def _body_id(model: mujoco.MjModel, name: str, field_name: str) -> int:
    import mujoco

    body_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name)
    if body_id < 0:
        raise RobotModelError(f"robot.{field_name}: body {name!r} is not in the model")
    return body_id


def resolve_robot(cfg: RobotConfig, model: mujoco.MjModel) -> RobotInfo:
    """Per-joint gains, limits, default pose and body ids of `model` under `cfg`, in model joint order."""
    joint_names = hinge_joint_names(model)
    joint_ids = np.array([model.joint(n).id for n in joint_names], dtype=np.int64)
    armature, effort = joint_actuator_params(cfg, joint_names)
    kp, kd = pd_gains(armature, cfg)
    _check_actuators(model, joint_names, kp, kd)

    limits = model.jnt_range[joint_ids].copy()
    mid = limits.mean(axis=1, keepdims=True)
    half = 0.5 * (limits[:, 1:] - limits[:, :1]) * cfg.soft_joint_limit_factor
    soft = np.concatenate([mid - half, mid + half], axis=1)

    return RobotInfo(
        joint_names=tuple(joint_names),
        body_names=tuple(model.body(b).name for b in range(1, model.nbody)),
        kp=kp,
        kd=kd,
        armature=armature,
        effort_limit=effort,
        action_scale=cfg.action_scale_factor * effort / kp,
        default_joint_pos=default_joint_positions(cfg, joint_names),
        joint_limits=limits,
        soft_joint_limits=soft,
        qpos_adr=model.jnt_qposadr[joint_ids].astype(np.int64),
        dof_adr=model.jnt_dofadr[joint_ids].astype(np.int64),
        anchor_body_id=_body_id(model, cfg.anchor_body, "anchor_body"),
        tracked_body_ids=np.array([_body_id(model, n, "tracked_bodies") for n in cfg.tracked_bodies], np.int64),
        end_effector_body_ids=np.array(
            [_body_id(model, n, "end_effector_bodies") for n in cfg.end_effector_bodies], np.int64),
        default_root_height_m=float(cfg.default_root_height_m),
    )


def _check_actuators(model: mujoco.MjModel, joint_names: list[str], kp: np.ndarray, kd: np.ndarray) -> None:
    # The simulator writes ctrl in joint order, so actuator i must drive joint i with the configured gains;
    # a mismatch means the model was built from a different config than the one being resolved.
    if model.nu != len(joint_names):
        raise RobotModelError(f"model has {model.nu} actuators for {len(joint_names)} joints; "
                              "build it with bmimic.robot.load_mjmodel")
    for i, joint in enumerate(joint_names):
        target = model.joint(model.actuator_trnid[i, 0]).name
        if target != joint:
            raise RobotModelError(f"actuator {i} drives {target!r}, expected {joint!r} (joint order)")
        if not (np.isclose(model.actuator_gainprm[i, 0], kp[i]) and np.isclose(-model.actuator_biasprm[i, 2], kd[i])):
            raise RobotModelError(
                f"actuator {model.actuator(i).name!r} has kp={model.actuator_gainprm[i, 0]:.4g}, "
                f"kd={-model.actuator_biasprm[i, 2]:.4g} but the config gives kp={kp[i]:.4g}, kd={kd[i]:.4g}; "
                "build the model with load_mjmodel(cfg=...) from the same config")
