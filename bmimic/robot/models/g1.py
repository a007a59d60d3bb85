"""The 29-DoF Unitree G1 (rev 1.0) as MjSpec code (the generic MjSpec steps are in `bmimic.robot.spec`;
its numbers, from motor classes to tracked bodies, in conf/robot/g1.yaml).

The kinematic and inertial figures below (body offsets, joint axes and ranges, masses, inertias) are
those of the public Unitree G1 descriptions (MuJoCo Menagerie `unitree_g1`, mjlab); the collision
geometry is primitives only, after mjlab's capsule model, with four contact spheres per sole.
Everything else (contact filtering, visuals, actuators, options) is built here.

Conventions: each actuator is named exactly like the joint it drives (e.g. `left_knee_joint`) and
actuator i drives joint i, in MuJoCo's depth-first joint order. A keyframe "default" holds the
BeyondMimic default pose. There are no sensors: they cost simulation time and nothing reads them.
"""

from __future__ import annotations

from typing import NamedTuple

import mujoco
import numpy as np

from bmimic.robot.config import RobotConfig
from bmimic.robot.spec import (
    FLOOR_GROUP,
    RobotModel,
    SimOptions,
    add_tracking_camera,
    add_world,
    configure_robot_spec,
)


class _Link(NamedTuple):
    name: str
    parent: str
    pos: tuple  # body frame in the parent frame
    quat: tuple  # w, x, y, z
    joint: str | None  # hinge at the body origin; None: the floating base
    axis: str | None
    range: tuple | None  # rad
    ipos: tuple  # centre of mass
    iquat: tuple  # principal axes
    mass: float  # kg
    inertia: tuple  # principal moments, kg m^2


