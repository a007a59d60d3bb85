"""The G1 model: structure, figures against the public reference model, PD design, contacts, user MJCF."""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from omegaconf import OmegaConf

from bmimic.robot import (
    G1_BODY_NAMES,
    G1_JOINT_NAMES,
    ActuatorClassConfig,
    RobotConfig,
    RobotModelError,
    build_spec,
    load_mjmodel,
    resolve_robot,
    robot_config,
    robot_names,
)
from tests.conftest import REPO

MENAGERIE_G1 = Path(os.environ.get("BMIMIC_MENAGERIE_G1") or
                    REPO.parent / "shared" / "reference" / "unitree_g1_menagerie" / "g1.xml")
"""MuJoCo Menagerie's G1 (not shipped): $BMIMIC_MENAGERIE_G1, else the development machine's copy."""

# notes/beyondmimic.md section 3.7: one joint per motor class -> (Kp, Kd, effort, action scale).
PD_TABLE = {
    "left_shoulder_pitch_joint": (14.2506, 0.9072, 25.0, 0.4386),  # 5020
    "left_hip_pitch_joint": (40.1792, 2.5579, 88.0, 0.5475),  # 7520_14
    "right_knee_joint": (99.0984, 6.3088, 139.0, 0.3507),  # 7520_22
    "left_wrist_yaw_joint": (16.7783, 1.0681, 5.0, 0.0745),  # 4010
    "waist_pitch_joint": (28.5012, 1.8144, 50.0, 0.4386),  # 2x5020
}


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return load_mjmodel()


@pytest.fixture(scope="module")
def info(model):
    return resolve_robot(robot_config(), model)


def _reference_model() -> mujoco.MjModel:
    if not MENAGERIE_G1.is_file():
        pytest.skip("MuJoCo Menagerie's G1 (g1.xml, not shipped) is absent: set BMIMIC_MENAGERIE_G1 to run this")
    spec = mujoco.MjSpec.from_file(str(MENAGERIE_G1))
    for geom in [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]:
        spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    return spec.compile()


def test_joints_are_the_29_g1_hinges_in_depth_first_order(model):
    hinges = [model.joint(j).name for j in range(model.njnt) if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE]
    assert hinges == list(G1_JOINT_NAMES)
    assert len(G1_JOINT_NAMES) == 29 and all(n.endswith("_joint") for n in G1_JOINT_NAMES)
    assert model.jnt_type[0] == mujoco.mjtJoint.mjJNT_FREE and model.nq == 36 and model.nv == 35
    assert G1_JOINT_NAMES[:6] == ("left_hip_pitch_joint", "left_hip_roll_joint", "left_hip_yaw_joint",
                                  "left_knee_joint", "left_ankle_pitch_joint", "left_ankle_roll_joint")
    assert G1_JOINT_NAMES[12:15] == ("waist_yaw_joint", "waist_roll_joint", "waist_pitch_joint")


def test_body_names_and_mass(model):
    assert [model.body(b).name for b in range(1, model.nbody)] == list(G1_BODY_NAMES)
    assert len(G1_BODY_NAMES) == 30 and G1_BODY_NAMES[0] == "pelvis"
    assert model.body_subtreemass[model.body("pelvis").id] == pytest.approx(33.34, rel=0.01)


def test_actuators_are_pd_position_servos_with_beyondmimic_gains(model, info):
    assert model.nu == 29
    for i, name in enumerate(G1_JOINT_NAMES):
        assert model.actuator(i).name == name
        assert model.joint(model.actuator_trnid[i, 0]).name == name
    for joint, (kp, kd, effort, scale) in PD_TABLE.items():
        j = info.joint_names.index(joint)
        assert info.kp[j] == pytest.approx(kp, abs=1e-4)
        assert info.kd[j] == pytest.approx(kd, abs=1e-4)
        assert info.effort_limit[j] == effort
        assert info.action_scale[j] == pytest.approx(scale, abs=1e-4)
        assert model.actuator_gainprm[j, 0] == pytest.approx(kp, abs=1e-4)
        np.testing.assert_allclose(model.actuator_biasprm[j, :3], [0.0, -info.kp[j], -info.kd[j]])
        np.testing.assert_allclose(model.actuator_forcerange[j], [-effort, effort])
        assert model.dof_armature[info.dof_adr[j]] == pytest.approx(info.armature[j])
    assert model.actuator_gaintype.tolist() == [mujoco.mjtGain.mjGAIN_FIXED] * 29
    assert model.actuator_biastype.tolist() == [mujoco.mjtBias.mjBIAS_AFFINE] * 29
    assert model.actuator_forcelimited.all() and not model.actuator_ctrllimited.any()
    assert not model.dof_damping.any() and not model.dof_frictionloss.any()
    assert model.nsensor == 0


