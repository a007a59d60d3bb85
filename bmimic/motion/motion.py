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
import math
import os
from pathlib import Path
from typing import Sequence

import mujoco
import numpy as np

from bmimic.motion.math import output_times, quat_slerp
from bmimic.motion.model import model_body_names, model_joint_names
from bmimic.motion.npz import NPZ_ARRAY_KEYS, check_physical, motion_fields, read_npz
from bmimic.motion.segments import MotionDataError, Segment, segments_from_json, segments_to_json

MAX_DISTANCE_M = 1000.0
"""Bodies farther than this from the origin are refused: float32 (the simulator's and the
reference's precision) moves a body by ~6 cm at 1e6 m and by ~0.1 mm already at 1 km."""


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
            source = np.asarray(getattr(self, key))
            with np.errstate(over="ignore"):  # a value beyond float32 becomes inf: refused here, by where it is
                array = source.astype(np.float32, copy=False)
            if source.dtype.kind == "f" and source.dtype.itemsize > 4:
                overflow = np.isinf(array) & np.isfinite(source)
                if overflow.any():
                    at = tuple(int(i) for i in np.argwhere(overflow)[0])
                    raise MotionDataError(f"{key} at frame {at[0]} is {float(source[at]):.3g}, beyond float32's "
                                          f"range (a motion is stored as float32)")
            setattr(self, key, array)
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
            frame, body = (int(i) for i in np.unravel_index(int(np.argmax(dist)), dist.shape))
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
        if self.joint_names == model_joints and self.body_names == model_bodies:
            return self  # already in order (every cached clip): no copy, no second validation
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
        inside = all(math.isfinite(t) and -1.0 <= t * self.fps <= self.num_frames + 1 for t in (start_s, end_s))
        first = int(round(start_s * self.fps)) if inside else -1  # (1e308 * fps overflows int())
        stop = int(round(end_s * self.fps)) if inside else -1
        if first < 0 or stop > self.num_frames or stop - first < 2:
            raise MotionDataError(
                f"window start_s={start_s:g}, end_s={end_s:g} is not inside the motion's [0, {self.duration_s:.3f}] s "
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
        if self.clip_starts.size > 1:
            raise MotionDataError(
                f"a motion of {self.clip_starts.size} clips at {self.fps:g} fps cannot be resampled to {fps:g} Hz "
                "as one piece; convert its clips at that rate")
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
        """Write the npz atomically (bmimic.runs.folder.atomic_write); `path` must end in .npz."""
        from bmimic.runs.folder import atomic_write

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
        content = read_npz(path)
        try:
            motion = Motion(**motion_fields(content, path, mjmodel, assume_model_order))
            check_physical(motion.body_quat_w, motion.joint_pos, motion.joint_names, motion.body_names, mjmodel)
            return motion if mjmodel is None else motion.to_model_order(mjmodel)
        except MotionDataError as err:
            raise MotionDataError(f"{path}: {err}") from None


__all__ = ["MAX_DISTANCE_M", "NPZ_ARRAY_KEYS", "Motion", "MotionDataError", "Segment", "segments_from_json",
           "segments_to_json"]
