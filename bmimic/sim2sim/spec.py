"""Reading a BeyondMimic-compatible ONNX: its metadata as a PolicySpec, its session and its baked-in motion.

Everything sim2sim's control loop needs comes from here (never from bmimic's training code): numpy,
onnxruntime and torch-free bmimic helpers only.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from bmimic import BmimicError
from bmimic.runs import safe_read
from bmimic.runs.schema import ITERATION, ONNX_METADATA_VERSION

if TYPE_CHECKING:
    from bmimic.motion.motion import Motion

REFERENCE_OUTPUTS = ("joint_pos", "joint_vel", "body_pos_w", "body_quat_w", "body_lin_vel_w", "body_ang_vel_w")
"""Reference outputs of a BeyondMimic-compatible ONNX, after `actions` (the released exporter's order)."""


class Sim2SimError(BmimicError):
    """A policy file, model or run folder that sim2sim cannot use (one-line message)."""


def first_line(e: BaseException) -> str:
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


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
    clip_names: list[str]
    """Name of each clip (files exported before the names were recorded: clip0, clip1, ...)."""
    segments: list
    """Labelled time ranges of the motion (bmimic.motion.Segment)."""
    bin_layout: str
    """Kind of the run's bins: "time" (bin_size_s wide) or "released" (BeyondMimic's layout)."""
    bin_size_s: float
    """Time-bin width of the run's sampler and evaluation (the mean bin length for the released layout)."""
    max_abs_qvel: float
    """|qvel| beyond which a world is broken (training's sim.max_abs_qvel)."""
    max_root_distance_m: float
    """Root distance from the origin beyond which a world is broken (sim.max_root_distance_m)."""
    iteration: int | None
    """Training iteration of the checkpoint, when recorded."""


def policy_error(path: Path, what: str) -> Sim2SimError:
    return Sim2SimError(f"{path}: {what}")


def regular_policy(path: Path) -> Path:
    """`path` once it is a regular file (safe_read.regular_file: onnxruntime would block on a FIFO or read
    a device forever); Sim2SimError (one line) otherwise."""
    try:
        return safe_read.regular_file(path)
    except FileNotFoundError:
        raise policy_error(path, "no such file") from None
    except OSError as e:
        raise policy_error(path, f"cannot be opened ({e.strerror or e})") from None
    except safe_read.UnsafeFileError as e:
        raise Sim2SimError(str(e)) from None


def read_metadata(path: Path) -> tuple[dict[str, str], list[str], list[str]]:
    """(metadata, input names, output names) of an ONNX file."""
    import onnxruntime as ort

    regular_policy(path)
    try:
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types for unreadable files
        raise policy_error(path, f"not a readable ONNX file: {first_line(e)}") from None
    meta = dict(session.get_modelmeta().custom_metadata_map)
    return meta, [i.name for i in session.get_inputs()], [o.name for o in session.get_outputs()]


def read_policy(path: str | Path) -> PolicySpec:
    """Parse and check the metadata of a BeyondMimic-compatible ONNX; raises Sim2SimError."""
    from bmimic.motion.motion import segments_from_json

    path = Path(path)
    meta, inputs, outputs = read_metadata(path)
    if inputs != ["obs", "time_step"] or outputs[1:] != list(REFERENCE_OUTPUTS):
        raise policy_error(path, f"inputs {inputs}, outputs {outputs}: not a BeyondMimic-compatible policy "
                                  "(obs, time_step -> actions + reference); use motion_policy_<it>.onnx")

    def get(key: str) -> str:
        if key not in meta:
            raise policy_error(path, f"metadata has no {key!r}; write the file again with python -m bmimic.export RUN")
        return meta[key]

    version = meta.get("bmimic_metadata_version")
    if version is not None and version != ONNX_METADATA_VERSION:  # another key set: its keys may mean otherwise
        raise policy_error(path, f"metadata version {version[:20]!r}, where this bmimic reads version "
                                 f"{ONNX_METADATA_VERSION}; write the file again with python -m bmimic.export RUN")

    def names(key: str) -> list[str]:
        return [x for x in get(key).split(",") if x]

    def numbers(key: str, n: int, positive: bool = False) -> np.ndarray:
        try:
            x = np.array([float(v) for v in get(key).split(",")], dtype=np.float64)
        except ValueError:
            raise policy_error(path, f"metadata {key!r} is not a comma-separated list of numbers") from None
        if x.shape != (n,) or not np.isfinite(x).all() or (positive and (x <= 0).any()):
            need = "positive " if positive else ""
            raise policy_error(path, f"metadata {key!r} must hold {n} finite {need}numbers, got {get(key)[:80]!r}")
        return x

    def scalar(key: str, kind=float):
        try:
            value = kind(get(key))
        except ValueError:
            raise policy_error(path, f"metadata {key!r}={get(key)!r} is not a {kind.__name__}") from None
        if not (math.isfinite(value) and value > 0):
            raise policy_error(path, f"metadata {key!r}={get(key)!r} must be > 0")
        return value

    def json_list(key: str) -> list[dict]:
        try:
            items = safe_read.parse_json(get(key), key)
        except ValueError:
            raise policy_error(path, f"metadata {key!r} is not JSON") from None
        if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
            raise policy_error(path, f"metadata {key!r} must be a JSON list of objects")
        return items

    def segments() -> list:
        try:
            return segments_from_json(get("motion_segments"))
        except ValueError as e:  # bad JSON or a malformed entry
            raise policy_error(path, f"metadata 'motion_segments': {first_line(e)}") from None

    joints = names("joint_names")
    nj = len(joints)
    body_names = names("body_names")
    layout = json_list("observation_layout")
    try:
        terms = [ObsTerm(str(t["name"]), str(t["func"]), int(t["dim"])) for t in layout]
        terminations = [(str(t["name"]), str(t["func"]), dict(t.get("params") or {})) for t in json_list("terminations")]
    except (KeyError, TypeError, ValueError):
        raise policy_error(path, "metadata observation_layout/terminations entries need name, func (and dim)") from None
    with_params = [t["name"] for t in layout if t.get("params")]
    if with_params:
        raise policy_error(path, f"observation terms {with_params} have parameters; sim2sim's numpy terms take none")
    if [t.name for t in terms] != names("observation_names"):
        raise policy_error(path, "metadata observation_layout does not list the observation_names in order")
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
        clip_names=[str(n) for n in json.loads(meta["motion_clip_names"])] if meta.get("motion_clip_names")
        else [f"clip{k}" for k in range(len(names("motion_clip_starts")))],
        segments=segments(),
        bin_layout=meta.get("bin_layout", "time"),  # files exported before the released layout existed
        bin_size_s=scalar("bin_size_s"),
        # files exported before these keys: training's defaults (bmimic.sim.config.SimConfig)
        max_abs_qvel=scalar("sim_max_abs_qvel") if "sim_max_abs_qvel" in meta else 1000.0,
        max_root_distance_m=scalar("sim_max_root_distance_m") if "sim_max_root_distance_m" in meta else 1000.0,
        iteration=int(meta[ITERATION]) if meta.get(ITERATION, "").lstrip("-").isdigit() else None,
    )
    _check_spec(spec)
    return spec