def test_options_keyframe_and_scene(model, info):
    assert model.opt.timestep == 0.005
    assert model.opt.integrator == mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    assert model.opt.solver == mujoco.mjtSolver.mjSOL_NEWTON
    assert (model.opt.iterations, model.opt.ls_iterations) == (10, 20)
    assert model.opt.cone == mujoco.mjtCone.mjCONE_PYRAMIDAL
    key = model.key("default").id
    np.testing.assert_allclose(model.key_qpos[key, :7], [0, 0, 0.76, 1, 0, 0, 0])
    np.testing.assert_allclose(model.key_qpos[key, info.qpos_adr], info.default_joint_pos)
    np.testing.assert_allclose(model.key_ctrl[key], info.default_joint_pos)
    expected = dict.fromkeys(G1_JOINT_NAMES, 0.0) | {
        "left_hip_pitch_joint": -0.312, "right_hip_pitch_joint": -0.312, "left_knee_joint": 0.669,
        "right_knee_joint": 0.669, "left_ankle_pitch_joint": -0.363, "right_ankle_pitch_joint": -0.363,
        "left_elbow_joint": 0.6, "right_elbow_joint": 0.6, "left_shoulder_pitch_joint": 0.2,
        "right_shoulder_pitch_joint": 0.2, "left_shoulder_roll_joint": 0.2, "right_shoulder_roll_joint": -0.2}
    np.testing.assert_allclose(info.default_joint_pos, [expected[n] for n in G1_JOINT_NAMES])
    camera = model.camera("tracking")
    assert model.cam_bodyid[camera.id] == model.body("pelvis").id
    assert model.cam_mode[camera.id] == mujoco.mjtCamLight.mjCAMLIGHT_TRACKCOM
    assert model.geom("floor").type == mujoco.mjtGeom.mjGEOM_PLANE and model.nlight >= 1


def test_geoms_are_primitives_with_mjlab_contact_settings(model):
    robot = model.geom_bodyid > 0
    assert not (model.geom_type == mujoco.mjtGeom.mjGEOM_MESH).any()
    colliding = robot & ((model.geom_contype != 0) | (model.geom_conaffinity != 0))
    feet = np.array(["_foot" in model.geom(g).name for g in range(model.ngeom)]) & colliding
    assert feet.sum() >= 4
    assert (model.geom_condim[feet] == 3).all() and (model.geom_priority[feet] == 1).all()
    np.testing.assert_allclose(model.geom_friction[feet, 0], 0.6)
    assert (model.geom_condim[colliding & ~feet] == 1).all()
    visual = robot & ~colliding
    assert (model.geom_group[visual] == 1).sum() > 20  # the renderer has something to draw
    assert model.body_mass.sum() == pytest.approx(model.body_subtreemass[1])  # geoms add no mass
    foot_friction = load_mjmodel(cfg=dataclasses.replace(robot_config(), foot_friction=0.9))
    np.testing.assert_allclose(foot_friction.geom_friction[feet, 0], 0.9)


def test_no_self_contact_at_the_default_pose(model):
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("default").id)
    mujoco.mj_forward(model, data)
    floor = model.geom("floor").id
    assert all(floor in (c.geom1, c.geom2) for c in data.contact[: data.ncon])


def test_forward_kinematics_match_the_reference_g1(model):
    reference = _reference_model()
    ours, theirs = mujoco.MjData(model), mujoco.MjData(reference)
    ref_qadr = np.array([reference.jnt_qposadr[reference.joint(n).id] for n in G1_JOINT_NAMES])
    our_qadr = np.array([model.jnt_qposadr[model.joint(n).id] for n in G1_JOINT_NAMES])
    ref_bodies = [reference.body(n).id for n in G1_BODY_NAMES]
    lo, hi = model.jnt_range[[model.joint(n).id for n in G1_JOINT_NAMES]].T
    np.testing.assert_allclose(reference.jnt_range[[reference.joint(n).id for n in G1_JOINT_NAMES]].T, (lo, hi))
    rng = np.random.default_rng(0)
    for _ in range(20):
        quat = rng.normal(size=4)
        root = np.concatenate([rng.uniform(-2, 2, 3), quat / np.linalg.norm(quat)])
        joints = rng.uniform(lo, hi)
        for data, qadr in ((ours, our_qadr), (theirs, ref_qadr)):
            data.qpos[:7] = root
            data.qpos[qadr] = joints
        mujoco.mj_kinematics(model, ours)
        mujoco.mj_kinematics(reference, theirs)
        np.testing.assert_allclose(ours.xpos[1:], theirs.xpos[ref_bodies], atol=1e-3)
        # Same orientation up to the quaternion sign.
        dots = np.abs(np.sum(ours.xquat[1:] * theirs.xquat[ref_bodies], axis=1))
        np.testing.assert_allclose(dots, 1.0, atol=1e-6)