# Depth-first, so body ids and joint order follow this table.
_LINKS = (
    _Link("pelvis", "world", (0.0, 0.0, 0.793), (1.0, 0.0, 0.0, 0.0),
          None, None, None,
          (0.0, 0.0, -0.07605), (1.0, 0.0, -0.000399148, 0.0), 3.813, (0.010549, 0.0093089, 0.0079184)),
    _Link("left_hip_pitch_link", "pelvis", (0.0, 0.064452, -0.1027), (1.0, 0.0, 0.0, 0.0),
          "left_hip_pitch_joint", "y", (-2.5307, 2.8798),
          (0.002741, 0.047791, -0.02606), (0.954862, 0.293964, 0.0302556, 0.030122), 1.35, (0.00181517, 0.00153422, 0.00116212)),
    _Link("left_hip_roll_link", "left_hip_pitch_link", (0.0, 0.052, -0.030465), (0.996179, 0.0, -0.0873386, 0.0),
          "left_hip_roll_joint", "x", (-0.5236, 2.9671),
          (0.029812, -0.001045, -0.087934), (0.977808, -1.97119e-05, 0.205576, -0.0403793), 1.52, (0.00254986, 0.00241169, 0.00148755)),
    _Link("left_hip_yaw_link", "left_hip_roll_link", (0.025001, 0.0, -0.12412), (1.0, 0.0, 0.0, 0.0),
          "left_hip_yaw_joint", "z", (-2.7576, 2.7576),
          (-0.057709, -0.010981, -0.15078), (0.600598, 0.15832, 0.223482, 0.751181), 1.702, (0.00776166, 0.00717575, 0.00160139)),
    _Link("left_knee_link", "left_hip_yaw_link", (-0.078273, 0.0021489, -0.17734), (0.996179, 0.0, 0.0873386, 0.0),
          "left_knee_joint", "y", (-0.087267, 2.8798),
          (0.005457, 0.003964, -0.12074), (0.923418, -0.0327699, 0.0158246, 0.382067), 1.932, (0.0113804, 0.0112778, 0.00146458)),
    _Link("left_ankle_pitch_link", "left_knee_link", (0.0, -9.4445e-05, -0.30001), (1.0, 0.0, 0.0, 0.0),
          "left_ankle_pitch_joint", "y", (-0.87267, 0.5236),
          (-0.007269, 0.0, 0.011137), (0.603053, 0.369225, 0.369225, 0.603053), 0.074, (1.89e-05, 1.40805e-05, 6.9195e-06)),
    _Link("left_ankle_roll_link", "left_ankle_pitch_link", (0.0, 0.0, -0.017558), (1.0, 0.0, 0.0, 0.0),
          "left_ankle_roll_joint", "x", (-0.2618, 0.2618),
          (0.026505, 0.0, -0.016425), (-0.000481092, 0.728482, -0.000618967, 0.685065), 0.608, (0.00167218, 0.0016161, 0.000217621)),
    _Link("right_hip_pitch_link", "pelvis", (0.0, -0.064452, -0.1027), (1.0, 0.0, 0.0, 0.0),
          "right_hip_pitch_joint", "y", (-2.5307, 2.8798),
          (0.002741, -0.047791, -0.02606), (0.954862, -0.293964, 0.0302556, -0.030122), 1.35, (0.00181517, 0.00153422, 0.00116212)),
    _Link("right_hip_roll_link", "right_hip_pitch_link", (0.0, -0.052, -0.030465), (0.996179, 0.0, -0.0873386, 0.0),
          "right_hip_roll_joint", "x", (-2.9671, 0.5236),
          (0.029812, 0.001045, -0.087934), (0.977808, 1.97119e-05, 0.205576, 0.0403793), 1.52, (0.00254986, 0.00241169, 0.00148755)),
    _Link("right_hip_yaw_link", "right_hip_roll_link", (0.025001, 0.0, -0.12412), (1.0, 0.0, 0.0, 0.0),
          "right_hip_yaw_joint", "z", (-2.7576, 2.7576),
          (-0.057709, 0.010981, -0.15078), (0.751181, 0.223482, 0.15832, 0.600598), 1.702, (0.00776166, 0.00717575, 0.00160139)),
    _Link("right_knee_link", "right_hip_yaw_link", (-0.078273, -0.0021489, -0.17734), (0.996179, 0.0, 0.0873386, 0.0),
          "right_knee_joint", "y", (-0.087267, 2.8798),
          (0.005457, -0.003964, -0.12074), (0.923439, 0.0345276, 0.0116333, -0.382012), 1.932, (0.011374, 0.0112843, 0.00146452)),
    _Link("right_ankle_pitch_link", "right_knee_link", (0.0, 9.4445e-05, -0.30001), (1.0, 0.0, 0.0, 0.0),
          "right_ankle_pitch_joint", "y", (-0.87267, 0.5236),
          (-0.007269, 0.0, 0.011137), (0.603053, 0.369225, 0.369225, 0.603053), 0.074, (1.89e-05, 1.40805e-05, 6.9195e-06)),
    _Link("right_ankle_roll_link", "right_ankle_pitch_link", (0.0, 0.0, -0.017558), (1.0, 0.0, 0.0, 0.0),
          "right_ankle_roll_joint", "x", (-0.2618, 0.2618),
          (0.026505, 0.0, -0.016425), (0.000481092, 0.728482, 0.000618967, 0.685065), 0.608, (0.00167218, 0.0016161, 0.000217621)),
    _Link("waist_yaw_link", "pelvis", (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
          "waist_yaw_joint", "z", (-2.618, 2.618),
          (0.003494, 0.000233, 0.018034), (0.289697, 0.591001, -0.337795, 0.672821), 0.214, (0.000163531, 0.000107714, 0.000102205)),
    _Link("waist_roll_link", "waist_yaw_link", (-0.0039635, 0.0, 0.044), (1.0, 0.0, 0.0, 0.0),
          "waist_roll_joint", "x", (-0.52, 0.52),
          (0.0, 2.3e-05, 0.0), (0.5, 0.5, -0.5, 0.5), 0.086, (8.245e-06, 7.079e-06, 6.339e-06)),
    _Link("torso_link", "waist_roll_link", (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
          "waist_pitch_joint", "y", (-0.52, 0.52),
          (0.00203158, 0.000339683, 0.184568), (0.999803, -6.03319e-05, 0.0198256, 0.00131986), 7.818, (0.121847, 0.109825, 0.0273735)),
    _Link("left_shoulder_pitch_link", "torso_link", (0.0039563, 0.10022, 0.24778), (0.990264, 0.139201, 1.38722e-05, -9.86868e-05),
          "left_shoulder_pitch_joint", "y", (-3.0892, 2.6704),
          (0.0, 0.035892, -0.011628), (0.654152, 0.0130458, -0.326267, 0.68225), 0.718, (0.000465864, 0.000432842, 0.000406394)),
    _Link("left_shoulder_roll_link", "left_shoulder_pitch_link", (0.0, 0.038, -0.013831), (0.990268, -0.139172, 0.0, 0.0),
          "left_shoulder_roll_joint", "x", (-1.5882, 2.2515),
          (-0.000227, 0.00727, -0.063243), (0.701256, -0.0196223, -0.00710317, 0.712604), 0.643, (0.000691311, 0.000618011, 0.000388977)),
    _Link("left_shoulder_yaw_link", "left_shoulder_roll_link", (0.0, 0.00624, -0.1032), (1.0, 0.0, 0.0, 0.0),
          "left_shoulder_yaw_joint", "z", (-2.618, 2.618),
          (0.010773, -0.002949, -0.072009), (0.716879, -0.0964829, -0.0679942, 0.687134), 0.734, (0.00106187, 0.00103217, 0.000400661)),
    _Link("left_elbow_link", "left_shoulder_yaw_link", (0.015783, 0.0, -0.080518), (1.0, 0.0, 0.0, 0.0),
          "left_elbow_joint", "y", (-1.0472, 2.0944),
          (0.064956, 0.004454, -0.010062), (0.541765, 0.636132, 0.388821, 0.388129), 0.6, (0.000443035, 0.000421612, 0.000259353)),
    _Link("left_wrist_roll_link", "left_elbow_link", (0.1, 0.00188791, -0.01), (1.0, 0.0, 0.0, 0.0),
          "left_wrist_roll_joint", "x", (-1.97222, 1.97222),
          (0.0171394, 0.000537591, 4.8864e-07), (0.575338, 0.411667, -0.574906, 0.411094), 0.085445, (5.48211e-05, 4.96646e-05, 3.57798e-05)),
    _Link("left_wrist_pitch_link", "left_wrist_roll_link", (0.038, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
          "left_wrist_pitch_joint", "y", (-1.61443, 1.61443),
          (0.0229999, -0.00111685, -0.00111658), (0.249998, 0.661363, 0.293036, 0.643608), 0.48405, (0.000430353, 0.000429873, 0.000164648)),
    _Link("left_wrist_yaw_link", "left_wrist_pitch_link", (0.046, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
          "left_wrist_yaw_joint", "z", (-1.61443, 1.61443),
          (0.0708244, 0.000191745, 0.00161742), (0.510571, 0.526295, 0.468078, 0.493188), 0.254576, (0.000646113, 0.000559993, 0.000147566)),
    _Link("right_shoulder_pitch_link", "torso_link", (0.0039563, -0.10021, 0.24778), (0.990264, -0.139201, 1.38722e-05, 9.86868e-05),
          "right_shoulder_pitch_joint", "y", (-3.0892, 2.6704),
          (0.0, -0.035892, -0.011628), (0.68225, -0.326267, 0.0130458, 0.654152), 0.718, (0.000465864, 0.000432842, 0.000406394)),
    _Link("right_shoulder_roll_link", "right_shoulder_pitch_link", (0.0, -0.038, -0.013831), (0.990268, 0.139172, 0.0, 0.0),
          "right_shoulder_roll_joint", "x", (-2.2515, 1.5882),
          (-0.000227, -0.00727, -0.063243), (0.712604, -0.00710317, -0.0196223, 0.701256), 0.643, (0.000691311, 0.000618011, 0.000388977)),
    _Link("right_shoulder_yaw_link", "right_shoulder_roll_link", (0.0, -0.00624, -0.1032), (1.0, 0.0, 0.0, 0.0),
          "right_shoulder_yaw_joint", "z", (-2.618, 2.618),
          (0.010773, 0.002949, -0.072009), (0.687134, -0.0679942, -0.0964829, 0.716879), 0.734, (0.00106187, 0.00103217, 0.000400661)),
    _Link("right_elbow_link", "right_shoulder_yaw_link", (0.015783, 0.0, -0.080518), (1.0, 0.0, 0.0, 0.0),
          "right_elbow_joint", "y", (-1.0472, 2.0944),
          (0.064956, -0.004454, -0.010062), (0.388129, 0.388821, 0.636132, 0.541765), 0.6, (0.000443035, 0.000421612, 0.000259353)),
    _Link("right_wrist_roll_link", "right_elbow_link", (0.1, -0.00188791, -0.01), (1.0, 0.0, 0.0, 0.0),
          "right_wrist_roll_joint", "x", (-1.97222, 1.97222),
          (0.0171394, -0.000537591, 4.8864e-07), (0.411667, 0.575338, -0.411094, 0.574906), 0.085445, (5.48211e-05, 4.96646e-05, 3.57798e-05)),
    _Link("right_wrist_pitch_link", "right_wrist_roll_link", (0.038, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
          "right_wrist_pitch_joint", "y", (-1.61443, 1.61443),
          (0.0229999, 0.00111685, -0.00111658), (0.643608, 0.293036, 0.661363, 0.249998), 0.48405, (0.000430353, 0.000429873, 0.000164648)),
    _Link("right_wrist_yaw_link", "right_wrist_pitch_link", (0.046, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
          "right_wrist_yaw_joint", "z", (-1.61443, 1.61443),
          (0.0708244, -0.000191745, 0.00161742), (0.493188, 0.468078, 0.526295, 0.510571), 0.254576, (0.000646113, 0.000559993, 0.000147566)),
)

G1_BODY_NAMES: tuple[str, ...] = tuple(link.name for link in _LINKS)
"""The 30 robot bodies in MuJoCo body order (pelvis first, world body excluded)."""
G1_JOINT_NAMES: tuple[str, ...] = tuple(link.joint for link in _LINKS if link.joint is not None)
"""The 29 hinge joints in MuJoCo depth-first order (= LAFAN1 CSV order)."""

_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}

# Collision primitives of the left side and the trunk; the right side mirrors the left in y.
# (name, body, type, radius, capsule fromto or sphere pos), body-frame metres.
_COLLISION_LEFT = (
    ("left_hip_collision", "left_hip_roll_link", "capsule", 0.06, (0.02, 0.0, 0.0, 0.02, 0.0, -0.08)),
    ("left_thigh_collision", "left_hip_yaw_link", "capsule", 0.055, (0.0, 0.0, -0.03, -0.06, 0.0, -0.17)),
    ("left_shin_collision", "left_knee_link", "capsule", 0.045, (0.01, 0.0, 0.0, 0.01, 0.0, -0.15)),
    ("left_linkage_brace_collision", "left_knee_link", "capsule", 0.03, (0.01, 0.0, -0.2, 0.01, 0.0, -0.28)),
    ("left_shoulder_yaw_collision", "left_shoulder_yaw_link", "capsule", 0.035, (0.0, 0.0, -0.08, 0.0, 0.0, 0.05)),
    ("left_elbow_collision", "left_elbow_link", "capsule", 0.035, (-0.01, 0.0, -0.01, 0.08, 0.0, -0.01)),
    ("left_wrist_collision", "left_wrist_pitch_link", "capsule", 0.035, (-0.01, 0.0, 0.0, 0.06, 0.0, 0.0)),
    ("left_hand_collision", "left_wrist_yaw_link", "capsule", 0.035, (0.07, 0.0, 0.0, 0.15, -0.02, 0.0)),
)
_COLLISION_TRUNK = (
    ("pelvis_collision", "pelvis", "sphere", 0.07, (0.0, 0.0, -0.08)),
    ("torso_collision", "torso_link", "capsule", 0.09, (0.01, 0.0, 0.08, 0.01, 0.0, 0.2)),
    ("head_collision", "torso_link", "sphere", 0.06, (0.0, 0.0, 0.43)),
)
# Sole contact spheres on each ankle_roll_link: heel and toe, inner and outer edge (x, y at z = -0.025).
# Four points span the sole like the mjlab capsule set but give at most four contacts per foot.
_FOOT_RADIUS = 0.01
_FOOT_Z = -0.025
_FOOT_POINTS_LEFT = ((-0.045, 0.025), (-0.045, -0.025), (0.125, 0.03), (0.125, -0.03))
_SOLE_BOX = ((0.04, 0.0, -0.025), (0.09, 0.033, 0.01))  # visual only: centre, half sizes

# Self-collision groups (contype bit of each group, and the groups it collides with). The floor collides
# with everything; the legs with each other; the arms with the trunk and each other. Arm-leg pairs are
# left out: the LAFAN1 G1 retargets swing the hands through the (coarse) hip and thigh capsules in about
# a third of walking frames (median depth 14 mm), so they would only push the arms off the reference and
# add contacts. Within a limb and trunk-leg pairs either always touch or cannot meet.
_FLOOR, _TRUNK, _LEFT_LEG, _RIGHT_LEG, _LEFT_ARM, _RIGHT_ARM = FLOOR_GROUP, 2, 4, 8, 16, 32
_COLLIDES_WITH = {
    _TRUNK: _FLOOR | _LEFT_ARM | _RIGHT_ARM,
    _LEFT_LEG: _FLOOR | _RIGHT_LEG,
    _RIGHT_LEG: _FLOOR | _LEFT_LEG,
    _LEFT_ARM: _FLOOR | _TRUNK | _RIGHT_ARM,
    _RIGHT_ARM: _FLOOR | _TRUNK | _LEFT_ARM,
}


G1_SIM_OPTIONS = SimOptions()
"""MuJoCo solver settings of BeyondMimic on MuJoCo (mjlab); decimation lives in the sim config."""

_ROBOT_RGBA = (0.7, 0.7, 0.72, 1.0)
_JOINT_RGBA = (0.25, 0.25, 0.28, 1.0)
_COLLISION_RGBA = (0.2, 0.6, 0.2, 0.3)


def _limb_group(body: str) -> int:
    side = "left" if body.startswith("left_") else "right" if body.startswith("right_") else None
    if side is None:
        return _TRUNK
    arm = any(part in body for part in ("shoulder", "elbow", "wrist"))
    return {("left", False): _LEFT_LEG, ("right", False): _RIGHT_LEG,
            ("left", True): _LEFT_ARM, ("right", True): _RIGHT_ARM}[(side, arm)]


def _mirror(name: str, body: str, kind: str, radius: float, at: tuple) -> tuple:
    flipped = tuple(-v if i % 3 == 1 else v for i, v in enumerate(at))
    return name.replace("left_", "right_"), body.replace("left_", "right_"), kind, radius, flipped


def _collision_table() -> tuple:
    return _COLLISION_TRUNK + _COLLISION_LEFT + tuple(_mirror(*row) for row in _COLLISION_LEFT)


def _add_collision_geoms(bodies: dict, foot_friction: float) -> None:
    for name, body, kind, radius, at in _collision_table():
        group = _limb_group(body)
        common = dict(name=name, size=[radius, 0.0, 0.0], group=3, rgba=_COLLISION_RGBA, condim=1,
                      contype=group, conaffinity=_COLLIDES_WITH[group])
        if kind == "capsule":
            bodies[body].add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=at, **common)
        else:
            bodies[body].add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=at, **common)
    for side, sign in (("left", 1.0), ("right", -1.0)):
        group = _LEFT_LEG if side == "left" else _RIGHT_LEG
        for i, (x, y) in enumerate(_FOOT_POINTS_LEFT):
            # priority 1: the foot's friction and condim govern its contacts with the floor.
            bodies[f"{side}_ankle_roll_link"].add_geom(
                name=f"{side}_foot{i + 1}_collision", type=mujoco.mjtGeom.mjGEOM_SPHERE,
                size=[_FOOT_RADIUS, 0.0, 0.0], pos=[x, sign * y, _FOOT_Z], group=3, rgba=_COLLISION_RGBA,
                condim=3, priority=1, friction=[foot_friction, 0.005, 0.0001],
                contype=group, conaffinity=_COLLIDES_WITH[group])


def _add_visual_geoms(bodies: dict) -> None:
    """Group-1 primitives that never collide: a limb capsule per link plus twins of the collision shapes."""
    visual = dict(group=1, contype=0, conaffinity=0)
    for link in _LINKS:
        if link.parent != "world" and np.linalg.norm(link.pos) > 0.02:
            bodies[link.parent].add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.025, 0.0, 0.0],
                                         fromto=[0.0, 0.0, 0.0, *link.pos], rgba=_JOINT_RGBA, **visual)
    for _, body, kind, radius, at in _collision_table():
        if kind == "capsule":
            bodies[body].add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[radius, 0.0, 0.0], fromto=at,
                                  rgba=_ROBOT_RGBA, **visual)
        else:
            bodies[body].add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[radius, 0.0, 0.0], pos=at,
                                  rgba=_ROBOT_RGBA, **visual)
    bodies["torso_link"].add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, size=[0.03, 0.0, 0.0],  # neck
                                  fromto=[0.005, 0.0, 0.28, 0.0, 0.0, 0.39], rgba=_JOINT_RGBA, **visual)
    centre, half = _SOLE_BOX
    for side in ("left", "right"):
        bodies[f"{side}_ankle_roll_link"].add_geom(type=mujoco.mjtGeom.mjGEOM_BOX, size=half, pos=centre,
                                                   rgba=_JOINT_RGBA, **visual)