def _check_spec(spec: PolicySpec) -> None:
    """Consistency of the layout, bodies and periods (each failure names the key)."""
    path, nj, nb = spec.path, len(spec.joint_names), len(spec.body_names)
    for name in (spec.anchor_body, spec.root_body, *spec.end_effector_bodies):
        if name not in spec.body_names:
            raise policy_error(path, f"metadata body {name!r} (anchor/root/end effector) is not in body_names")
    for term in spec.obs_terms:
        if term.func not in OBS_DIMS:
            raise policy_error(path, f"observation term {term.name!r}: function {term.func!r} has no numpy version "
                                      f"in bmimic.sim2sim (known: {sorted(OBS_DIMS)})")
        expected = OBS_DIMS[term.func](nj, nb)
        if term.dim != expected:
            raise policy_error(path, f"observation term {term.name!r} ({term.func}) has size {term.dim}, "
                                      f"expected {expected} for {nj} joints and {nb} bodies")
    if sum(t.dim for t in spec.obs_terms) != spec.obs_dim:
        raise policy_error(path, f"observation_layout sizes add up to {sum(t.dim for t in spec.obs_terms)}, "
                                  f"not policy_obs_dim={spec.obs_dim}")
    for name, func, params in spec.terminations:
        if func not in TERMINATIONS:
            raise policy_error(path, f"termination {name!r}: function {func!r} has no numpy version in "
                                      f"bmimic.sim2sim (known: {sorted(TERMINATIONS)})")
        if set(params) != {TERMINATIONS[func]} or not all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0
                for v in params.values()):
            raise policy_error(path, f"termination {name!r} ({func}): params {params} must be "
                                      f"{{{TERMINATIONS[func]!r}: a finite threshold > 0}}")
    if not math.isclose(spec.physics_dt_s * spec.decimation, spec.control_dt_s, rel_tol=1e-6):
        raise policy_error(path, f"physics_dt_s x decimation = {spec.physics_dt_s * spec.decimation:g} s, "
                                  f"but control_dt_s = {spec.control_dt_s:g} s")
    if not math.isclose(spec.fps * spec.control_dt_s, 1.0, rel_tol=1e-6):
        raise policy_error(path, f"metadata motion_fps={spec.fps:g} is not the control rate "
                                  f"1 / control_dt_s = {1.0 / spec.control_dt_s:g} Hz (one reference frame per "
                                  "control step): the bins and horizon would be counted in the wrong frames")
    if len(spec.clip_names) != len(spec.clip_starts) or len(set(spec.clip_names)) != len(spec.clip_names):
        raise policy_error(path, f"metadata motion_clip_names ({len(spec.clip_names)} names) must name each of the "
                                  f"{len(spec.clip_starts)} clips of motion_clip_starts once")
    frame_bytes = 4 * (2 * nj + 13 * nb)  # the baked reference: float32 joints and body poses/velocities
    if spec.num_frames * frame_bytes > path.stat().st_size:
        raise policy_error(path, f"metadata motion_num_frames={spec.num_frames} cannot be right: that many frames "
                                  f"of the baked motion need {spec.num_frames * frame_bytes / 2**20:.0f} MiB, the "
                                  f"file has {path.stat().st_size / 2**20:.1f} MiB")




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
    return ort.InferenceSession(str(regular_policy(path)), options, providers=["CPUExecutionProvider"])