def test_inertial_figures_match_the_reference_g1(model):
    reference = _reference_model()
    ids = [reference.body(n).id for n in G1_BODY_NAMES]
    np.testing.assert_allclose(model.body_mass[1:], reference.body_mass[ids], rtol=1e-9)
    np.testing.assert_allclose(model.body_ipos[1:], reference.body_ipos[ids], atol=1e-9)
    np.testing.assert_allclose(model.body_inertia[1:], reference.body_inertia[ids], rtol=1e-6)


def _simulate(model, seconds):
    """Heights of the pelvis and of the lowest robot collision geom at each step, from the default key."""
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("default").id)  # ctrl = default joint pos
    robot_geoms = (model.geom_bodyid > 0) & (model.geom_contype != 0)
    pelvis, lowest = [], []
    for _ in range(round(seconds / model.opt.timestep)):
        mujoco.mj_step(model, data)
        assert np.isfinite(data.qpos).all() and np.isfinite(data.qvel).all()
        bottoms = data.geom_xpos[robot_geoms, 2] - _half_height(model, data)[robot_geoms]
        pelvis.append(data.qpos[2])
        lowest.append(bottoms.min())
    return np.array(pelvis), np.array(lowest)


def _half_height(model, data):
    # Lowest point of spheres and capsules below their centre (other robot geoms are visual only).
    axis_z = data.geom_xmat[:, 8]
    capsule = model.geom_type == mujoco.mjtGeom.mjGEOM_CAPSULE
    return model.geom_size[:, 0] + np.where(capsule, np.abs(axis_z) * model.geom_size[:, 1], 0.0)


def test_default_pose_under_beyondmimic_pd_is_finite_and_lands_on_its_feet(model):
    # The BeyondMimic gains are soft (ankle Kp 28.5 Nm/rad << m g h of about 230 Nm/rad): under constant
    # targets the robot tips forward after about 1 s, as it does in mjlab. It must first stand on its feet,
    # and the whole 2 s, fall included, must stay finite without sinking into the floor.
    pelvis, lowest = _simulate(model, 2.0)
    standing = slice(0, round(0.5 / model.opt.timestep))
    assert pelvis[standing].min() > 0.7
    assert lowest[standing].min() > -0.01


def test_default_pose_stands_with_stiffer_motors():
    # Ten times the reflected inertia gives ten times the Kp, enough to hold the bent-knee pose statically.
    cfg = robot_config()
    cfg.actuator_classes = [dataclasses.replace(c, armature=10 * c.armature) for c in cfg.actuator_classes]
    pelvis, lowest = _simulate(load_mjmodel(cfg=cfg), 2.0)
    assert pelvis.min() > 0.6 and pelvis[-1] > 0.7
    assert lowest.min() > -0.01


def test_every_joint_matches_exactly_one_actuator_class():
    cfg = robot_config()
    for joint in G1_JOINT_NAMES:
        matches = [c.name for c in cfg.actuator_classes if any(re.fullmatch(p, joint) for p in c.joints)]
        assert len(matches) == 1, (joint, matches)


def test_ambiguous_or_missing_actuator_class_names_the_joint(model):
    cfg = robot_config()
    cfg.actuator_classes.append(ActuatorClassConfig("dup", ["left_knee_joint"], 0.01, 10.0))
    with pytest.raises(RobotModelError, match="left_knee_joint"):
        resolve_robot(cfg, model)
    cfg = robot_config()
    cfg.actuator_classes = [c for c in cfg.actuator_classes if c.name != "4010"]
    with pytest.raises(RobotModelError, match="wrist_pitch_joint"):
        load_mjmodel(cfg=cfg)


def test_resolve_rejects_a_model_built_from_another_config(model):
    with pytest.raises(RobotModelError, match="kp="):
        resolve_robot(dataclasses.replace(robot_config(), natural_frequency_hz=5.0), model)


def test_resolve_bodies(info, model):
    assert info.anchor_body_id == model.body("torso_link").id
    assert [model.body(b).name for b in info.tracked_body_ids] == robot_config().tracked_bodies
    assert len(info.tracked_body_ids) == 14
    assert [model.body(b).name for b in info.end_effector_body_ids] == [
        "left_ankle_roll_link", "right_ankle_roll_link", "left_wrist_yaw_link", "right_wrist_yaw_link"]
    np.testing.assert_array_equal(info.qpos_adr, np.arange(7, 36))
    np.testing.assert_array_equal(info.dof_adr, np.arange(6, 35))
    with pytest.raises(RobotModelError, match="tracked_bodies.*'hand'"):
        resolve_robot(dataclasses.replace(robot_config(), tracked_bodies=["pelvis", "hand"]), model)


