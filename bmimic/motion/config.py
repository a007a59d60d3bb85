"""Motion configuration (`conf/motion/*.yaml`, `data`) and `load_motion`, which turns it into a `Motion`.

LAFAN1 clips are named relative to one folder, `data.lafan_dir` (default: the environment variable
BMIMIC_LAFAN_DIR), by `lafan_clip_path`; a missing folder or clip is one line saying where to get it.

Generated and converted motions are cached as npz under `cache_dir`, keyed by everything they depend
on (source content or generator settings, the generator/converter version and the robot model's
kinematic figures), so a changed input or model never reuses a stale file.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any, List, Optional

import numpy as np

from bmimic.motion.segments import MotionDataError, Segment

if TYPE_CHECKING:  # the schema imports without mujoco (composing a config needs none); load_motion imports it
    import mujoco

    from bmimic.motion.motion import Motion

log = logging.getLogger(__name__)

CONVERTER_VERSION = "1"
"""Part of the CSV cache key; bump whenever conversion output changes."""
CONTROL_FPS = 50.0
"""The default control rate (sim.timestep_s 0.005 x sim.decimation 4); load_motion takes the actual one."""

LAFAN_ENV = "BMIMIC_LAFAN_DIR"
"""Environment variable that `data.lafan_dir` defaults to (conf/train.yaml)."""
LAFAN_SOURCE = ("folder g1/ of the LAFAN1 Retargeting Dataset, "
                "https://huggingface.co/datasets/unitreerobotics/LAFAN1_Retargeting_Dataset")
"""Where users get the LAFAN1 G1 clips (CC BY-NC-ND 4.0, not shipped with bmimic)."""


@dataclasses.dataclass
class DataConfig:
    """Where the user's motion datasets are (the `data` node of conf/train.yaml)."""

    lafan_dir: Optional[str] = None
    """Folder of the LAFAN1 G1 CSV clips (the dataset's g1/ folder); conf/train.yaml defaults it to
    $BMIMIC_LAFAN_DIR. The `lafan_*` motion options name clips in it."""


@dataclasses.dataclass
class MotionConfig:
    """Which reference motion to track and which part of it."""

    name: str = "default"
    """Label of this motion (run names, plots)."""
    source: str = "builtin"
    """"builtin" (generated in code, no data needed), "lafan" (the LAFAN1 G1 clip `clip` in
    data.lafan_dir), "file" (an npz or a LAFAN1 G1 CSV at `path`) or "library" (the clips of `clips`,
    `glob` and `folder`, bmimic.motion.library)."""
    clips: Optional[List[Any]] = None
    """Source "library": the clips, each a mapping with one of `path` (CSV/npz), `clip` (LAFAN1 name) or
    `builtin` (with `seed`, `duration_s`), and optional `start_s`, `end_s`, `weight`, `name`."""
    glob: Optional[str] = None
    """Source "library": also every .csv/.npz file matching this pattern (relative to the launch folder)."""
    folder: Optional[str] = None
    """Source "library": also every .csv/.npz clip directly in this folder, in name order, each named after
    its file (relative to the launch folder; `motion=lafan_folder` sets it to data.lafan_dir). A file that
    cannot be a clip (unreadable, malformed, shorter than one time bin) is refused, never skipped."""
    include: Optional[Any] = None
    """Source "library": patterns (fnmatch, on the file name or its stem, e.g. `walk*`) that a file of
    `folder` or `glob` must match one of to be a clip (null: every file). One that matches no file is refused."""
    exclude: Optional[Any] = None
    """Source "library": patterns a file of `folder` or `glob` must match none of. One that matches no
    file is refused (a typo would otherwise train on clips meant to stay out)."""
    clip: Optional[str] = None
    """LAFAN1 clip for source "lafan", e.g. "dance1_subject1" (the CSV of that name in data.lafan_dir)."""
    path: Optional[str] = None
    """Motion file for source "file": `.npz` (BeyondMimic format with names) or `.csv` (LAFAN1 G1,
    converted and cached). Relative paths are resolved against the directory the command was started in."""
    fps_in: float = 30.0
    """Frame rate of a CSV file (LAFAN1: 30)."""
    builtin: str = "graded"
    """Name of the built-in motion for source "builtin": "graded" or "easy_only"."""
    seed: int = 0
    """Seed of the built-in motion (amplitudes, frequencies, sides, order within a difficulty level)."""
    duration_s: float = 30.0
    """Length of the built-in motion in seconds (segments stretch, or the graded cycle repeats)."""
    start_s: Optional[float] = None
    """Start of the window to train on, in seconds from the motion's start (None: 0)."""
    end_s: Optional[float] = None
    """End of the window to train on, in seconds (None: the motion's end)."""
    assume_model_order: bool = False
    """Accept an npz without joint/body names (e.g. made by mjlab) as being in the model's order."""
    check_plausible: bool = True
    """Refuse a motion file (or LAFAN1 clip) that is not a plausible reference: its root upside down at
    the first frame, or its feet far from the ground on most frames (a root quaternion in the wrong
    order, a position in other units); false uses it anyway, with a warning."""


