"""The reference motion container: arrays, npz I/O, name-based mapping to a model, windows and libraries.

A `Motion` holds numpy arrays at the control rate (50 Hz), in the robot model's joint and body order:

    joint_pos, joint_vel        [T, J]      rad, rad/s          (hinge joints, MuJoCo order)
    body_pos_w                  [T, B, 3]   m, world frame      (body origins = MuJoCo xpos)
    body_quat_w                 [T, B, 4]   w, x, y, z          (MuJoCo xquat)
    body_lin_vel_w              [T, B, 3]   m/s, world frame, velocity of the body *origin* (not its COM)
    body_ang_vel_w              [T, B, 3]   rad/s, world frame

On disk it is BeyondMimic's npz (keys above plus `fps`) with this project's extra keys `joint_names`,
`body_names` (string arrays), `segments` (JSON string) and `clip_starts` (int array). Data are mapped
to a model by name, never by position: the same robot exported by Isaac Lab orders its bodies
breadth-first and has 40 of them, so positional mapping silently tracks the wrong bodies.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from pathlib import Path
from typing import NamedTuple, Sequence

import mujoco
import numpy as np

from bmimic import BmimicError
from bmimic.motion.math import angular_velocity_from_quats, quat_normalize, quat_rotate_inverse, quat_slerp

NPZ_ARRAY_KEYS = (
    "joint_pos",
    "joint_vel",
    "body_pos_w",
    "body_quat_w",
    "body_lin_vel_w",
    "body_ang_vel_w",
)


MAX_DISTANCE_M = 1000.0
"""Bodies farther than this from the origin are refused: float32 (the simulator's and the
reference's precision) moves a body by ~6 cm at 1e6 m and by ~0.1 mm already at 1 km."""


class MotionDataError(BmimicError, ValueError):
    """Bad motion data or a motion that does not fit the robot model; the message is one line."""


class Segment(NamedTuple):
    """A labelled time range of a motion (used to name time bins in the analysis)."""

    name: str
    start_s: float
    end_s: float
    difficulty: str


def segments_to_json(segments: Sequence[Segment]) -> str:
    return json.dumps([s._asdict() for s in segments])


def segments_from_json(text: str) -> list[Segment]:
    try:
        items = json.loads(text)
    except ValueError as err:
        raise MotionDataError(f"segments is not valid JSON ({err})") from None
    if not isinstance(items, list):
        raise MotionDataError("segments must be a JSON list of {name, start_s, end_s, difficulty}")
    out = []
    for k, i in enumerate(items):
        try:
            seg = Segment(str(i["name"]), float(i["start_s"]), float(i["end_s"]), str(i["difficulty"]))
        except (KeyError, TypeError, ValueError) as err:
            raise MotionDataError(f"segments entry {k} is malformed ({err!r}); expected "
                                  "{name, start_s, end_s, difficulty}") from None
        out.append(seg)
    return out


# ---------------------------------------------------------------------------------------------------
# Model names


def model_joint_names(mjmodel: mujoco.MjModel) -> list[str]:
    """Names of the model's hinge and slide joints in MuJoCo order (the free joint is left out)."""
    free = mujoco.mjtJoint.mjJNT_FREE
    return [mjmodel.joint(j).name for j in range(mjmodel.njnt) if mjmodel.jnt_type[j] != free]


def model_body_names(mjmodel: mujoco.MjModel) -> list[str]:
    """Names of the model's bodies in MuJoCo order without the world body."""
    return [mjmodel.body(b).name for b in range(1, mjmodel.nbody)]


def free_joint_qposadr(mjmodel: mujoco.MjModel) -> tuple[int, int]:
    """qpos and qvel addresses of the robot's floating-base (free) joint."""
    for j in range(mjmodel.njnt):
        if mjmodel.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
            return int(mjmodel.jnt_qposadr[j]), int(mjmodel.jnt_dofadr[j])
    raise MotionDataError("the robot model has no free joint; motions need a floating base")


def joint_addresses(mjmodel: mujoco.MjModel, joint_names: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    """qpos and qvel addresses of the named joints (raises if a name is not in the model)."""
    qpos_adr, dof_adr = [], []
    for name in joint_names:
        jid = mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid < 0:
            raise MotionDataError(f"joint '{name}' is not in the robot model")
        qpos_adr.append(mjmodel.jnt_qposadr[jid])
        dof_adr.append(mjmodel.jnt_dofadr[jid])
    return np.asarray(qpos_adr, dtype=np.int64), np.asarray(dof_adr, dtype=np.int64)


def find_joint_limit_violation(
    joint_pos: np.ndarray, joint_names: Sequence[str], mjmodel: mujoco.MjModel, tolerance_rad: float = 0.1
) -> tuple[int, int, float, float, float] | None:
    """First (frame, joint index, value, low, high) where a limited joint leaves its range by more than
    `tolerance_rad`, or None."""
    low = np.full(len(joint_names), -np.inf)
    high = np.full(len(joint_names), np.inf)
    for k, name in enumerate(joint_names):
        jid = mujoco.mj_name2id(mjmodel, mujoco.mjtObj.mjOBJ_JOINT, name)
        if jid >= 0 and mjmodel.jnt_limited[jid]:
            low[k], high[k] = mjmodel.jnt_range[jid]
    bad = (joint_pos < low - tolerance_rad) | (joint_pos > high + tolerance_rad)
    if not bad.any():
        return None
    frame, joint = np.argwhere(bad)[0]
    return int(frame), int(joint), float(joint_pos[frame, joint]), float(low[joint]), float(high[joint])


# ---------------------------------------------------------------------------------------------------
# The container


@dataclasses.dataclass
class Motion:
    """A reference motion in model order at `fps` frames per second (see the module docstring)."""

    fps: float
    joint_pos: np.ndarray
    joint_vel: np.ndarray
    body_pos_w: np.ndarray
    body_quat_w: np.ndarray
    body_lin_vel_w: np.ndarray
    body_ang_vel_w: np.ndarray
    joint_names: list[str]
    body_names: list[str]
    segments: list[Segment] = dataclasses.field(default_factory=list)
    clip_starts: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(1, dtype=np.int64))

    def __post_init__(self) -> None:
        self.fps = float(self.fps)
        for key in NPZ_ARRAY_KEYS:
            setattr(self, key, np.asarray(getattr(self, key), dtype=np.float32))
        self.joint_names = [str(n) for n in self.joint_names]
        self.body_names = [str(n) for n in self.body_names]
        self.segments = [Segment(str(n), float(a), float(b), str(d)) for n, a, b, d in self.segments]
        self.clip_starts = np.asarray(self.clip_starts, dtype=np.int64).reshape(-1)
        self._validate()

    def _validate(self) -> None:
        if not np.isfinite(self.fps) or self.fps <= 0:
            raise MotionDataError(f"fps must be a positive number, got {self.fps}")
        num, nj, nb = self.num_frames, len(self.joint_names), len(self.body_names)
        expected = {
            "joint_pos": (num, nj),
            "joint_vel": (num, nj),
            "body_pos_w": (num, nb, 3),
            "body_quat_w": (num, nb, 4),
            "body_lin_vel_w": (num, nb, 3),
            "body_ang_vel_w": (num, nb, 3),
        }
        for key, shape in expected.items():
            if getattr(self, key).shape != shape:
                raise MotionDataError(
                    f"{key} has shape {getattr(self, key).shape}, expected {shape} "
                    f"({num} frames, {nj} joint names, {nb} body names)"
                )
            arr = getattr(self, key)
            if not np.isfinite(arr).all():
                frame = int(np.argwhere(~np.isfinite(arr))[0][0])
                raise MotionDataError(f"{key} is not finite at frame {frame}")
        if num < 1:
            raise MotionDataError("motion has no frames")
        dist = np.linalg.norm(self.body_pos_w, axis=-1)
        if dist.size and dist.max() > MAX_DISTANCE_M:
            frame, body = np.unravel_index(int(np.argmax(dist)), dist.shape)
            raise MotionDataError(
                f"body '{self.body_names[body]}' at frame {frame} is {dist[frame, body]:.4g} m from the origin, "
                f"beyond {MAX_DISTANCE_M:g} m (float32 positions lose precision there); shift the motion "
                "towards the origin")
        if len(set(self.joint_names)) != nj or len(set(self.body_names)) != nb:
            raise MotionDataError("joint_names / body_names contain duplicates")
        starts = self.clip_starts
        if starts.size == 0 or starts[0] != 0 or np.any(np.diff(starts) <= 0) or starts[-1] >= num:
            raise MotionDataError(f"clip_starts must start at 0 and increase within [0, {num}), got {starts}")
        duration = num / self.fps
        for seg in self.segments:
            if not (math.isfinite(seg.start_s) and math.isfinite(seg.end_s)
                    and 0.0 <= seg.start_s < seg.end_s <= duration + 1e-6):
                raise MotionDataError(
                    f"segment {seg.name!r} spans [{seg.start_s}, {seg.end_s}] s, not a range within the "
                    f"motion's [0, {duration:.3f}] s")

    # -- sizes -------------------------------------------------------------------------------------
    @property
    def num_frames(self) -> int:
        return int(self.joint_pos.shape[0])

    @property
    def duration_s(self) -> float:
        return self.num_frames / self.fps

    @property
    def num_clips(self) -> int:
        return int(self.clip_starts.size)

    # -- reordering, windows, libraries ------------------------------------------------------------
    def to_model_order(self, mjmodel: mujoco.MjModel) -> Motion:
        """Reorder joints and bodies by name into the model's order; extra entries are dropped."""
        model_joints, model_bodies = model_joint_names(mjmodel), model_body_names(mjmodel)
        missing_j = [n for n in model_joints if n not in self.joint_names]
        missing_b = [n for n in model_bodies if n not in self.body_names]
        if missing_j or missing_b:
            raise MotionDataError(
                "motion does not cover the robot model: missing joints "
                f"{missing_j or 'none'}, missing bodies {missing_b or 'none'}"
            )
        ji = [self.joint_names.index(n) for n in model_joints]
        bi = [self.body_names.index(n) for n in model_bodies]
        return dataclasses.replace(
            self,
            joint_pos=self.joint_pos[:, ji],
            joint_vel=self.joint_vel[:, ji],
            body_pos_w=self.body_pos_w[:, bi],
            body_quat_w=self.body_quat_w[:, bi],
            body_lin_vel_w=self.body_lin_vel_w[:, bi],
            body_ang_vel_w=self.body_ang_vel_w[:, bi],
            joint_names=model_joints,
            body_names=model_bodies,
        )

    def window(self, start_s: float | None = None, end_s: float | None = None) -> Motion:
        """Frames in [start_s, end_s) (rounded to frames); segments are clipped and shifted to start at 0."""
        start_s = 0.0 if start_s is None else float(start_s)
        end_s = self.duration_s if end_s is None else float(end_s)
        first = int(round(start_s * self.fps))
        stop = int(round(end_s * self.fps))
        if first < 0 or stop > self.num_frames or stop - first < 2:
            raise MotionDataError(
                f"window [{start_s}, {end_s}] s is not inside the motion's [0, {self.duration_s:.3f}] s "
                "or is shorter than two frames"
            )
        t0, t1 = first / self.fps, stop / self.fps
        segments = []
        for seg in self.segments:
            s, e = max(seg.start_s, t0), min(seg.end_s, t1)
            if e - s > 1e-9:
                segments.append(Segment(seg.name, s - t0, e - t0, seg.difficulty))
        starts = [0] + [int(c) - first for c in self.clip_starts if first < c < stop]
        sl = slice(first, stop)
        return dataclasses.replace(
            self,
            joint_pos=self.joint_pos[sl],
            joint_vel=self.joint_vel[sl],
            body_pos_w=self.body_pos_w[sl],
            body_quat_w=self.body_quat_w[sl],
            body_lin_vel_w=self.body_lin_vel_w[sl],
            body_ang_vel_w=self.body_ang_vel_w[sl],
            segments=segments,
            clip_starts=np.asarray(starts, dtype=np.int64),
        )

    @staticmethod
    def concatenate(motions: Sequence[Motion]) -> Motion:
        """One library of several clips, back to back in time; `clip_starts` marks where each begins.

        Bins and segments index the library's common time axis; clip boundaries are where a tracked
        episode must not run on from one clip into the next.
        """
        if not motions:
            raise MotionDataError("cannot concatenate an empty list of motions")
        first = motions[0]
        for m in motions[1:]:
            if m.fps != first.fps or m.joint_names != first.joint_names or m.body_names != first.body_names:
                raise MotionDataError("motions to concatenate must share fps, joint names and body names")
        segments, starts, offset = [], [], 0
        for m in motions:
            t0 = offset / first.fps
            segments += [Segment(s.name, s.start_s + t0, s.end_s + t0, s.difficulty) for s in m.segments]
            starts += [int(c) + offset for c in m.clip_starts]
            offset += m.num_frames
        cat = {key: np.concatenate([getattr(m, key) for m in motions]) for key in NPZ_ARRAY_KEYS}
        return Motion(
            fps=first.fps,
            joint_names=first.joint_names,
            body_names=first.body_names,
            segments=segments,
            clip_starts=np.asarray(starts, dtype=np.int64),
            **cat,
        )

    def resample(self, fps: float) -> Motion:
        """The motion at `fps` frames per second (times 0, 1/fps, ... before the last frame's time):
        positions, velocities and joints interpolated linearly, orientations by slerp. Segments keep
        their times. Motions of several clips are refused (a frame between clips would blend two)."""
        fps = float(fps)
        if not (math.isfinite(fps) and fps > 0):
            raise MotionDataError(f"cannot resample to {fps} fps")
        if abs(fps - self.fps) <= 1e-9 * fps:
            return self
        if self.num_clips > 1:
            raise MotionDataError(
                f"a motion of {self.num_clips} clips at {self.fps:g} fps cannot be resampled to {fps:g} Hz "
                "as one piece; convert its clips at that rate")
        from bmimic.motion.math import output_times

        times = output_times(self.num_frames, self.fps, fps)
        if len(times) < 2:
            raise MotionDataError(f"{self.num_frames} frames at {self.fps:g} fps give fewer than 2 at {fps:g} Hz")
        index = times * self.fps
        i0 = np.minimum(np.floor(index).astype(np.int64), self.num_frames - 2)
        blend = (index - i0).astype(np.float32)

        def lerp(a: np.ndarray) -> np.ndarray:
            w = blend.reshape(-1, *([1] * (a.ndim - 1)))
            return a[i0] + (a[i0 + 1] - a[i0]) * w

        duration = len(times) / fps
        segments = [Segment(s.name, s.start_s, min(s.end_s, duration), s.difficulty)
                    for s in self.segments if s.start_s < duration - 1e-9]
        return dataclasses.replace(
            self,
            fps=fps,
            joint_pos=lerp(self.joint_pos),
            joint_vel=lerp(self.joint_vel),
            body_pos_w=lerp(self.body_pos_w),
            body_quat_w=quat_slerp(self.body_quat_w[i0], self.body_quat_w[i0 + 1], blend[:, None]),
            body_lin_vel_w=lerp(self.body_lin_vel_w),
            body_ang_vel_w=lerp(self.body_ang_vel_w),
            segments=segments,
            clip_starts=np.zeros(1, dtype=np.int64),
        )

    # -- I/O ---------------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write the npz atomically (bmimic.run_folder.atomic_write); `path` must end in .npz."""
        from bmimic.run_folder import atomic_write

        path = Path(path)
        if path.suffix != ".npz":
            raise MotionDataError(f"{path}: a motion file must end in .npz")
        fps = int(self.fps) if float(self.fps).is_integer() else self.fps
        arrays = dict(
            fps=np.asarray([fps]),
            joint_names=np.asarray(self.joint_names, dtype=np.str_),
            body_names=np.asarray(self.body_names, dtype=np.str_),
            segments=np.asarray(segments_to_json(self.segments)),
            clip_starts=self.clip_starts,
            **{key: getattr(self, key) for key in NPZ_ARRAY_KEYS},
        )
        atomic_write(path, lambda tmp: np.savez(tmp, **arrays))

    @staticmethod
    def load(
        path: str | os.PathLike, mjmodel: mujoco.MjModel | None, assume_model_order: bool = False
    ) -> Motion:
        """Read an npz and, given a model, map it to the model's joint and body order by name.

        Files without `joint_names`/`body_names` are refused unless `assume_model_order=True` (and then
        their shapes must match the model), because their order cannot be checked.
        """
        path = Path(path)
        if not path.is_file():
            raise MotionDataError(f"{path}: file not found")
        try:
            with np.load(path, allow_pickle=False) as data:
                content = {key: data[key] for key in data.files}
        except Exception as err:  # noqa: BLE001 - any reader failure means "not an npz we can read"
            raise MotionDataError(f"{path}: not a readable npz file ({type(err).__name__}: {err})") from None
        try:
            motion = _motion_from_npz_content(content, path, mjmodel, assume_model_order)
            return motion if mjmodel is None else motion.to_model_order(mjmodel)
        except MotionDataError as err:
            raise MotionDataError(f"{path}: {err}") from None


def _motion_from_npz_content(
    content: dict[str, np.ndarray], path: Path, mjmodel: mujoco.MjModel | None, assume_model_order: bool
) -> Motion:
    missing = [k for k in ("fps", *NPZ_ARRAY_KEYS) if k not in content]
    if missing:
        raise MotionDataError(f"missing key(s) {missing}; expected a BeyondMimic motion npz")
    ndims = {"joint_pos": 2, "joint_vel": 2, "body_pos_w": 3, "body_quat_w": 3, "body_lin_vel_w": 3,
             "body_ang_vel_w": 3}
    for key in ("fps", "clip_starts", *NPZ_ARRAY_KEYS):
        if key not in content:
            continue
        arr = content[key]
        kinds = "iu" if key == "clip_starts" else "fiu"
        if arr.dtype.kind not in kinds:
            raise MotionDataError(f"{key} has dtype {arr.dtype}; expected {'integers' if kinds == 'iu' else 'numbers'}")
        if key in ndims and arr.ndim != ndims[key]:
            raise MotionDataError(f"{key} has {arr.ndim} dimensions (shape {arr.shape}); expected {ndims[key]}")
    for key in ("joint_names", "body_names", "segments"):
        if key in content and content[key].dtype.kind not in "US":
            raise MotionDataError(f"{key} has dtype {content[key].dtype}; expected strings")
    if "segments" in content and content["segments"].size != 1:
        raise MotionDataError(f"segments must be one JSON string, got an array of shape {content['segments'].shape}")
    num_joints = content["joint_pos"].shape[-1]
    num_bodies = content["body_pos_w"].shape[1] if content["body_pos_w"].ndim == 3 else -1
    has_names = "joint_names" in content and "body_names" in content
    if has_names:
        joint_names = [str(n) for n in content["joint_names"].reshape(-1)]
        body_names = [str(n) for n in content["body_names"].reshape(-1)]
    elif mjmodel is None:
        raise MotionDataError("has no joint_names/body_names and no model was given to assume an order")
    else:
        joint_names, body_names = model_joint_names(mjmodel), model_body_names(mjmodel)
        origin = (
            "; 40 bodies is Isaac Lab's breadth-first G1 order, which cannot be mapped by position"
            if num_bodies == 40
            else ""
        )
        if not assume_model_order:
            raise MotionDataError(
                f"has no joint_names/body_names, so its order cannot be checked ({num_joints} joints, "
                f"{num_bodies} bodies; the model has {len(joint_names)} joints, {len(body_names)} bodies"
                f"{origin}); if it was made from this MuJoCo model (e.g. by mjlab), pass "
                "assume_model_order=True (motion.assume_model_order=true)"
            )
        if (num_joints, num_bodies) != (len(joint_names), len(body_names)):
            raise MotionDataError(
                f"has no names and {num_joints} joints, {num_bodies} bodies, but the model has "
                f"{len(joint_names)} joints, {len(body_names)} bodies{origin}; refusing to map by position"
            )
    fps = np.asarray(content["fps"]).reshape(-1)
    if fps.size != 1:
        raise MotionDataError(f"fps must hold one number, got {fps.size}")
    num_frames = content["joint_pos"].shape[0]
    fps_value = float(fps[0])
    if "segments" in content:
        segments = segments_from_json(str(content["segments"].reshape(-1)[0]))
    else:
        segments = [Segment(path.stem, 0.0, num_frames / fps_value if fps_value > 0 else 0.0, "unknown")]
    clip_starts = content.get("clip_starts", np.zeros(1, dtype=np.int64))
    motion = Motion(
        fps=fps_value,
        joint_names=joint_names,
        body_names=body_names,
        segments=segments,
        clip_starts=clip_starts,
        **{key: content[key] for key in NPZ_ARRAY_KEYS},
    )
    norms = np.linalg.norm(motion.body_quat_w, axis=-1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        frame, body = np.argwhere(np.abs(norms - 1.0) > 1e-3)[0]
        raise MotionDataError(
            f"body_quat_w of '{body_names[body]}' at frame {frame} has norm {norms[frame, body]:.4f}, "
            "not unit (tolerance 1e-3)"
        )
    if mjmodel is not None:
        bad = find_joint_limit_violation(motion.joint_pos, joint_names, mjmodel)
        if bad is not None:
            frame, j, value, low, high = bad
            raise MotionDataError(
                f"frame {frame}: joint '{joint_names[j]}' = {value:.3f} rad is outside its range "
                f"[{low:.3f}, {high:.3f}] by more than 0.1 rad"
            )
    return motion


# ---------------------------------------------------------------------------------------------------
# Building a Motion from generalised coordinates (shared by the CSV converter and the built-in motions)


def kinematic_motion(
    mjmodel: mujoco.MjModel,
    fps: float,
    root_pos: np.ndarray,
    root_quat: np.ndarray,
    joint_pos: np.ndarray,
    joint_names: Sequence[str],
    segments: Sequence[Segment] = (),
) -> Motion:
    """Velocities by finite differences and body states by MuJoCo forward kinematics.

    root_pos [T, 3] m, root_quat [T, 4] (w, x, y, z), joint_pos [T, J] rad for the named joints; joints
    of the model not named stay at qpos0. Joint and root linear velocities are central differences
    (np.gradient, one-sided at the ends); the root angular velocity comes from quaternion differences
    (world frame). Body velocities are those of the body origins (xpos) in the world frame, from
    `cvel`: v_origin = v_com - w x (subtree_com[root] - xpos).
    """
    names = list(joint_names)
    model_joints = model_joint_names(mjmodel)
    if sorted(names) != sorted(model_joints):
        raise MotionDataError(
            f"joints {sorted(set(model_joints) ^ set(names))} are not both in the data and in the robot model"
        )
    dt = 1.0 / float(fps)
    num = root_pos.shape[0]
    if num < 2:
        raise MotionDataError(f"a motion needs at least two frames, got {num}")
    root_quat = quat_normalize(np.asarray(root_quat, dtype=np.float64))
    root_pos = np.asarray(root_pos, dtype=np.float64)
    joint_pos = np.asarray(joint_pos, dtype=np.float64)
    root_lin_vel = np.gradient(root_pos, dt, axis=0)
    root_ang_vel = angular_velocity_from_quats(root_quat, dt)
    joint_vel = np.gradient(joint_pos, dt, axis=0)

    free_q, free_v = free_joint_qposadr(mjmodel)
    qadr, vadr = joint_addresses(mjmodel, joint_names)
    qpos = np.tile(mjmodel.qpos0, (num, 1))
    qvel = np.zeros((num, mjmodel.nv))
    qpos[:, free_q : free_q + 3] = root_pos
    qpos[:, free_q + 3 : free_q + 7] = root_quat
    qpos[:, qadr] = joint_pos
    qvel[:, free_v : free_v + 3] = root_lin_vel
    # MuJoCo's free joint takes its angular velocity in the body frame.
    qvel[:, free_v + 3 : free_v + 6] = quat_rotate_inverse(root_quat, root_ang_vel)
    qvel[:, vadr] = joint_vel

    nb = mjmodel.nbody - 1
    xpos = np.empty((num, nb, 3))
    xquat = np.empty((num, nb, 4))
    cvel = np.empty((num, nb, 6))
    com = np.empty((num, nb, 3))
    root_ids = mjmodel.body_rootid[1:]
    data = mujoco.MjData(mjmodel)
    for t in range(num):
        data.qpos[:] = qpos[t]
        data.qvel[:] = qvel[t]
        mujoco.mj_kinematics(mjmodel, data)
        mujoco.mj_comPos(mjmodel, data)
        mujoco.mj_comVel(mjmodel, data)
        xpos[t] = data.xpos[1:]
        xquat[t] = data.xquat[1:]
        cvel[t] = data.cvel[1:]
        com[t] = data.subtree_com[root_ids]
    ang = cvel[..., :3]
    lin = cvel[..., 3:] - np.cross(ang, com - xpos)

    order = [names.index(n) for n in model_joints]
    return Motion(
        fps=fps,
        joint_pos=joint_pos[:, order],
        joint_vel=joint_vel[:, order],
        body_pos_w=xpos,
        body_quat_w=xquat,
        body_lin_vel_w=lin,
        body_ang_vel_w=ang,
        joint_names=[names[i] for i in order],
        body_names=model_body_names(mjmodel),
        segments=list(segments),
    )
