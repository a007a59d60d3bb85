"""The MjSpec steps every robot model of bmimic goes through (the built-in G1 and a user's MJCF, and
sim2sim's native model): the floor and light, the tracking camera, PD actuators named after their
joints, the solver options, the default keyframe; reading, checking and compiling an MJCF."""

from __future__ import annotations

from pathlib import Path
from typing import Callable, NamedTuple, Sequence

import mujoco
import numpy as np

from bmimic.robot.config import (
    RobotConfig,
    RobotModelError,
    default_joint_positions,
    joint_actuator_params,
    pd_gains,
)

FLOOR_GROUP = 1
"""Contype bit of the floor (it collides with every robot collision group)."""


class SimOptions(NamedTuple):
    """MuJoCo solver settings of BeyondMimic on MuJoCo (mjlab); decimation lives in the sim config."""

    timestep_s: float = 0.005
    integrator: int = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    solver: int = mujoco.mjtSolver.mjSOL_NEWTON
    iterations: int = 10
    ls_iterations: int = 20
    cone: int = mujoco.mjtCone.mjCONE_PYRAMIDAL



class RobotModel(NamedTuple):
    """A built-in robot's body, as its module in bmimic.robot.models declares it (`ROBOT`)."""

    joint_names: tuple[str, ...]
    """Its hinge joints in MuJoCo's depth-first order; actuator i drives joint i. A user's MJCF of this
    robot must have exactly these."""
    sim_options: SimOptions
    """MuJoCo solver settings."""
    build: Callable[[RobotConfig], mujoco.MjSpec]
    """The robot on a floor as an MjSpec (not compiled), configured by its RobotConfig."""
    what: str
    """How errors name the robot's joint set."""


def _look_at_xyaxes(eye: np.ndarray, target: np.ndarray) -> list[float]:
    # Camera x points right and y up; it looks along its -z axis.
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, (0.0, 0.0, 1.0))
    right /= np.linalg.norm(right)
    return [*right, *np.cross(right, forward)]


def add_world(spec: mujoco.MjSpec) -> None:
    """Checkered floor plane and a light, unless the spec already has them."""
    world = spec.worldbody
    if not any(g.type == mujoco.mjtGeom.mjGEOM_PLANE for g in world.geoms):
        spec.add_texture(name="bmimic_grid", type=mujoco.mjtTexture.mjTEXTURE_2D,
                         builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER, width=512, height=512,
                         rgb1=[0.2, 0.3, 0.4], rgb2=[0.1, 0.2, 0.3], mark=mujoco.mjtMark.mjMARK_EDGE,
                         markrgb=[0.8, 0.8, 0.8])
        material = spec.add_material(name="bmimic_grid", texrepeat=[1.0, 1.0], texuniform=True,
                                     reflectance=0.2)
        material.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = "bmimic_grid"
        # condim 3 on the floor: non-foot geoms (condim 1) still get friction against the ground.
        world.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0.0, 0.0, 0.05],
                       material="bmimic_grid", contype=FLOOR_GROUP, conaffinity=FLOOR_GROUP, condim=3)
    if not any(t.type == mujoco.mjtTexture.mjTEXTURE_SKYBOX for t in spec.textures):
        spec.add_texture(name="bmimic_sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                         builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT, width=512, height=3072,
                         rgb1=[0.3, 0.5, 0.7], rgb2=[0.0, 0.0, 0.0])
    if not spec.lights:
        world.add_light(name="sun", type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, pos=[0.0, 0.0, 4.0],
                        dir=[0.0, 0.0, -1.0], diffuse=[0.7, 0.7, 0.7], castshadow=False)


def add_tracking_camera(spec: mujoco.MjSpec, root: mujoco.MjsBody) -> None:
    """A camera named `tracking` on `root` that follows the robot (videos), unless the spec has one."""
    if any(c.name == "tracking" for c in spec.cameras):
        return
    eye = np.array([1.4, -1.9, 0.35])
    camera = root.add_camera(name="tracking", mode=mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM, pos=eye, fovy=45.0)
    camera.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
    camera.alt.xyaxes = _look_at_xyaxes(eye, np.array([0.0, 0.0, -0.15]))


def configure_robot_spec(spec: mujoco.MjSpec, cfg: RobotConfig, joint_names: Sequence[str], what: str,
                         options: SimOptions) -> None:
    """Give a robot spec the project's interface: PD actuators, armature, options, floor, camera,
    keyframe. Its hinge joints must be exactly `joint_names` (`what` names them in the error).

    Existing actuators, sensors and keyframes are replaced; joint damping and friction loss are zeroed
    because the actuators supply all the joint-space damping. Geoms are left as they are: a user file
    keeps its own collision and friction settings (`cfg.foot_friction` applies to the built-in G1).
    """
    joint_names = checked_joint_names(spec, joint_names, what)
    joints = {j.name: j for j in spec.joints}
    armature, effort = joint_actuator_params(cfg, joint_names)
    kp, kd = pd_gains(armature, cfg)

    for element in [*spec.actuators, *spec.sensors, *spec.keys]:
        spec.delete(element)
    spec.nkey = 0  # MJCF <size nkey> would otherwise keep empty keyframes
    for i, name in enumerate(joint_names):
        joint = joints[name]
        joint.armature = float(armature[i])
        joint.damping = [0.0, 0.0, 0.0]  # linear and polynomial terms
        joint.frictionloss = 0.0
        add_pd_actuator(spec, name, kp[i], kd[i], effort[i])

    spec.option.timestep = options.timestep_s
    spec.option.integrator = options.integrator
    spec.option.solver = options.solver
    spec.option.iterations = options.iterations
    spec.option.ls_iterations = options.ls_iterations
    spec.option.cone = options.cone

    add_world(spec)
    add_tracking_camera(spec, root_body(spec))
    _add_default_keyframe(spec, cfg, joint_names)


