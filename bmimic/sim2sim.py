"""`python -m bmimic.sim2sim RUN_DIR_OR_ONNX [options]`: the exported policy in native MuJoCo on the CPU.

    python -m bmimic.sim2sim outputs/runs/default/<stamp>                 # latest motion_policy_<it>.onnx
    python -m bmimic.sim2sim RUN --model menagerie --episodes-per-bin 8 --workers 16
    python -m bmimic.sim2sim RUN/checkpoints/motion_policy_500.onnx --model path/to/g1.xml --video dance.mp4

A second-simulator check before a robot: the BeyondMimic-compatible ONNX (`motion_policy_<it>.onnx`,
written at every checkpoint or by `python -m bmimic.export RUN`) runs under onnxruntime in MuJoCo's C
engine (the `mujoco` bindings, not MuJoCo-Warp), and everything the control loop needs is read from
the file's metadata alone, never from bmimic's training code:

- Reference motion: the one baked into the file, read by evaluating its reference outputs at every
  time step (what BeyondMimic's deployment controller plays), not the run's motion file.
- Actuation: each joint gets a MuJoCo position-style actuator built with MjSpec from the metadata
  gains (gainprm Kp, biasprm (0, -Kp, -Kd), forcerange +-effort limit), the actuator model training
  used (`bmimic.robot.add_pd_actuator`), so the implicitfast integrator treats the Kd term implicitly
  as it did in training; a torque computed in Python once per physics step would make the damping
  explicit and change the closed loop. Control: target = default_joint_pos + action_scale * action,
  written once per control step and held for `decimation` physics steps of `physics_dt_s`.
- Observations: rebuilt in numpy from `observation_layout` (term functions and sizes), the tracked
  bodies, the anchor body and the baked reference; terminations from `terminations`; the physics
  options (integrator, solver, cone, iterations) from the `sim_*` keys.
- `--model project` is the G1 the run trained on (its `robot` config; the built-in G1 for a bare
  ONNX file), `menagerie` the MuJoCo Menagerie G1 (`BMIMIC_MENAGERIE_G1` or a `shared/reference`
  folder beside the checkout; mesh geoms whose files are missing are dropped, so only its primitive
  geoms collide), a path any MJCF. Joints are matched by name, a mismatch is refused. The model's own
  armature, joint damping and friction loss are kept (`--joint-dynamics model`: a model difference is
  what the check is for); `--joint-dynamics metadata` sets training's (metadata armature, none else).

The evaluation is `bmimic.eval`'s, with the same accounting (bmimic.training.evaluation):
`episodes_per_bin` episodes start at the same stratified frames of every time bin, from the reference
state, with the deterministic policy, for `horizon_s`; the reference stops at the end of its clip. An
episode that terminates fails at the frame it was judged at (with `max_mpkpe_rel_mm`, one whose mean
anchor-relative MPKPE exceeds it fails at its worst frame); failures are charged to the bin where they
happen, per visit, and per-step errors to the frame they were measured at. A physics divergence
(MuJoCo resets the state) is a termination. Settings not given are those of the MuJoCo-Warp evaluation
compared against. Episodes run in parallel, one MjData and one single-threaded onnxruntime session per
worker process. Tables (bmimic.eval's, plus `end_s`, `end_bin`, `diverged` per episode) go to
RUN/sim2sim/<model>/<checkpoint>/, with `sim2sim_gap_bins.csv`, and the gap in success rate and
anchor-relative MPKPE to the MuJoCo-Warp evaluation of the same checkpoint (RUN/eval/<checkpoint>/
from `bmimic.eval`, else the training-time evaluation in RUN/eval.parquet) is printed overall and per
bin, with a note when the two ran with different episodes per bin, horizon or MPKPE threshold.

The simulation path (this module's top level and everything a worker runs) imports numpy, mujoco,
onnxruntime and torch-free bmimic helpers only; the command's bookkeeping (bins, start frames,
tables) reuses bmimic.eval's, so the two evaluations are comparable row by row.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, NamedTuple, Sequence

import numpy as np

from bmimic import BmimicError

if TYPE_CHECKING:
    from bmimic.motion.motion import Motion

log = logging.getLogger("bmimic.sim2sim")

MODELS = ("project", "menagerie")
"""Named robot models for --model (anything else is an MJCF path)."""
MENAGERIE_ENV = "BMIMIC_MENAGERIE_G1"
"""Environment variable naming the Menagerie G1 MJCF (g1.xml)."""
MENAGERIE_RELATIVE = Path("shared") / "reference" / "unitree_g1_menagerie" / "g1.xml"
"""Where the Menagerie G1 is looked for, under the checkout, its parent and the working directory."""
MOTION_FILE = re.compile(r"motion_policy_(\d+)\.onnx$")
REFERENCE_OUTPUTS = ("joint_pos", "joint_vel", "body_pos_w", "body_quat_w", "body_lin_vel_w", "body_ang_vel_w")
"""Reference outputs of a BeyondMimic-compatible ONNX, after `actions` (the released exporter's order)."""
ERROR_NAMES = ("mpkpe_mm", "mpkpe_rel_mm", "anchor_ori_err_rad", "body_ori_err_rad", "joint_pos_err_rad",
               "joint_vel_err_radps", "ee_pos_err_mm")
"""Per-step tracking errors, named and ordered as bmimic.training.evaluation.ERROR_COLUMNS."""
REL_MPKPE = ERROR_NAMES.index("mpkpe_rel_mm")
GAP_FILE = "sim2sim_gap_bins.csv"


class Sim2SimError(BmimicError):
    """A policy file, model or run folder that sim2sim cannot use (one-line message)."""


# ============================================================================================ policy file
@dataclass
class ObsTerm:
    """One observation term of the policy input, in order."""

    name: str
    """Term name (BeyondMimic's observation_names)."""
    func: str
    """Observation function (a name of bmimic.envs.mdp.observations, re-implemented here in numpy)."""
    dim: int
    """Number of entries the term contributes."""


@dataclass
class PolicySpec:
    """Everything the metadata of a BeyondMimic-compatible ONNX says about the control loop."""

    path: Path
    """The ONNX file."""
    joint_names: list[str]
    """Actuated joints; every per-joint array and the actions are in this order."""
    kp: np.ndarray
    """Position gain per joint, Nm/rad."""
    kd: np.ndarray
    """Damping gain per joint, Nm s/rad."""
    default_joint_pos: np.ndarray
    """Default pose (the action offset), rad."""
    action_scale: np.ndarray
    """rad per unit action."""
    armature: np.ndarray
    """Armature training used, kg m^2 (applied with --joint-dynamics metadata)."""
    effort_limit: np.ndarray
    """Actuator torque limit, Nm."""
    body_names: list[str]
    """Tracked bodies, the order of the reference body arrays."""
    anchor_body: str
    """Body anchoring the reference to the robot."""
    root_body: str
    """The floating-base body (its reference pose and velocity start an episode)."""
    end_effector_bodies: list[str]
    """Bodies checked by the end-effector termination."""
    obs_terms: list[ObsTerm]
    """The policy input, term by term."""
    obs_dim: int
    """Size of the policy input."""
    terminations: list[tuple[str, str, dict]]
    """(name, function, params) of each termination term (time-outs excluded)."""
    control_dt_s: float
    """Policy period."""
    physics_dt_s: float
    """Physics time step."""
    decimation: int
    """Physics steps per control step."""
    sim_options: dict
    """integrator, solver, cone (names), iterations, ls_iterations."""
    fps: float
    """Reference frames per second (one frame per control step)."""
    num_frames: int
    """Reference frames baked into the file."""
    clip_starts: np.ndarray
    """First frame of each clip of the motion."""
    segments: list
    """Labelled time ranges of the motion (bmimic.motion.Segment)."""
    bin_layout: str
    """Kind of the run's bins: "time" (bin_size_s wide) or "released" (BeyondMimic's layout)."""
    bin_size_s: float
    """Time-bin width of the run's sampler and evaluation (the mean bin length for the released layout)."""
    iteration: int | None
    """Training iteration of the checkpoint, when recorded."""


def _policy_error(path: Path, what: str) -> Sim2SimError:
    return Sim2SimError(f"{path}: {what}")


def read_metadata(path: Path) -> tuple[dict[str, str], list[str], list[str]]:
    """(metadata, input names, output names) of an ONNX file."""
    import onnxruntime as ort

    try:
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for unreadable files
        raise _policy_error(path, f"not a readable ONNX file: {_first_line(e)}") from None
    meta = dict(session.get_modelmeta().custom_metadata_map)
    return meta, [i.name for i in session.get_inputs()], [o.name for o in session.get_outputs()]


def read_policy(path: str | Path) -> PolicySpec:
    """Parse and check the metadata of a BeyondMimic-compatible ONNX; raises Sim2SimError."""
    from bmimic.motion.motion import segments_from_json

    path = Path(path)
    if not path.is_file():
        raise _policy_error(path, "no such file")
    meta, inputs, outputs = read_metadata(path)
    if inputs != ["obs", "time_step"] or outputs[1:] != list(REFERENCE_OUTPUTS):
        raise _policy_error(path, f"inputs {inputs}, outputs {outputs}: not a BeyondMimic-compatible policy "
                                  "(obs, time_step -> actions + reference); use motion_policy_<it>.onnx")

    def get(key: str) -> str:
        if key not in meta:
            raise _policy_error(path, f"metadata has no {key!r}; write the file again with python -m bmimic.export RUN")
        return meta[key]

    def names(key: str) -> list[str]:
        return [x for x in get(key).split(",") if x]

    def numbers(key: str, n: int, positive: bool = False) -> np.ndarray:
        try:
            x = np.array([float(v) for v in get(key).split(",")], dtype=np.float64)
        except ValueError:
            raise _policy_error(path, f"metadata {key!r} is not a comma-separated list of numbers") from None
        if x.shape != (n,) or not np.isfinite(x).all() or (positive and (x <= 0).any()):
            need = "positive " if positive else ""
            raise _policy_error(path, f"metadata {key!r} must hold {n} finite {need}numbers, got {get(key)[:80]!r}")
        return x

    def scalar(key: str, kind=float):
        try:
            value = kind(get(key))
        except ValueError:
            raise _policy_error(path, f"metadata {key!r}={get(key)!r} is not a {kind.__name__}") from None
        if not (math.isfinite(value) and value > 0):
            raise _policy_error(path, f"metadata {key!r}={get(key)!r} must be > 0")
        return value

    def json_list(key: str) -> list[dict]:
        try:
            items = json.loads(get(key))
        except json.JSONDecodeError:
            raise _policy_error(path, f"metadata {key!r} is not JSON") from None
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise _policy_error(path, f"metadata {key!r} must be a JSON list of objects")
        return items

    def segments() -> list:
        try:
            return segments_from_json(get("motion_segments"))
        except ValueError as e:  # bad JSON or a malformed entry
            raise _policy_error(path, f"metadata 'motion_segments': {_first_line(e)}") from None

    joints = names("joint_names")
    nj = len(joints)
    body_names = names("body_names")
    layout = json_list("observation_layout")
    try:
        terms = [ObsTerm(str(t["name"]), str(t["func"]), int(t["dim"])) for t in layout]
        terminations = [(str(t["name"]), str(t["func"]), dict(t.get("params") or {})) for t in json_list("terminations")]
    except (KeyError, TypeError, ValueError):
        raise _policy_error(path, "metadata observation_layout/terminations entries need name, func (and dim)") from None
    with_params = [t["name"] for t in layout if t.get("params")]
    if with_params:
        raise _policy_error(path, f"observation terms {with_params} have parameters; sim2sim's numpy terms take none")
    if [t.name for t in terms] != names("observation_names"):
        raise _policy_error(path, "metadata observation_layout does not list the observation_names in order")
    spec = PolicySpec(
        path=path,
        joint_names=joints,
        kp=numbers("joint_stiffness", nj, positive=True),
        kd=numbers("joint_damping", nj),
        default_joint_pos=numbers("default_joint_pos", nj),
        action_scale=numbers("action_scale", nj),
        armature=numbers("joint_armature", nj),
        effort_limit=numbers("joint_effort_limit", nj, positive=True),
        body_names=body_names,
        anchor_body=get("anchor_body_name"),
        root_body=get("root_body_name"),
        end_effector_bodies=names("end_effector_body_names"),
        obs_terms=terms,
        obs_dim=scalar("policy_obs_dim", int),
        terminations=terminations,
        control_dt_s=scalar("control_dt_s"),
        physics_dt_s=scalar("physics_dt_s"),
        decimation=scalar("decimation", int),
        sim_options={k: get(f"sim_{k}") for k in ("integrator", "solver", "cone")}
        | {k: scalar(f"sim_{k}", int) for k in ("iterations", "ls_iterations")},
        fps=scalar("motion_fps"),
        num_frames=scalar("motion_num_frames", int),
        clip_starts=numbers("motion_clip_starts", len(names("motion_clip_starts"))).astype(np.int64),
        segments=segments(),
        bin_layout=meta.get("bin_layout", "time"),  # files exported before the released layout existed
        bin_size_s=scalar("bin_size_s"),
        iteration=int(meta["iteration"]) if meta.get("iteration", "").lstrip("-").isdigit() else None,
    )
    _check_spec(spec)
    return spec


def _check_spec(spec: PolicySpec) -> None:
    """Consistency of the layout, bodies and periods (each failure names the key)."""
    path, nj, nb = spec.path, len(spec.joint_names), len(spec.body_names)
    for name in (spec.anchor_body, spec.root_body, *spec.end_effector_bodies):
        if name not in spec.body_names:
            raise _policy_error(path, f"metadata body {name!r} (anchor/root/end effector) is not in body_names")
    for term in spec.obs_terms:
        if term.func not in OBS_DIMS:
            raise _policy_error(path, f"observation term {term.name!r}: function {term.func!r} has no numpy version "
                                      f"in bmimic.sim2sim (known: {sorted(OBS_DIMS)})")
        expected = OBS_DIMS[term.func](nj, nb)
        if term.dim != expected:
            raise _policy_error(path, f"observation term {term.name!r} ({term.func}) has size {term.dim}, "
                                      f"expected {expected} for {nj} joints and {nb} bodies")
    if sum(t.dim for t in spec.obs_terms) != spec.obs_dim:
        raise _policy_error(path, f"observation_layout sizes add up to {sum(t.dim for t in spec.obs_terms)}, "
                                  f"not policy_obs_dim={spec.obs_dim}")
    for name, func, params in spec.terminations:
        if func not in TERMINATIONS:
            raise _policy_error(path, f"termination {name!r}: function {func!r} has no numpy version in "
                                      f"bmimic.sim2sim (known: {sorted(TERMINATIONS)})")
        if set(params) != {TERMINATIONS[func]} or not all(isinstance(v, (int, float)) for v in params.values()):
            raise _policy_error(path, f"termination {name!r} ({func}): params {params} must be "
                                      f"{{{TERMINATIONS[func]!r}: number}}")
    if not math.isclose(spec.physics_dt_s * spec.decimation, spec.control_dt_s, rel_tol=1e-6):
        raise _policy_error(path, f"physics_dt_s x decimation = {spec.physics_dt_s * spec.decimation:g} s, "
                                  f"but control_dt_s = {spec.control_dt_s:g} s")


# ============================================================================================ numpy maths
def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of unit quaternions (w, x, y, z)."""
    w, x, y, z = np.moveaxis(np.asarray(q, dtype=np.float64), -1, 0)
    m = np.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
                  2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
                  2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), axis=-1)
    return m.reshape(m.shape[:-1] + (3, 3))


def rotation_angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle in [0, pi] of the rotation between rotation matrices a and b ([..., 3, 3])."""
    cos = 0.5 * (np.einsum("...ij,...ij->...", a, b) - 1.0)  # (trace(a^T b) - 1) / 2
    return np.arccos(np.clip(cos, -1.0, 1.0))


# ============================================================================================ observations
# Size of each observation function for J joints and B tracked bodies.
OBS_DIMS: dict[str, Callable[[int, int], int]] = {
    "motion_command": lambda j, b: 2 * j,
    "motion_anchor_pos_b": lambda j, b: 3,
    "motion_anchor_ori_b": lambda j, b: 6,
    "robot_body_pos_b": lambda j, b: 3 * b,
    "robot_body_ori_b": lambda j, b: 6 * b,
    "base_lin_vel": lambda j, b: 3,
    "base_ang_vel": lambda j, b: 3,
    "joint_pos_rel": lambda j, b: j,
    "joint_vel_rel": lambda j, b: j,
    "last_action": lambda j, b: j,
}
# Termination functions with a numpy version, and the one threshold parameter each takes.
TERMINATIONS = {"bad_anchor_pos_z_only": "threshold_m", "bad_anchor_ori": "threshold",
                "bad_motion_body_pos_z_only": "threshold_m"}


def policy_session(path: Path):
    """A single-threaded onnxruntime session (deterministic; one per worker process)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def read_reference(session, spec: PolicySpec) -> Motion:
    """The motion baked into the file (tracked bodies only), read by evaluating its reference outputs at
    every time step 0..T-1, as a deployment controller plays it."""
    from bmimic.motion.motion import Motion, MotionDataError

    obs = np.zeros((1, spec.obs_dim), dtype=np.float32)
    out = {name: [] for name in REFERENCE_OUTPUTS}
    for t in range(spec.num_frames):
        values = session.run(list(REFERENCE_OUTPUTS), {"obs": obs, "time_step": np.array([[t]], dtype=np.float32)})
        for name, v in zip(REFERENCE_OUTPUTS, values):
            out[name].append(v[0])
    try:
        return Motion(fps=spec.fps, **{k: np.asarray(v) for k, v in out.items()}, joint_names=spec.joint_names,
                      body_names=spec.body_names, segments=spec.segments, clip_starts=spec.clip_starts)
    except MotionDataError as e:
        raise _policy_error(spec.path, f"the baked-in motion does not fit the metadata: {e}") from None


# ============================================================================================ robot model
def find_menagerie() -> Path:
    """The Menagerie G1 MJCF: $BMIMIC_MENAGERIE_G1, else shared/reference/... beside the checkout or here."""
    env = os.environ.get(MENAGERIE_ENV)
    if env:
        path = Path(env).expanduser()
        if not path.is_file():
            raise Sim2SimError(f"{MENAGERIE_ENV}={env}: no such file")
        return path
    repo = Path(__file__).resolve().parents[1]
    for base in (repo, repo.parent, Path.cwd(), Path.cwd().parent):
        if (base / MENAGERIE_RELATIVE).is_file():
            return base / MENAGERIE_RELATIVE
    raise Sim2SimError(f"--model menagerie: the Menagerie G1 (g1.xml) was not found; set {MENAGERIE_ENV} or pass "
                       "its path as --model PATH")


def _project_spec(run_dir: Path | None):
    """The G1 of the run's robot config (the built-in default without a run), and a description."""
    from bmimic.robot import RobotConfig, build_g1_spec
    from bmimic.robot.g1 import load_user_spec

    if run_dir is None:
        return build_g1_spec(RobotConfig()), "built-in G1 (default robot config; no run folder)"
    from omegaconf import OmegaConf

    try:
        robot = OmegaConf.merge(OmegaConf.structured(RobotConfig),
                                OmegaConf.load(run_dir / ".hydra" / "config.yaml").robot)
        cfg: RobotConfig = OmegaConf.to_object(robot)
    except Exception as e:  # omegaconf raises many types; all mean the same to the user
        raise Sim2SimError(f"{run_dir / '.hydra' / 'config.yaml'}: robot config unreadable: {_first_line(e)}") from None
    if not cfg.mjcf_path:
        return build_g1_spec(cfg), "built-in G1 (the run's robot config)"
    mjcf = Path(cfg.mjcf_path).expanduser()
    if not mjcf.is_absolute() and not mjcf.exists():
        try:  # relative to where training was started (as bmimic.eval resolves it)
            launch = Path(OmegaConf.load(run_dir / ".hydra" / "hydra.yaml").hydra.runtime.cwd)
            mjcf = launch / mjcf if (launch / mjcf).exists() else mjcf
        except Exception:  # no hydra.yaml: leave the path as written
            pass
    return load_user_spec(mjcf, cfg), f"the run's robot.mjcf_path {mjcf}"


def _file_spec(path: Path):
    """An MJCF as an MjSpec; mesh geoms whose files are missing are removed (and said so)."""
    import mujoco

    from bmimic.robot.g1 import missing_mesh_files, parse_mjcf

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
    """Folder name of a --model choice: project, menagerie, or the MJCF's file stem."""
    return model if model in MODELS else re.sub(r"[^A-Za-z0-9_.-]", "_", Path(model).stem) or "model"


def build_model(spec: PolicySpec, model: str = "project", run_dir: Path | None = None,
                joint_dynamics: str = "model"):
    """(compiled MjModel, description) of `model` with the policy's actuators, options and a floor."""
    import mujoco

    from bmimic.robot import RobotModelError
    from bmimic.robot.g1 import (
        add_pd_actuator,
        add_tracking_camera,
        add_world,
        checked_joint_names,
        root_body,
    )

    if model == "project":
        mjs, source = _project_spec(run_dir)
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
        raise _policy_error(spec.path, f"metadata sim_* option unknown to MuJoCo: {e}") from None
    opt.iterations = spec.sim_options["iterations"]
    opt.ls_iterations = spec.sim_options["ls_iterations"]
    add_world(mjs)
    add_tracking_camera(mjs, root_body(mjs))
    try:
        mjm = mjs.compile()
    except ValueError as e:
        raise Sim2SimError(f"--model {model}: MuJoCo could not compile it: {_first_line(e)}") from None
    return mjm, f"{source}; joint dynamics: {joint_dynamics}"


# ============================================================================================ rollout
class Rollout:
    """One robot in native MuJoCo driven by the policy: reset to a reference frame, step, observe.

    Mirrors the evaluation environment's step: PD targets held for `decimation` physics steps,
    kinematics of the new state, terminations against the current reference frame, then the frame
    advances (stopping at the clip's last frame) and the observation is built from the new frame.
    Rotations are handled as matrices (MuJoCo's xmat, the reference's precomputed once), which gives
    the same quantities as the training code's quaternion formulas.
    """

    def __init__(self, mjm, spec: PolicySpec, ref: Motion, session=None) -> None:
        import mujoco

        self.m, self.d = mjm, mujoco.MjData(mjm)
        self.spec, self.ref, self.session = spec, ref, session
        jid = [mjm.joint(n).id for n in spec.joint_names]
        self.qadr = mjm.jnt_qposadr[jid].astype(np.int64)
        self.vadr = mjm.jnt_dofadr[jid].astype(np.int64)
        free = int(np.flatnonzero(mjm.jnt_type == mujoco.mjtJoint.mjJNT_FREE)[0])
        self.free_q, self.free_v = int(mjm.jnt_qposadr[free]), int(mjm.jnt_dofadr[free])
        self.body_ids = np.array([mjm.body(n).id for n in spec.body_names], dtype=np.int64)
        self.anchor = spec.body_names.index(spec.anchor_body)
        self.root = spec.body_names.index(spec.root_body)
        self.ee = np.array([spec.body_names.index(n) for n in spec.end_effector_bodies], dtype=np.int64)
        self.ref_mat = quat_to_matrix(ref.body_quat_w)  # [T, B, 3, 3]
        ends = np.append(ref.clip_starts[1:], ref.num_frames)
        self.clip_end = np.repeat(ends, np.diff(np.append(ref.clip_starts, ref.num_frames)))  # frame -> its clip's end
        self.actions = np.zeros(len(spec.joint_names))
        self.frame = 0
        self.segment_end = spec.num_frames
        self._obs = np.zeros((1, spec.obs_dim), dtype=np.float32)
        self._time = np.zeros((1, 1), dtype=np.float32)
        self._bad = mujoco.mjtWarning.mjWARN_BADQACC
        self._terms = [(getattr(self, "_t_" + f), p) for _, f, p in spec.terminations]
        self._obs_fns = [getattr(self, "_o_" + t.func) for t in spec.obs_terms]
        self._version = 0  # bumped by every change of the physics state
        self._cached: tuple = (None, None)

    # ---------------------------------------------------------------------------------- state
    def reference_qpos(self, frame: int) -> np.ndarray:
        """qpos of the reference pose at `frame` (root body pose + joint angles)."""
        r, f = self.ref, self._clamp(frame)
        qpos = self.m.qpos0.copy()
        qpos[self.free_q:self.free_q + 3] = r.body_pos_w[f, self.root]
        qpos[self.free_q + 3:self.free_q + 7] = r.body_quat_w[f, self.root]
        qpos[self.qadr] = r.joint_pos[f]
        return qpos

    def reset(self, frame: int) -> None:
        """Put the robot exactly at the reference state of `frame` (no noise), actions zero."""
        r, f = self.ref, self._clamp(frame)
        qvel = np.zeros(self.m.nv)
        qvel[self.free_v:self.free_v + 3] = r.body_lin_vel_w[f, self.root]
        # The free joint's angular velocity is in the body frame.
        qvel[self.free_v + 3:self.free_v + 6] = self.ref_mat[f, self.root].T @ r.body_ang_vel_w[f, self.root]
        qvel[self.vadr] = r.joint_vel[f]
        self.set_state(self.reference_qpos(f), qvel, f, np.zeros(len(self.spec.joint_names)))

    def set_state(self, qpos: np.ndarray, qvel: np.ndarray, frame: int, actions: np.ndarray) -> None:
        """Any state: qpos/qvel in this model's layout, the reference frame, the last action."""
        import mujoco

        mujoco.mj_resetData(self.m, self.d)
        self.d.qpos[:] = qpos
        self.d.qvel[:] = qvel
        self.frame = int(frame)
        self.segment_end = int(self.clip_end[self._clamp(frame)])
        self.actions = np.asarray(actions, dtype=np.float64).copy()
        mujoco.mj_forward(self.m, self.d)
        self._version += 1

    def _clamp(self, frame: int) -> int:
        return min(max(int(frame), 0), self.spec.num_frames - 1)

    def state(self) -> dict:
        """Robot and reference quantities at the current physics state and reference frame (cached)."""
        key = (self._version, self.frame)
        if self._cached[0] == key:
            return self._cached[1]
        d, r, a = self.d, self.ref, self.anchor
        f = self._clamp(self.frame)
        pos = d.xpos[self.body_ids]
        mat = d.xmat[self.body_ids].reshape(-1, 3, 3)
        ref_pos, ref_mat = r.body_pos_w[f], self.ref_mat[f]
        # Anchor-centred, yaw-aligned, height-preserving targets (BeyondMimic): the yaw of
        # R_robot_anchor R_ref_anchor^T rotates the reference about the robot's anchor.
        m = mat[a] @ ref_mat[a].T
        yaw = math.atan2(m[1, 0], m[0, 0])
        c, s_ = math.cos(yaw), math.sin(yaw)
        rz = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
        origin = np.array([pos[a, 0], pos[a, 1], ref_pos[a, 2]])
        state = {
            "joint_pos": d.qpos[self.qadr], "joint_vel": d.qvel[self.vadr],
            "root_lin_vel_w": d.qvel[self.free_v:self.free_v + 3],
            "root_ang_vel_b": d.qvel[self.free_v + 3:self.free_v + 6],
            "pos": pos, "mat": mat,
            "ref_joint_pos": r.joint_pos[f], "ref_joint_vel": r.joint_vel[f],
            "ref_pos": ref_pos, "ref_mat": ref_mat,
            "rel_pos": origin + (ref_pos - ref_pos[a]) @ rz.T,
            "rel_mat": rz @ ref_mat,
        }
        self._cached = (key, state)
        return state

    # ---------------------------------------------------------------------------------- observations
    def observation(self) -> np.ndarray:
        """[1, obs_dim] float32 policy input at the current state and frame."""
        s = self.state()
        i = 0
        for fn, term in zip(self._obs_fns, self.spec.obs_terms):
            self._obs[0, i:i + term.dim] = fn(s)
            i += term.dim
        return self._obs

    def _o_motion_command(self, s):
        return np.concatenate((s["ref_joint_pos"], s["ref_joint_vel"]))

    def _o_motion_anchor_pos_b(self, s):
        a = self.anchor
        return s["mat"][a].T @ (s["ref_pos"][a] - s["pos"][a])

    def _o_motion_anchor_ori_b(self, s):
        a = self.anchor  # first two columns of R_anchor^T R_ref_anchor, row by row
        return (s["mat"][a].T @ s["ref_mat"][a])[:, :2].reshape(-1)

    def _o_robot_body_pos_b(self, s):
        a = self.anchor
        return ((s["pos"] - s["pos"][a]) @ s["mat"][a]).reshape(-1)

    def _o_robot_body_ori_b(self, s):
        return np.einsum("ji,bjk->bik", s["mat"][self.anchor], s["mat"])[:, :, :2].reshape(-1)

    def _o_base_lin_vel(self, s):
        return s["mat"][self.root].T @ s["root_lin_vel_w"]  # the root body's frame is the free joint's

    def _o_base_ang_vel(self, s):
        return s["root_ang_vel_b"]

    def _o_joint_pos_rel(self, s):
        return s["joint_pos"] - self.spec.default_joint_pos

    def _o_joint_vel_rel(self, s):
        return s["joint_vel"]

    def _o_last_action(self, s):
        return self.actions

    # ---------------------------------------------------------------------------------- terminations
    def _t_bad_anchor_pos_z_only(self, s, threshold_m: float) -> bool:
        return abs(s["ref_pos"][self.anchor, 2] - s["pos"][self.anchor, 2]) > threshold_m

    def _t_bad_anchor_ori(self, s, threshold: float) -> bool:
        # z of gravity (0, 0, -1) in the anchor frame is -R[2, 2]: the difference of cos(tilt).
        return abs(s["ref_mat"][self.anchor, 2, 2] - s["mat"][self.anchor, 2, 2]) > threshold

    def _t_bad_motion_body_pos_z_only(self, s, threshold_m: float) -> bool:
        err = np.abs(s["rel_pos"][self.ee, 2] - s["pos"][self.ee, 2])
        return bool((err > threshold_m).any())

    def terminated(self) -> bool:
        """Any termination term at the current state and frame."""
        s = self.state()
        return any(fn(s, **params) for fn, params in self._terms)

    # ---------------------------------------------------------------------------------- errors
    def errors(self) -> np.ndarray:
        """The ERROR_NAMES at the current state and frame (bmimic.training.evaluation's definitions)."""
        s = self.state()
        a, ee = self.anchor, self.ee
        return np.array((
            1000.0 * np.linalg.norm(s["ref_pos"] - s["pos"], axis=-1).mean(),
            1000.0 * np.linalg.norm((s["ref_pos"] - s["ref_pos"][a]) - (s["pos"] - s["pos"][a]), axis=-1).mean(),
            float(rotation_angle(s["ref_mat"][a], s["mat"][a])),
            float(rotation_angle(s["rel_mat"], s["mat"]).mean()),
            float(np.abs(s["ref_joint_pos"] - s["joint_pos"]).mean()),
            float(np.abs(s["ref_joint_vel"] - s["joint_vel"]).mean()),
            1000.0 * np.linalg.norm(s["rel_pos"][ee] - s["pos"][ee], axis=-1).mean(),
        ))

    # ---------------------------------------------------------------------------------- stepping
    def policy_action(self) -> np.ndarray:
        """The deterministic action for the current observation and reference frame."""
        self._time[0, 0] = self.frame
        return self.session.run(["actions"], {"obs": self.observation(), "time_step": self._time})[0][0]

    def physics(self, actions: np.ndarray) -> bool:
        """Hold the PD targets of `actions` for one control step; False if MuJoCo had to reset (diverged)."""
        import mujoco

        self.actions = np.asarray(actions, dtype=np.float64).copy()
        self.d.ctrl[:] = self.spec.default_joint_pos + self.spec.action_scale * self.actions
        bad = self.d.warning[self._bad].number
        for _ in range(self.spec.decimation):
            mujoco.mj_step(self.m, self.d)
        mujoco.mj_kinematics(self.m, self.d)  # body poses of the new state
        self._version += 1
        return self.d.warning[self._bad].number == bad and bool(np.isfinite(self.d.qpos).all())

    def advance(self) -> bool:
        """Next reference frame (held at the clip's last one); True once that last frame is reached."""
        self.frame = min(self.frame + 1, self.segment_end - 1)
        return self.frame >= self.segment_end - 1


class Episode(NamedTuple):
    """One evaluation episode: its tidy row and the errors of each step where they were measured."""

    row: dict
    """bmimic.training.evaluation.EPISODE_COLUMNS, `error_failed`, the mean of each ERROR_NAMES entry over
    the alive steps, `diverged` and `wall_s`."""
    frames: np.ndarray
    """[steps] the reference frame each step was judged at."""
    errors: np.ndarray
    """[steps, len(ERROR_NAMES)] the errors of each step."""


def run_episode(rollout: Rollout, start_frame: int, horizon_steps: int, max_mpkpe_rel_mm: float | None = None,
                on_step: Callable[[Rollout, bool], None] | None = None) -> Episode:
    """One evaluation episode, accounted exactly as bmimic.training.evaluation.Evaluator.run_episodes does.

    Each step is judged at the frame the reference stood at when it began (terminations; the step's
    errors, measured after the reference advanced, are summed at that frame). The episode ends at a
    termination (failed, charged at that frame), when the reference reaches its clip's last frame
    (`end_frame` is then that frame) or at the horizon; `horizon_truncated` when the clip ends before the
    horizon. With `max_mpkpe_rel_mm`, an episode that did not terminate but whose mean anchor-relative
    MPKPE exceeds it fails, charged at its worst step's frame (the first, on ties). A step after which
    MuJoCo had to reset the state (divergence) terminates the episode at that step's frame, and its
    errors (of a state that no longer exists) are not counted.
    """
    rollout.reset(start_frame)
    start = rollout.frame
    truncated = rollout.segment_end - 1 - start < horizon_steps
    if on_step is not None:
        on_step(rollout, False)
    frames: list[int] = []
    errors: list[np.ndarray] = []
    terminated = diverged = False
    end_frame = start
    t0 = time.perf_counter()
    for _ in range(horizon_steps):
        frame = end_frame = rollout.frame
        action = rollout.policy_action()
        if not rollout.physics(action):
            terminated = diverged = True
            break
        stop = rollout.terminated()
        clip_end = rollout.advance()
        frames.append(frame)
        errors.append(rollout.errors())
        if on_step is not None:
            on_step(rollout, stop)
        if stop:
            terminated = True
            break
        if clip_end:
            end_frame = rollout.frame  # tracked up to the clip's last frame
            break
    err = np.asarray(errors, dtype=np.float64).reshape(len(frames), len(ERROR_NAMES))
    means = err.sum(axis=0) / max(len(frames), 1)
    error_failed = bool(max_mpkpe_rel_mm is not None and not terminated and means[REL_MPKPE] > max_mpkpe_rel_mm)
    if terminated:
        failure_frame = end_frame
    elif error_failed:
        failure_frame = frames[int(np.argmax(err[:, REL_MPKPE]))]
    else:
        failure_frame = -1
    row = {
        "start_frame": int(start), "end_frame": int(end_frame), "failed": terminated or error_failed,
        "failure_frame": int(failure_frame), "terminated": terminated, "error_failed": error_failed,
        "steps": len(frames), "horizon_truncated": bool(truncated), **dict(zip(ERROR_NAMES, means.tolist())),
        "diverged": diverged, "wall_s": time.perf_counter() - t0,
    }
    return Episode(row, np.asarray(frames, dtype=np.int64), err)


# ============================================================================================ workers
_WORKER: dict = {}


def _init_worker(policy_path: Path, mjm, spec: PolicySpec, ref: Motion, horizon_steps: int,
                 max_mpkpe_rel_mm: float | None) -> None:
    _WORKER["rollout"] = Rollout(mjm, spec, ref, policy_session(policy_path))
    _WORKER["args"] = (horizon_steps, max_mpkpe_rel_mm)


def _work(start_frame: int) -> Episode:
    return run_episode(_WORKER["rollout"], int(start_frame), *_WORKER["args"])


def run_episodes(policy_path: Path, mjm, spec: PolicySpec, ref: Motion, frames: np.ndarray, horizon_steps: int,
                 workers: int, max_mpkpe_rel_mm: float | None = None) -> tuple[list[Episode], float]:
    """(one Episode per start frame, in order; wall seconds) over `workers` processes (spawned: no fork
    of the caller's threads), each with its own MjData and onnxruntime session."""
    t0 = time.perf_counter()
    workers = max(1, min(workers, len(frames)))
    init = (policy_path, mjm, spec, ref, horizon_steps, max_mpkpe_rel_mm)
    if workers == 1:
        _init_worker(*init)
        episodes = [_work(f) for f in frames]
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"), initializer=_init_worker,
                                 initargs=init) as pool:
            episodes = list(pool.map(_work, frames, chunksize=max(1, len(frames) // (8 * workers))))
    return episodes, time.perf_counter() - t0


# ============================================================================================ input location
def locate(path: str | Path) -> tuple[Path, Path | None]:
    """(BeyondMimic-compatible ONNX, run folder or None) for a run folder or an ONNX file."""
    p = Path(path).expanduser()
    if not p.exists():
        raise Sim2SimError(f"{p}: no such run folder or ONNX file")
    if p.is_file():
        run = p.resolve().parent.parent
        return p.resolve(), run if (run / ".hydra" / "config.yaml").is_file() else None
    found = [(int(m.group(1)), f) for f in (p / "checkpoints").glob("motion_policy_*.onnx")
             if (m := MOTION_FILE.search(f.name))]
    if not found:
        raise Sim2SimError(f"{p}: no checkpoints/motion_policy_<it>.onnx (the BeyondMimic-compatible export); "
                           f"write it with: python -m bmimic.export {p}")
    return max(found)[1].resolve(), p.resolve()


def checkpoint_label(spec: PolicySpec) -> str:
    """model_<it> (the name bmimic.eval gives the same checkpoint), else the file stem."""
    if spec.iteration is not None:
        return f"model_{spec.iteration}"
    m = MOTION_FILE.search(spec.path.name)
    return f"model_{m.group(1)}" if m else spec.path.stem


def _first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


# ============================================================================================ MuJoCo-Warp side
SETTINGS = ("episodes_per_bin", "horizon_s", "max_mpkpe_rel_mm")
"""Evaluation settings two evaluations must share to be compared bin by bin."""


@dataclass
class WarpEval:
    """The MuJoCo-Warp evaluation of the same checkpoint, for the gap."""

    source: str
    """Where it was read."""
    bins: object
    """pandas DataFrame: bin, visits, failures, success_rate (1 - failures / visits), mpkpe_rel_mm."""
    success_rate: float
    """Overall success rate (episodes that did not fail / episodes)."""
    mpkpe_rel_mm: float
    """Overall anchor-relative MPKPE (mean over the evaluation steps)."""
    settings: dict
    """The SETTINGS it ran with, as far as known (a missing key: unknown; max_mpkpe_rel_mm None: not set)."""


def warp_eval(run_dir: Path | None, label: str, iteration: int | None) -> WarpEval | None:
    """RUN/eval/<label>/ (bmimic.eval) if present, else the training-time rows of RUN/eval.parquet."""
    import pandas as pd

    from bmimic.training.evaluation import summarize

    if run_dir is None:
        return None
    columns = ["bin", "visits", "failures", "success_rate", "mpkpe_rel_mm"]
    folder = run_dir / "eval" / label
    if (folder / "eval_summary.json").is_file() and (folder / "eval_bins.parquet").is_file():
        s = json.loads((folder / "eval_summary.json").read_text())
        bins = pd.read_parquet(folder / "eval_bins.parquet")
        if "visits" in bins:
            return WarpEval(str(folder), bins[columns], float(s["eval_success_rate"]), float(s["eval_mpkpe_rel_mm"]),
                            {k: s[k] for k in SETTINGS if k in s})
        log.warning("%s: tables of the old start-bin accounting, not compared (evaluate again with python -m "
                    "bmimic.eval)", folder)
    table = run_dir / "eval.parquet"
    if iteration is None or not table.is_file():
        return None
    rows = pd.read_parquet(table)
    rows = rows[rows["iteration"] == iteration].reset_index(drop=True)
    if rows.empty:
        return None
    if "visits" not in rows:
        log.warning("%s: rows of the old start-bin accounting, not compared (run python -m bmimic.eval %s)",
                    table, run_dir)
        return None
    overall = summarize(rows)
    settings = {"episodes_per_bin": int(rows["start_episodes"].max())}
    config = _run_eval_config(run_dir)
    settings |= {k: config[k] for k in SETTINGS[1:] if k in config}
    return WarpEval(f"{table} (iteration {iteration})", rows.assign(success_rate=1.0 - rows["failure_rate"])[columns],
                    overall["eval_success_rate"], overall["eval_mpkpe_rel_mm"], settings)


def _run_eval_config(run_dir: Path | None) -> dict:
    """The run's resolved `eval` settings (resolved_config.json), or {} when unknown."""
    try:
        section = json.loads((run_dir / "resolved_config.json").read_text())["eval"]
    except (TypeError, OSError, KeyError, ValueError):
        return {}
    return section if isinstance(section, dict) else {}


def eval_settings(run_dir: Path | None, warp: WarpEval | None, episodes_per_bin: int | None,
                  horizon_s: float | None, max_mpkpe_rel_mm: float | None) -> dict:
    """The SETTINGS of this evaluation: given ones win, then the MuJoCo-Warp evaluation's (so the gap
    compares like with like), then the run's config, then bmimic's defaults on a CPU."""
    given = {"episodes_per_bin": episodes_per_bin, "horizon_s": horizon_s, "max_mpkpe_rel_mm": max_mpkpe_rel_mm}
    known = {"episodes_per_bin": 1, "horizon_s": 2.0, "max_mpkpe_rel_mm": None}
    config = _run_eval_config(run_dir)  # a null max_mpkpe_rel_mm is a setting ("not set"), other nulls are not
    known |= {k: config[k] for k in SETTINGS if k in config and (config[k] is not None or k == "max_mpkpe_rel_mm")}
    known |= warp.settings if warp is not None else {}
    out = {k: given[k] if given[k] is not None else known[k] for k in SETTINGS}
    if out["episodes_per_bin"] < 1 or not out["horizon_s"] > 0 or not (out["max_mpkpe_rel_mm"] is None
                                                                      or out["max_mpkpe_rel_mm"] > 0):
        raise Sim2SimError(f"--episodes-per-bin {out['episodes_per_bin']} / --horizon-s {out['horizon_s']} / "
                           f"--max-mpkpe-rel-mm {out['max_mpkpe_rel_mm']}: need >= 1, > 0 and > 0")
    return {"episodes_per_bin": int(out["episodes_per_bin"]), "horizon_s": float(out["horizon_s"]),
            "max_mpkpe_rel_mm": None if out["max_mpkpe_rel_mm"] is None else float(out["max_mpkpe_rel_mm"])}


def setting_differences(ours: dict, warp: WarpEval) -> list[str]:
    """Each SETTING in which this evaluation differs from the MuJoCo-Warp one, or that is unknown there."""
    out = []
    for key in SETTINGS:
        if key not in warp.settings:
            out.append(f"{key}: {ours[key]} here, unknown there")
            continue
        a, b = ours[key], warp.settings[key]
        if (a is None) != (b is None) or (a is not None and not math.isclose(float(a), float(b))):
            out.append(f"{key}: {a} here, {b} there")
    return out


def gap_table(bins, warp: WarpEval):
    """Per bin: MuJoCo-Warp and sim2sim visits, failures (where they happened), success rate per visit
    and anchor-relative MPKPE, and the differences."""
    ours = bins[["bin", "bin_start_s", "bin_end_s", "segment", "horizon_truncated", "visits", "failures",
                 "success_rate", "mpkpe_rel_mm"]]
    names = ["visits", "failures", "success_rate", "mpkpe_rel_mm"]
    out = ours.rename(columns={c: f"sim2sim_{c}" for c in names})
    out = out.merge(warp.bins.rename(columns={c: f"warp_{c}" for c in names}), on="bin", how="left")
    out["success_gap"] = out["sim2sim_success_rate"] - out["warp_success_rate"]
    out["mpkpe_rel_gap_mm"] = out["sim2sim_mpkpe_rel_mm"] - out["warp_mpkpe_rel_mm"]
    return out


def format_gap(result, warp: WarpEval | None, gap) -> str:
    s = result.summary
    if warp is None:
        return ("gap to MuJoCo-Warp: no evaluation of this checkpoint in the run folder "
                "(run python -m bmimic.eval RUN to get one)")
    lines = [f"gap to MuJoCo-Warp ({warp.source}); success = 1 - failures / visits per bin, "
             f"failures charged where they happen:",
             f"  success rate   warp {warp.success_rate:.3f}  sim2sim {s['eval_success_rate']:.3f}  "
             f"gap {s['eval_success_rate'] - warp.success_rate:+.3f}",
             f"  rel MPKPE mm   warp {warp.mpkpe_rel_mm:.1f}  sim2sim {s['eval_mpkpe_rel_mm']:.1f}  "
             f"gap {s['eval_mpkpe_rel_mm'] - warp.mpkpe_rel_mm:+.1f}"]
    if s["gap_setting_differences"]:
        lines.append("  note: not like with like, the evaluations differ in " + "; ".join(s["gap_setting_differences"]))
    shown = gap
    title = "per bin:"
    if len(gap) > 30:
        shown = gap.reindex(gap["success_gap"].abs().sort_values(ascending=False).index).head(10)
        title = f"the 10 bins of {len(gap)} with the largest success gap:"
    cols = ["bin", "segment", "warp_visits", "sim2sim_visits", "warp_success_rate", "sim2sim_success_rate",
            "success_gap", "warp_mpkpe_rel_mm", "sim2sim_mpkpe_rel_mm", "mpkpe_rel_gap_mm"]
    lines += [title, shown[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}")]
    return "\n".join(lines)


# ============================================================================================ evaluation
def collect(episodes: Sequence[Episode], start_bins: np.ndarray, num_frames: int):
    """bmimic.training.evaluation.Rollouts of sim2sim episodes: the rows with their start `bin` first,
    and per motion frame the steps judged at it and their error sums."""
    import pandas as pd

    from bmimic.training.evaluation import ERROR_COLUMNS, Rollouts

    rows = pd.DataFrame([e.row for e in episodes])
    rows.insert(0, "bin", np.asarray(start_bins, dtype=np.int64))
    sums = np.zeros((num_frames, 1 + len(ERROR_COLUMNS)))
    for e in episodes:
        np.add.at(sums, e.frames, np.column_stack((np.ones(len(e.frames)), e.errors)))
    return Rollouts(rows, pd.DataFrame(sums, columns=["steps", *ERROR_COLUMNS]))


def evaluate(policy_path: Path, run_dir: Path | None, model: str = "project", episodes_per_bin: int | None = None,
             horizon_s: float | None = None, workers: int = 1, joint_dynamics: str = "model",
             max_mpkpe_rel_mm: float | None = None):
    """Run the sim2sim evaluation; returns (bmimic.eval.EvalResult, WarpEval or None, gap table or None).

    Settings not given are the MuJoCo-Warp evaluation's (eval_settings), so the gap compares like with like."""
    from bmimic.eval import EvalResult, bin_table, episode_table, segment_table
    from bmimic.sampling.bins import make_layout
    from bmimic.training.evaluation import stratified_start_frames, summarize

    spec = read_policy(policy_path)
    label = checkpoint_label(spec)
    warp = warp_eval(run_dir, label, spec.iteration)
    settings = eval_settings(run_dir, warp, episodes_per_bin, horizon_s, max_mpkpe_rel_mm)
    per_bin = settings["episodes_per_bin"]
    ref = read_reference(policy_session(policy_path), spec)
    mjm, model_note = build_model(spec, model, run_dir, joint_dynamics)
    layout = make_layout(spec.bin_layout, spec.num_frames, spec.fps, spec.bin_size_s)
    frames = stratified_start_frames(layout.bin_first_frame.numpy(), layout.bin_num_frames.numpy(), per_bin)
    horizon_steps = max(1, int(round(settings["horizon_s"] / spec.control_dt_s)))
    log.info("sim2sim %s on %s: %d bins x %d episodes, horizon %g s, %d workers", policy_path.name, model_note,
             layout.num_bins, per_bin, settings["horizon_s"], workers)
    runs, wall = run_episodes(policy_path, mjm, spec, ref, frames, horizon_steps, workers, settings["max_mpkpe_rel_mm"])
    rollouts = collect(runs, np.repeat(np.arange(layout.num_bins), per_bin), spec.num_frames)

    raw = rollouts.episodes
    iteration = -1 if spec.iteration is None else spec.iteration
    episodes = episode_table(raw, layout, ref, spec.control_dt_s, iteration)
    episodes["end_s"] = episodes["end_frame"] / spec.fps
    episodes["end_bin"] = layout.frame_to_bin.numpy()[episodes["end_frame"].to_numpy()]
    episodes["diverged"] = raw["diverged"].to_numpy()
    bins = bin_table(rollouts, episodes, layout, ref.segments)
    steps = int(raw["steps"].sum())
    worker_s = float(raw["wall_s"].sum())
    summary = {
        **summarize(bins),
        "episodes": int(len(episodes)),
        "failures": int(episodes["failed"].sum()),
        "diverged": int(episodes["diverged"].sum()),
        "num_bins": int(layout.num_bins),
        **settings,
        "horizon_truncated_bins": int(bins["horizon_truncated"].sum()),
        "checkpoint": str(policy_path),
        "iteration": iteration,
        "run_dir": str(run_dir) if run_dir else "",
        "label": label,
        "device": f"cpu, native MuJoCo, {workers} worker process(es)",
        "simulator": "mujoco (C) " + _version("mujoco") + ", onnxruntime " + _version("onnxruntime"),
        "model": model,
        "model_description": model_note,
        "joint_dynamics": joint_dynamics,
        "workers": int(workers),
        "control_steps": steps,
        "physics_steps": steps * spec.decimation,
        "eval_wall_time_s": wall,
        "control_steps_per_s": steps / wall if wall > 0 else math.nan,
        "control_steps_per_s_per_worker": steps / worker_s if worker_s > 0 else math.nan,
    }
    gap = None
    if warp is not None:
        gap = gap_table(bins, warp)
        summary.update(warp_source=warp.source, warp_success_rate=warp.success_rate,
                       warp_mpkpe_rel_mm=warp.mpkpe_rel_mm,
                       gap_success_rate=summary["eval_success_rate"] - warp.success_rate,
                       gap_mpkpe_rel_mm=summary["eval_mpkpe_rel_mm"] - warp.mpkpe_rel_mm,
                       gap_setting_differences=setting_differences(settings, warp))
    result = EvalResult(episodes, bins, segment_table(rollouts, episodes, ref), summary)
    return result, warp, gap


def _version(module: str) -> str:
    try:
        return str(__import__(module).__version__)
    except (ImportError, AttributeError):
        return "?"


# ============================================================================================ video
def render_video(policy_path: Path, run_dir: Path | None, model: str, joint_dynamics: str, out: Path,
                 start_s: float, duration_s: float, width: int = 640, height: int = 480) -> Path:
    """One episode from `start_s`, with the reference as a ghost, at the control rate (MP4 or GIF)."""
    from bmimic.render import TrackingRenderer, annotate, write_video

    spec = read_policy(policy_path)
    session = policy_session(policy_path)
    ref = read_reference(session, spec)
    mjm, _ = build_model(spec, model, run_dir, joint_dynamics)
    rollout = Rollout(mjm, spec, ref, session)
    renderer = TrackingRenderer(mjm, width, height)
    frames: list[np.ndarray] = []

    def draw(r: Rollout, terminated: bool) -> None:
        renderer.renderer.update_scene(r.d, camera=renderer.camera, scene_option=renderer.option)
        renderer._add_ghost(r.reference_qpos(r.frame))  # the renderer's ghost of the reference pose
        text = [f"sim2sim {model_label(model)}  t={r.frame / spec.fps:5.2f} s"] + (["terminated"] if terminated else [])
        frames.append(annotate(renderer.renderer.render(), text, alert=terminated))

    start = min(max(0, int(round(start_s * spec.fps))), spec.num_frames - 1)
    try:
        run_episode(rollout, start, max(1, int(round(duration_s / spec.control_dt_s))), on_step=draw)
    finally:
        renderer.close()
    return write_video(frames, out, 1.0 / spec.control_dt_s)


# ============================================================================================ CLI
def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bmimic.sim2sim",
        description="Evaluate the exported (BeyondMimic-compatible) ONNX policy in native MuJoCo on the CPU.",
        epilog="Tables: RUN/sim2sim/<model>/<checkpoint>/{eval_episodes.parquet,eval_bins.parquet,"
               f"eval_segments.csv,eval_summary.json,{GAP_FILE}}}")
    p.add_argument("path", help="a run folder (its latest checkpoints/motion_policy_<it>.onnx) or such an ONNX file")
    p.add_argument("--model", default="project",
                   help="project (the run's G1), menagerie (MuJoCo Menagerie's G1) or an MJCF path")
    p.add_argument("--episodes-per-bin", type=int, help="default: as the run's MuJoCo-Warp evaluation")
    p.add_argument("--horizon-s", type=float, help="seconds an episode must survive (default: as the run's evaluation)")
    p.add_argument("--max-mpkpe-rel-mm", type=float,
                   help="also fail episodes whose mean root-relative MPKPE exceeds this (default: as the run's evaluation)")
    p.add_argument("--workers", type=int, default=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
                   else os.cpu_count() or 1, help="worker processes (default: the CPU cores available)")
    p.add_argument("--joint-dynamics", choices=("model", "metadata"), default="model",
                   help="keep the model's armature/damping/friction loss (default) or use training's")
    p.add_argument("--video", type=Path, help="also render one episode to this .mp4 (or .gif)")
    p.add_argument("--video-start-s", type=float, default=0.0, help="where the video episode starts in the motion")
    p.add_argument("--video-s", type=float, default=10.0, help="longest video episode in seconds")
    p.add_argument("--out", type=Path, help="folder for the tables (default RUN/sim2sim/<model>/<checkpoint>)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    try:
        if args.video is not None:
            from bmimic.render import select_gl_backend, video_path

            video_path(args.video)  # a bad suffix is refused before any work
            select_gl_backend()  # before mujoco is imported
        if args.workers < 1:
            raise Sim2SimError(f"--workers {args.workers}: need at least 1")
        policy_path, run_dir = locate(args.path)
        result, warp, gap = evaluate(policy_path, run_dir, args.model, args.episodes_per_bin, args.horizon_s,
                                     args.workers, args.joint_dynamics, args.max_mpkpe_rel_mm)
        out = args.out or (run_dir or policy_path.parent) / "sim2sim" / model_label(args.model) / result.summary["label"]
        _write(result, gap, out.resolve())
        video = None
        if args.video is not None:
            video = render_video(policy_path, run_dir, args.model, args.joint_dynamics, args.video,
                                 args.video_start_s, args.video_s)
    except _user_errors() as e:
        print(f"error: {_first_line(e)}", file=sys.stderr)
        return 2
    from bmimic.eval import format_report

    s = result.summary
    print(format_report(result))
    print(f"model: {s['model_description']}")
    print(f"throughput: {s['control_steps']} control steps ({s['physics_steps']} physics steps) in "
          f"{s['eval_wall_time_s']:.1f} s on {s['workers']} worker process(es): {s['control_steps_per_s']:.0f} control steps/s "
          f"({s['control_steps_per_s_per_worker']:.0f} per worker)")
    print(format_gap(result, warp, gap))
    if video is not None:
        print(f"video: {video}")
    return 0


def _write(result, gap, out_dir: Path) -> None:
    from bmimic.eval import write_tables
    from bmimic.runs import atomic_write

    out_dir.mkdir(parents=True, exist_ok=True)
    if gap is not None:
        atomic_write(out_dir / GAP_FILE, lambda tmp: gap.to_csv(tmp, index=False))
    write_tables(result, out_dir)  # the summary last: its presence means a complete set


def _user_errors() -> tuple[type[BaseException], ...]:
    from bmimic.motion.motion import MotionDataError

    return (BmimicError, MotionDataError)


if __name__ == "__main__":
    # Run through the importable module, so worker processes unpickle the same classes.
    from bmimic.sim2sim import main as _main

    sys.exit(_main())
