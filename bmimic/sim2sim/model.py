"""The robot model sim2sim runs the policy on: the run's G1, MuJoCo Menagerie's or any MJCF, with the
policy's actuators, physics options and a floor."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import cast

from bmimic.runs import safe_read
from bmimic.runs.folder import HYDRA_DIR
from bmimic.sim2sim.spec import PolicySpec, Sim2SimError, first_line, policy_error

MODELS = ("bmimic_g1", "menagerie")
"""Named robot models for --model (anything else is an MJCF path), each also its output folder's name."""
RENAMED = {"project": "bmimic_g1"}
"""Earlier names of MODELS, still accepted (`project` said whose code, not which robot the folder holds)."""
MENAGERIE_ENV = "BMIMIC_MENAGERIE_G1"
"""Environment variable naming the Menagerie G1 MJCF (g1.xml)."""
MENAGERIE_RELATIVE = Path("shared") / "reference" / "unitree_g1_menagerie" / "g1.xml"
"""Where the Menagerie G1 is looked for, under the checkout, its parent and the working directory."""


def find_menagerie() -> Path:
    """The Menagerie G1 MJCF: $BMIMIC_MENAGERIE_G1, else shared/reference/... beside the checkout or here."""
    env = os.environ.get(MENAGERIE_ENV)
    if env:
        path = Path(env).expanduser()
        if not path.is_file():
            raise Sim2SimError(f"{MENAGERIE_ENV}={env}: no such file")
        return path
    repo = Path(__file__).resolve().parents[2]
    for base in (repo, repo.parent, Path.cwd(), Path.cwd().parent):
        if (base / MENAGERIE_RELATIVE).is_file():
            return base / MENAGERIE_RELATIVE
    raise Sim2SimError(f"--model menagerie: the Menagerie G1 (g1.xml) was not found; set {MENAGERIE_ENV} or pass "
                       "its path as --model PATH")


def _run_g1_spec(run_dir: Path | None):
    """The G1 of the run's robot config (the built-in default without a run), and a description."""
    from bmimic.robot import RobotConfig, build_spec, load_user_spec, robot_config

    if run_dir is None:
        return build_spec(robot_config()), "built-in G1 (default robot config; no run folder)"
    from omegaconf import OmegaConf

    try:
        robot = OmegaConf.merge(OmegaConf.structured(RobotConfig), OmegaConf.create(safe_read.read_yaml_text(run_dir / HYDRA_DIR / "config.yaml")).robot)
        cfg = cast(RobotConfig, OmegaConf.to_object(robot))
    except Exception as e:  # omegaconf raises many types; all mean the same to the user
        raise Sim2SimError(f"{run_dir / HYDRA_DIR / 'config.yaml'}: robot config unreadable: {first_line(e)}") from None
    if not cfg.mjcf_path:
        return build_spec(cfg), f"built-in {cfg.name.upper()} (the run's robot config)"
    mjcf = Path(cfg.mjcf_path).expanduser()
    if not mjcf.is_absolute() and not mjcf.exists():
        try:  # relative to where training was started (as bmimic.eval resolves it)
            launch = Path(OmegaConf.create(safe_read.read_yaml_text(run_dir / HYDRA_DIR / "hydra.yaml")).hydra.runtime.cwd)
            mjcf = launch / mjcf if (launch / mjcf).exists() else mjcf
        except Exception:  # no hydra.yaml: leave the path as written
            pass
    return load_user_spec(mjcf, cfg), f"the run's robot.mjcf_path {mjcf}"


def _file_spec(path: Path):
    """An MJCF as an MjSpec; mesh geoms whose files are missing are removed (and said so)."""
    import mujoco

    from bmimic.robot.spec import missing_mesh_files, parse_mjcf

    spec = parse_mjcf(path, "--model")
    note = str(path)
    missing = missing_mesh_files(spec, path)
    if missing:
        geoms = [g for g in spec.geoms if g.type == mujoco.mjtGeom.mjGEOM_MESH]
        for g in geoms:
            spec.delete(g)
        for m in list(spec.meshes):
            spec.delete(m)
        note += f" ({len(missing)} mesh files missing: {len(geoms)} mesh geoms removed, primitives only)"
    return spec, note


def model_label(model: str) -> str:
    """Folder name of a --model choice: bmimic_g1, menagerie, or the MJCF's file stem."""
    model = RENAMED.get(model, model)
    return model if model in MODELS else re.sub(r"[^A-Za-z0-9_.-]", "_", Path(model).stem) or "model"


def build_model(spec: PolicySpec, model: str = "bmimic_g1", run_dir: Path | None = None,
                joint_dynamics: str = "model"):
    """(compiled MjModel, description) of `model` with the policy's actuators, options and a floor."""
    import mujoco

    from bmimic.robot import RobotModelError
    from bmimic.robot.spec import (
        add_pd_actuator,
        add_tracking_camera,
        add_world,
        checked_joint_names,
        root_body,
    )

    model = RENAMED.get(model, model)
    if model == "bmimic_g1":
        mjs, source = _run_g1_spec(run_dir)
    else:
        mjs, source = _file_spec(find_menagerie() if model == "menagerie" else Path(model).expanduser())
    try:
        checked_joint_names(mjs, spec.joint_names, "the policy's joint_names")
    except RobotModelError as e:
        raise Sim2SimError(f"--model {model}: {e}") from None
    bodies = {b.name for b in mjs.bodies}
    missing = [n for n in dict.fromkeys([*spec.body_names, spec.anchor_body, spec.root_body]) if n not in bodies]
    if missing:
        raise Sim2SimError(f"--model {model}: bodies {missing} of the policy's metadata are not in the model")
    if root_body(mjs).name != spec.root_body:
        raise Sim2SimError(f"--model {model}: its floating base is {root_body(mjs).name!r}, the policy's root body "
                           f"is {spec.root_body!r}")
    for element in [*mjs.actuators, *mjs.sensors, *mjs.keys]:
        mjs.delete(element)
    mjs.nkey = 0
    joints = {j.name: j for j in mjs.joints}
    for i, name in enumerate(spec.joint_names):  # actuator i drives policy joint i
        add_pd_actuator(mjs, name, spec.kp[i], spec.kd[i], spec.effort_limit[i])
        if joint_dynamics == "metadata":
            joints[name].armature = float(spec.armature[i])
            joints[name].damping = [0.0, 0.0, 0.0]
            joints[name].frictionloss = 0.0
    opt = mjs.option
    opt.timestep = spec.physics_dt_s
    try:
        opt.integrator = getattr(mujoco.mjtIntegrator, "mjINT_" + spec.sim_options["integrator"].upper())
        opt.solver = getattr(mujoco.mjtSolver, "mjSOL_" + spec.sim_options["solver"].upper())
        opt.cone = getattr(mujoco.mjtCone, "mjCONE_" + spec.sim_options["cone"].upper())
    except AttributeError as e:
        raise policy_error(spec.path, f"metadata sim_* option unknown to MuJoCo: {e}") from None
    opt.iterations = spec.sim_options["iterations"]
    opt.ls_iterations = spec.sim_options["ls_iterations"]
    add_world(mjs)
    add_tracking_camera(mjs, root_body(mjs))
    try:
        mjm = mjs.compile()
    except ValueError as e:
        raise Sim2SimError(f"--model {model}: MuJoCo could not compile it: {first_line(e)}") from None
    return mjm, f"{source}; joint dynamics: {joint_dynamics}"