def add_pd_actuator(spec: mujoco.MjSpec, joint: str, kp: float, kd: float, effort_limit_nm: float) -> None:
    """A position-style PD actuator on `joint`, named after it (mjlab's G1 actuator model):
    force = clamp(kp (ctrl - q) - kd qdot, +-effort_limit_nm), with the kd term in the bias, so the
    implicit integrators treat the damping implicitly."""
    spec.add_actuator(
        name=joint, target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT,
        gaintype=mujoco.mjtGain.mjGAIN_FIXED, gainprm=[float(kp)] + [0.0] * 9,
        biastype=mujoco.mjtBias.mjBIAS_AFFINE, biasprm=[0.0, -float(kp), -float(kd)] + [0.0] * 7,
        ctrllimited=mujoco.mjtLimited.mjLIMITED_FALSE,
        forcelimited=mujoco.mjtLimited.mjLIMITED_TRUE, forcerange=[-float(effort_limit_nm), float(effort_limit_nm)])


def root_body(spec: mujoco.MjSpec) -> mujoco.MjsBody:
    """The body of the spec's (first) free joint: the floating base."""
    free = [j for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_FREE]
    return free[0].parent


def checked_joint_names(spec: mujoco.MjSpec, expected: Sequence[str], what: str) -> list[str]:
    """Hinge joint names in spec order, after checking they are exactly `expected` (any order) and there
    is one free joint."""
    hinges = [j.name for j in spec.joints if j.type == mujoco.mjtJoint.mjJNT_HINGE]
    others = [j.name or "<unnamed>" for j in spec.joints
              if j.type not in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_FREE)]
    missing = [n for n in expected if n not in hinges]
    extra = [n for n in hinges if n not in expected] + others
    if missing or extra or len(hinges) != len(expected):
        raise RobotModelError(f"model joints do not match {what}: missing {missing}, extra {extra}")
    n_free = sum(j.type == mujoco.mjtJoint.mjJNT_FREE for j in spec.joints)
    if n_free != 1:
        raise RobotModelError(f"model needs exactly one free joint (the floating base), has {n_free}")
    return hinges


def _add_default_keyframe(spec: mujoco.MjSpec, cfg: RobotConfig, joint_names: list[str]) -> None:
    # Compile once to learn the qpos layout, so a user model with any body order gets a valid key.
    model = compile_spec(spec, "robot model")
    qpos = model.qpos0.copy()
    free = int(np.flatnonzero(model.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
    adr = model.jnt_qposadr[free]
    qpos[adr:adr + 7] = [0.0, 0.0, cfg.default_root_height_m, 1.0, 0.0, 0.0, 0.0]
    default = default_joint_positions(cfg, joint_names)
    for name, value in zip(joint_names, default, strict=True):
        qpos[model.jnt_qposadr[model.joint(name).id]] = value
    spec.add_key(name="default", qpos=qpos, ctrl=default)


def compile_spec(spec: mujoco.MjSpec, source: str) -> mujoco.MjModel:
    try:
        return spec.compile()
    except ValueError as exc:
        raise RobotModelError(f"{source}: MuJoCo could not compile it: {exc}") from None


def missing_mesh_files(spec: mujoco.MjSpec, mjcf: Path) -> list[str]:
    """Mesh files the spec (read from `mjcf`) references that are not on disk."""
    mesh_dir = mjcf.parent / (spec.meshdir or "")
    missing = []
    for mesh in spec.meshes:
        if mesh.file and not (mesh_dir / mesh.file).is_file():
            missing.append(str(mesh_dir / mesh.file))
    return missing


def parse_mjcf(path: Path, key: str) -> mujoco.MjSpec:
    """The MJCF at `path` as an MjSpec (not compiled); errors name the setting `key` it came from."""
    if not path.is_file():
        raise RobotModelError(f"{key}: {path} does not exist")
    try:
        return mujoco.MjSpec.from_file(str(path))
    except ValueError as exc:
        raise RobotModelError(f"{key}: cannot parse {path}: {exc}") from None


__all__ = ["FLOOR_GROUP", "SimOptions", "add_pd_actuator", "add_tracking_camera", "add_world", "checked_joint_names",
           "compile_spec", "configure_robot_spec", "missing_mesh_files", "parse_mjcf", "root_body"]