def build_g1_spec(cfg: RobotConfig) -> mujoco.MjSpec:
    """The G1 on a floor as an MjSpec (not compiled), configured by `cfg` (conf/robot/g1.yaml)."""
    spec = mujoco.MjSpec()
    spec.modelname = "g1_29dof_rev_1_0"
    spec.compiler.degree = False
    # Masses and inertias come from the table only; the primitives must not add any.
    spec.compiler.inertiafromgeom = mujoco.mjtInertiaFromGeom.mjINERTIAFROMGEOM_FALSE
    add_world(spec)

    bodies = {"world": spec.worldbody}
    for link in _LINKS:
        body = bodies[link.parent].add_body(
            name=link.name, pos=link.pos, quat=link.quat, ipos=link.ipos, iquat=link.iquat,
            mass=link.mass, inertia=link.inertia, explicitinertial=True)
        if link.joint is None:
            body.add_freejoint(name="floating_base_joint")
        else:
            body.add_joint(name=link.joint, type=mujoco.mjtJoint.mjJNT_HINGE, axis=_AXES[str(link.axis)],
                           range=link.range, limited=mujoco.mjtLimited.mjLIMITED_TRUE)
        bodies[link.name] = body

    _add_collision_geoms(bodies, cfg.foot_friction)
    _add_visual_geoms(bodies)
    add_tracking_camera(spec, bodies["pelvis"])
    spec.visual.global_.offwidth = 1280
    spec.visual.global_.offheight = 720
    configure_robot_spec(spec, cfg, G1_JOINT_NAMES, ROBOT.what, G1_SIM_OPTIONS)
    return spec


ROBOT = RobotModel(joint_names=G1_JOINT_NAMES, sim_options=G1_SIM_OPTIONS, build=build_g1_spec,
                   what="the G1 (the 29 hinge joints of bmimic.robot.G1_JOINT_NAMES)")