def clip_frames(spec: PolicySpec, k: int) -> range:
    """The frames of clip `k` of the baked motion."""
    ends = [*spec.clip_starts[1:].tolist(), spec.num_frames]
    return range(int(spec.clip_starts[k]), int(ends[k]))


def clip_indices(spec: PolicySpec, names: Sequence[str] | None) -> list[int]:
    """The clips called `names` (None: every clip), in the motion's order; Sim2SimError (one line) for a
    name the file does not hold."""
    if names is None:
        return list(range(len(spec.clip_names)))
    unknown = [n for n in names if n not in spec.clip_names]
    if unknown or not names:
        shown = ", ".join(spec.clip_names[:8]) + (", ..." if len(spec.clip_names) > 8 else "")
        raise policy_error(spec.path, f"--clip {','.join(names)}: {'no clip ' + repr(unknown[0]) if unknown else 'no name'}"
                                      f" in its motion ({len(spec.clip_names)} clips: {shown})")
    return sorted({spec.clip_names.index(n) for n in names})


def read_reference(session, spec: PolicySpec, clips: Sequence[int] | None = None) -> Motion:
    """The motion baked into the file (tracked bodies only), read by evaluating its reference outputs at
    every time step 0..T-1, as a deployment controller plays it. `clips`: read only those clips' frames
    (a library of hours takes minutes to read whole); the others hold the first frame read, and nothing
    may start or run there (an episode stops at its clip's end)."""
    from bmimic.motion.motion import Motion, MotionDataError

    obs = np.zeros((1, spec.obs_dim), dtype=np.float32)
    frames = [t for k in (range(len(spec.clip_starts)) if clips is None else clips) for t in clip_frames(spec, k)]
    out: dict[str, np.ndarray] = {}
    for t in frames:
        values = session.run(list(REFERENCE_OUTPUTS), {"obs": obs, "time_step": np.array([[t]], dtype=np.float32)})
        for name, v in zip(REFERENCE_OUTPUTS, values):
            if name not in out:  # filled with the first frame read, each frame then with its own
                out[name] = np.repeat(v, spec.num_frames, axis=0)
            out[name][t] = v[0]
    try:
        return Motion(fps=spec.fps, **out, joint_names=spec.joint_names,
                      body_names=spec.body_names, segments=spec.segments, clip_starts=spec.clip_starts)
    except MotionDataError as e:
        raise policy_error(spec.path, f"the baked-in motion does not fit the metadata: {e}") from None