def resolve_path(path: str) -> Path:
    """Relative paths are taken from the original working directory (Hydra may have changed it)."""
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.utils import to_absolute_path

        if HydraConfig.initialized():
            return Path(to_absolute_path(path))
    except ImportError:
        pass
    return Path(path).expanduser().resolve()


def lafan_clip_path(clip: str, lafan_dir: str | os.PathLike | None) -> Path:
    """The CSV of LAFAN1 clip `clip` (e.g. "dance1_subject1", ".csv" optional) in `lafan_dir`.

    Raises MotionDataError, one line naming what is missing, where to download it and what to set,
    when `lafan_dir` is unset or missing or has no such clip. Relative folders are taken from the
    directory the command was started in.
    """
    name = clip if Path(clip).suffix.lower() == ".csv" else f"{clip}.csv"
    how = f"download {LAFAN_SOURCE} and set {LAFAN_ENV}=/path/to/g1 (or data.lafan_dir=/path/to/g1)"
    if lafan_dir is None or not str(lafan_dir).strip():
        raise MotionDataError(f"LAFAN1 clip {name}: data.lafan_dir is not set; {how}")
    folder = resolve_path(str(lafan_dir))
    if not folder.is_dir():
        raise MotionDataError(f"LAFAN1 clip {name}: data.lafan_dir {folder} is not a folder; {how}")
    path = folder / name
    if not path.is_file():
        raise MotionDataError(f"LAFAN1 clip {name}: not in data.lafan_dir {folder}; {how}")
    return path


def model_fingerprint(mjmodel: mujoco.MjModel) -> str:
    """Hash of the figures that forward kinematics and the centre of mass depend on."""
    h = hashlib.sha256()
    for arr in (
        mjmodel.body_parentid,
        mjmodel.body_pos,
        mjmodel.body_quat,
        mjmodel.body_mass,
        mjmodel.body_ipos,
        mjmodel.jnt_type,
        mjmodel.jnt_axis,
        mjmodel.jnt_pos,
        mjmodel.jnt_range,
        mjmodel.geom_bodyid,
        mjmodel.geom_pos,
        mjmodel.geom_size,
    ):
        h.update(np.ascontiguousarray(arr).tobytes())
    for i in range(mjmodel.nbody):
        h.update(mjmodel.body(i).name.encode())
    for i in range(mjmodel.njnt):
        h.update(mjmodel.joint(i).name.encode())
    return h.hexdigest()[:16]


def _cached(cache_file: Path, mjmodel: mujoco.MjModel, make) -> Motion:
    from bmimic.motion.motion import Motion

    if cache_file.is_file():
        try:
            return Motion.load(cache_file, mjmodel)
        except MotionDataError:
            pass  # a damaged cache entry is rebuilt below
    motion = make()
    try:
        motion.save(cache_file)
    except OSError as err:  # a read-only or full cache costs the next start time, not this run
        log.warning("could not cache the motion at %s: %s", cache_file, err.strerror or err)
    return motion