@settings(max_examples=50, deadline=None)
@given(factor=st.floats(0.05, 1.0))
def test_soft_limits_shrink_about_the_midpoint(model, factor):
    info = resolve_robot(dataclasses.replace(robot_config(), soft_joint_limit_factor=factor), model)
    hard, soft = info.joint_limits, info.soft_joint_limits
    np.testing.assert_allclose(soft.mean(axis=1), hard.mean(axis=1), atol=1e-12)
    np.testing.assert_allclose(soft[:, 1] - soft[:, 0], factor * (hard[:, 1] - hard[:, 0]), rtol=1e-9)
    assert (soft[:, 0] >= hard[:, 0] - 1e-12).all() and (soft[:, 1] <= hard[:, 1] + 1e-12).all()


def test_user_mjcf_roundtrip_keeps_the_interface(tmp_path, model):
    path = tmp_path / "g1_user.xml"
    path.write_text(build_spec(robot_config()).to_xml())
    user = load_mjmodel(mjcf_path=str(path))
    assert user.nu == 29 and user.nkey == 1 and user.nsensor == 0
    np.testing.assert_allclose(user.actuator_gainprm[:, 0], model.actuator_gainprm[:, 0])
    np.testing.assert_allclose(user.key_qpos, model.key_qpos)
    resolve_robot(robot_config(), user)


def test_user_mjcf_with_a_renamed_joint_fails_listing_missing_and_extra(tmp_path):
    spec = build_spec(robot_config())
    for element in [*spec.actuators, *spec.keys]:  # a user file would not drive the old name
        spec.delete(element)
    spec.nkey = 0
    spec.joint("left_knee_joint").name = "left_knee"
    path = tmp_path / "renamed.xml"
    path.write_text(spec.to_xml())
    with pytest.raises(RobotModelError, match=r"missing \['left_knee_joint'\], extra \['left_knee'\]"):
        load_mjmodel(mjcf_path=str(path))


def test_user_mjcf_errors_name_the_file(tmp_path):
    with pytest.raises(RobotModelError, match="nope.xml does not exist"):
        load_mjmodel(mjcf_path=str(tmp_path / "nope.xml"))
    with pytest.raises(RobotModelError, match="unknown robot 'h1'"):
        load_mjmodel("h1")


def test_reference_model_without_meshes_fails_clearly_and_stripped_loads(tmp_path):
    reference = _reference_model()  # skips when ../shared is absent
    with pytest.raises(RobotModelError, match=r"g1\.xml references \d+ missing mesh files"):
        load_mjmodel(mjcf_path=str(MENAGERIE_G1))
    spec = mujoco.MjSpec.from_file(str(MENAGERIE_G1))
    for geom in [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]:
        spec.delete(geom)
    for mesh in list(spec.meshes):
        spec.delete(mesh)
    path = tmp_path / "menagerie_stripped.xml"
    path.write_text(spec.to_xml())
    user = load_mjmodel(mjcf_path=str(path))
    info = resolve_robot(robot_config(), user)
    assert info.joint_names == G1_JOINT_NAMES and user.nsensor == 0
    assert user.body_subtreemass[1] == pytest.approx(reference.body_subtreemass[1])
    assert "floor" in [user.geom(g).name for g in range(user.ngeom)]
    assert not user.dof_frictionloss.any()


def test_the_g1s_numbers_live_in_its_yaml_only():
    raw = OmegaConf.load(REPO / "conf" / "robot" / "g1.yaml")
    assert list(raw.defaults) == ["robot_schema", "_self_"]
    values = OmegaConf.masked_copy(raw, [k for k in raw if k != "defaults"])
    assert set(values) == {f.name for f in dataclasses.fields(RobotConfig)}
    schema = OmegaConf.structured(RobotConfig)  # no robot's numbers: every value but mjcf_path is missing
    assert [k for k in schema if not OmegaConf.is_missing(schema, k)] == ["mjcf_path"]
    from tests.conftest import compose

    assert robot_config("g1") == OmegaConf.to_object(compose(["robot=g1"]).robot)
    assert robot_config("g1").foot_friction == 0.6 and robot_config().name == "g1"


def test_built_in_robots_are_found_by_their_two_files():
    assert robot_names() == ["g1"]  # bmimic/robot/models/g1.py and conf/robot/g1.yaml
    for bad in ("h1", "config", "../g1", ""):
        with pytest.raises(RobotModelError, match=r"robot.name: unknown robot .*; built-in robots: \['g1'\]"):
            robot_config(bad)
    with pytest.raises(RobotModelError, match="'h1' asked for, the robot config is 'g1'"):
        load_mjmodel("h1", cfg=robot_config())
