"""The npz format of a motion (BeyondMimic's keys plus `joint_names`, `body_names`, `segments`,
`clip_starts`): reading a file's arrays into checked `Motion` fields. `Motion.load` and `Motion.save`
are the entry points."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from bmimic.motion.model import find_joint_limit_violation, model_body_names, model_joint_names
from bmimic.motion.segments import MotionDataError, Segment, segments_from_json

NPZ_ARRAY_KEYS = (
    "joint_pos",
    "joint_vel",
    "body_pos_w",
    "body_quat_w",
    "body_lin_vel_w",
    "body_ang_vel_w",
)


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """Every array of the npz at `path` (never unpickling); MotionDataError if it cannot be read."""
    if not path.is_file():
        raise MotionDataError(f"{path}: file not found")
    try:
        with np.load(path, allow_pickle=False) as data:
            return {key: data[key] for key in data.files}
    except Exception as err:  # noqa: BLE001 - any reader failure means "not an npz we can read"
        raise MotionDataError(f"{path}: not a readable npz file ({type(err).__name__}: {err})") from None


def motion_fields(
    content: dict[str, np.ndarray], path: Path, mjmodel: mujoco.MjModel | None, assume_model_order: bool
) -> dict[str, Any]:
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
    return dict(
        fps=fps_value,
        joint_names=joint_names,
        body_names=body_names,
        segments=segments,
        clip_starts=clip_starts,
        **{key: content[key] for key in NPZ_ARRAY_KEYS},
    )


def check_physical(body_quat_w: np.ndarray, joint_pos: np.ndarray, joint_names: list[str], body_names: list[str],
                   mjmodel: mujoco.MjModel | None) -> None:
    """Unit quaternions, and (given the model) joints within their ranges up to 0.1 rad."""
    norms = np.linalg.norm(body_quat_w, axis=-1)
    if np.any(np.abs(norms - 1.0) > 1e-3):
        frame, body = np.argwhere(np.abs(norms - 1.0) > 1e-3)[0]
        raise MotionDataError(
            f"body_quat_w of '{body_names[body]}' at frame {frame} has norm {norms[frame, body]:.4f}, "
            "not unit (tolerance 1e-3)"
        )
    if mjmodel is not None:
        bad = find_joint_limit_violation(joint_pos, joint_names, mjmodel)
        if bad is not None:
            frame, j, value, low, high = bad
            raise MotionDataError(
                f"frame {frame}: joint '{joint_names[j]}' = {value:.3f} rad is outside its range "
                f"[{low:.3f}, {high:.3f}] by more than 0.1 rad"
            )