def load_motion(
    cfg: MotionConfig,
    mjmodel: mujoco.MjModel,
    cache_dir: str | os.PathLike = "outputs/cache",
    bin_size_s: float = 1.0,
    lafan_dir: str | os.PathLike | None = None,
    control_fps: float = CONTROL_FPS,
) -> Motion:
    """The configured motion at the control rate `control_fps` (1 / (sim.timestep_s x sim.decimation))
    in model order, windowed to [start_s, end_s]: one reference frame per control step, so the
    reference never plays at the wrong speed. Other rates are resampled (CSVs are converted at it).

    `lafan_dir` (data.lafan_dir) is the folder that source "lafan" names its clip in.

    Raises MotionDataError (one line naming the field or file) for bad settings or data, including a
    window shorter than two time bins of `bin_size_s`.
    """
    from bmimic.motion import builtin
    from bmimic.motion.limits import check_motion_size, check_plausible, implausibility
    from bmimic.motion.motion import Motion

    cache = resolve_path(str(cache_dir))
    if cfg.source == "builtin":
        check_motion_size(mjmodel, float(cfg.duration_s), builtin.FPS, "motion.duration_s", generated=True)
        key = hashlib.sha256(
            f"builtin|{cfg.builtin}|{cfg.seed}|{float(cfg.duration_s)!r}|{builtin.GENERATOR_VERSION}|"
            f"{model_fingerprint(mjmodel)}".encode()
        ).hexdigest()
        motion = _cached(
            cache / f"builtin-{cfg.builtin}-{key[:24]}.npz",
            mjmodel,
            lambda: builtin.generate_builtin(mjmodel, cfg.builtin, int(cfg.seed), float(cfg.duration_s)),
        )
    elif cfg.source in ("file", "lafan"):
        if cfg.source == "lafan":
            if not cfg.clip:
                raise MotionDataError("motion.clip: required when motion.source is 'lafan' (e.g. dance1_subject1)")
            path = lafan_clip_path(str(cfg.clip), lafan_dir)
        elif not cfg.path:
            raise MotionDataError("motion.path: required when motion.source is 'file'")
        else:
            path = resolve_path(str(cfg.path))
        if not path.is_file():
            raise MotionDataError(f"motion.path: {path}: file not found")
        suffix = path.suffix.lower()
        if suffix == ".npz":
            motion = Motion.load(path, mjmodel, assume_model_order=bool(cfg.assume_model_order))
        elif suffix == ".csv":
            # imported here, not with the package, so `python -m bmimic.motion.convert` runs without a warning
            from bmimic.motion.convert import convert_csv

            try:
                h = hashlib.sha256(path.read_bytes())
            except OSError as err:
                raise MotionDataError(f"motion.path: {path}: cannot read ({err.strerror or err})") from None
            h.update(
                f"|fps_in={float(cfg.fps_in)!r}|fps_out={float(control_fps)!r}|{CONVERTER_VERSION}|"
                f"{model_fingerprint(mjmodel)}".encode()
            )
            motion = _cached(
                cache / f"{h.hexdigest()}.npz",
                mjmodel,
                lambda: convert_csv(path, mjmodel, float(cfg.fps_in), float(control_fps)),
            )
            # The cache is keyed by content, so the entry may come from a file of another name: the one
            # segment a CSV gets is named after this file, as convert_csv names it (a library's per-clip table).
            motion.segments = [Segment(path.stem, 0.0, motion.duration_s, "unknown")]
        else:
            raise MotionDataError(f"motion.path: {path}: expected a .npz or .csv file")
        if cfg.check_plausible:
            check_plausible(motion, f"motion.path: {path}", "set motion.check_plausible=false", mjmodel)
        elif (why := implausibility(motion, mjmodel)) is not None:
            log.warning("warning: motion.path: %s: %s; used anyway (motion.check_plausible=false)", path, why)
    else:
        hint = " (a library loads through bmimic.motion.library.load_any)" if cfg.source == "library" else ""
        raise MotionDataError(f"motion.source: expected 'builtin', 'lafan' or 'file', got {cfg.source!r}{hint}")

    if abs(motion.fps - control_fps) > 1e-6 * control_fps:
        # the file's own rate named too: a wrong fps in a file is what makes an absurd duration
        check_motion_size(mjmodel, motion.duration_s, control_fps,
                          f"motion {cfg.name!r} ({motion.num_frames} frames at fps {motion.fps:g}) resampled to the "
                          "control rate 1 / (sim.timestep_s x sim.decimation)")
        try:
            motion = motion.resample(control_fps)
        except MotionDataError as err:
            raise MotionDataError(f"motion {cfg.name!r}: {err}") from None
    if cfg.start_s is not None or cfg.end_s is not None:
        try:
            motion = motion.window(cfg.start_s, cfg.end_s)
        except MotionDataError as err:
            raise MotionDataError(f"motion.start_s/end_s: {err}") from None
    check_two_bins(cfg, motion, bin_size_s)
    return motion


def check_two_bins(cfg: MotionConfig, motion: Motion, bin_size_s: float) -> None:
    """Refuse a motion shorter than two time bins (one line naming the motion and the bin size)."""
    if motion.duration_s < 2 * bin_size_s - 1e-9:
        raise MotionDataError(
            f"motion {cfg.name!r}: {motion.duration_s:.2f} s is shorter than two time bins "
            f"of sampler.bin_size_seconds={bin_size_s:g} s; use a longer motion or window, or smaller bins"
        )
