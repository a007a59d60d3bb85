"""A motion library (`motion.source: library`): several clips, each loaded as a single motion is, then
back to back on one time axis (`Motion.concatenate`) with their boundaries kept (`clip_starts`).

Entries of `motion.clips` (a list of mappings) name exactly one source each:

- `path`: a CSV (LAFAN1 G1) or npz file, relative to the folder the command was started in;
- `clip`: a LAFAN1 clip name in `data.lafan_dir`;
- `builtin`: a built-in generated sequence ("graded" or "easy_only", with `seed` and `duration_s`);

with an optional window (`start_s`, `end_s`, seconds within that clip), a `weight` (> 0, the clip's
share under `sampler.clip_balance=clips`) and a `name` (default: the clip name, the file's stem, or
"<builtin>_<seed>"). `motion.glob` adds every CSV/npz file matching a pattern (sorted by name).
Each clip is converted and cached on its own (a changed clip re-converts only itself). A bad entry is
one line naming it, e.g. `motion.clips[1].path: b.npz: file not found`.
"""

from __future__ import annotations

import dataclasses
import glob as globlib
import os
from pathlib import Path
from typing import Any

import mujoco

from bmimic.motion.motion import Motion
from bmimic.motion.segments import MotionDataError, Segment

ENTRY_KEYS = ("path", "clip", "builtin", "seed", "duration_s", "start_s", "end_s", "weight", "name")
"""Keys an entry of motion.clips may have."""
SOURCES = ("path", "clip", "builtin")


@dataclasses.dataclass(frozen=True)
class ClipEntry:
    """One checked entry of a library."""

    name: str
    """The clip's label (tables, reports, the run's clip list)."""
    source: str
    """"file", "lafan" or "builtin" (a `motion.source`)."""
    value: str
    """The path, LAFAN1 clip name or built-in sequence name."""
    seed: int = 0
    duration_s: float = 10.0
    start_s: float | None = None
    end_s: float | None = None
    weight: float = 1.0


def _plain(x: Any) -> Any:
    try:
        from omegaconf import OmegaConf

        if OmegaConf.is_config(x):
            return OmegaConf.to_container(x, resolve=True)
    except ImportError:
        pass
    return x


def _number(where: str, x: Any, positive: bool = False, optional: bool = True) -> float | None:
    if x is None and optional:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, float)) or x != x or x in (float("inf"), float("-inf")):
        raise MotionDataError(f"{where}: expected a finite number, got {x!r}")
    if positive and not x > 0:
        raise MotionDataError(f"{where}: must be > 0, got {x!r}")
    return float(x)


def _entry(k: int, raw: Any) -> ClipEntry:
    where = f"motion.clips[{k}]"
    raw = _plain(raw)
    if isinstance(raw, str):  # a bare string is a path
        raw = {"path": raw}
    if not isinstance(raw, dict):
        raise MotionDataError(f"{where}: expected a mapping like {{path: a.csv}} or {{clip: dance1_subject1}}, "
                              f"got {raw!r}")
    unknown = sorted(set(raw) - set(ENTRY_KEYS))
    if unknown:
        raise MotionDataError(f"{where}: unknown key(s) {unknown}; an entry has {', '.join(ENTRY_KEYS)}")
    given = [s for s in SOURCES if raw.get(s) is not None]
    if len(given) != 1:
        raise MotionDataError(f"{where}: needs exactly one of path, clip or builtin, got {given or 'none'}")
    key = given[0]
    value = raw[key]
    if not isinstance(value, str) or not value.strip():
        raise MotionDataError(f"{where}.{key}: expected a non-empty string, got {value!r}")
    seed = raw.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise MotionDataError(f"{where}.seed: expected an integer, got {seed!r}")
    start, end = _number(f"{where}.start_s", raw.get("start_s")), _number(f"{where}.end_s", raw.get("end_s"))
    if start is not None and end is not None and not end > start:
        raise MotionDataError(f"{where}: end_s {end} must be after start_s {start}")
    weight = _number(f"{where}.weight", raw.get("weight", 1.0), positive=True, optional=False)
    duration = _number(f"{where}.duration_s", raw.get("duration_s", 10.0), positive=True, optional=False)
    source = {"path": "file", "clip": "lafan", "builtin": "builtin"}[key]
    default_name = {"file": Path(value).stem, "lafan": Path(value).stem, "builtin": f"{value}_{seed}"}[source]
    name = raw.get("name") if raw.get("name") is not None else default_name
    return ClipEntry(str(name), source, value, seed, duration, start, end, weight)


def library_entries(cfg: Any) -> list[ClipEntry]:
    """The checked entries of a library config (`motion.clips`, then the files of `motion.glob`)."""
    raw = _plain(getattr(cfg, "clips", None)) or []
    if not isinstance(raw, list):
        raise MotionDataError(f"motion.clips: expected a list of entries, got {raw!r}")
    entries = [_entry(k, r) for k, r in enumerate(raw)]
    pattern = getattr(cfg, "glob", None)
    if pattern:
        from bmimic.motion.config import resolve_path

        base = resolve_path(".")
        full = str(pattern) if os.path.isabs(str(pattern)) else str(base / str(pattern))
        files = sorted(p for p in globlib.glob(full) if Path(p).suffix.lower() in (".csv", ".npz"))
        if not files:
            raise MotionDataError(f"motion.glob: {pattern!r} matches no .csv or .npz file")
        entries += [ClipEntry(Path(f).stem, "file", f) for f in files]
    if not entries:
        raise MotionDataError("motion.clips: a library needs at least one clip (motion.clips or motion.glob)")
    names = [e.name for e in entries]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise MotionDataError(f"motion.clips: clip names must be unique, {dupes} repeat; give entries a name")
    return entries


def load_library(cfg: Any, mjmodel: mujoco.MjModel, cache_dir: str | os.PathLike, lafan_dir: Any,
                 control_fps: float) -> Motion:
    """Every clip of the library at the control rate, concatenated; each clip's segments are kept (a
    clip without segments gets one named after the clip)."""
    from bmimic.motion.config import MotionConfig, load_motion

    if getattr(cfg, "start_s", None) is not None or getattr(cfg, "end_s", None) is not None:
        raise MotionDataError("motion.start_s/end_s: a library windows each clip instead (motion.clips[k].start_s)")
    clips = []
    for k, e in enumerate(library_entries(cfg)):
        one = MotionConfig(name=e.name, source=e.source, start_s=e.start_s, end_s=e.end_s,
                           fps_in=float(getattr(cfg, "fps_in", 30.0)),
                           assume_model_order=bool(getattr(cfg, "assume_model_order", False)),
                           path=e.value if e.source == "file" else None, clip=e.value if e.source == "lafan" else None,
                           builtin=e.value if e.source == "builtin" else "graded", seed=e.seed, duration_s=e.duration_s)
        try:
            m = load_motion(one, mjmodel, cache_dir=cache_dir, bin_size_s=0.0, lafan_dir=lafan_dir,
                            control_fps=control_fps)
        except MotionDataError as err:
            key = {"file": "path", "lafan": "clip", "builtin": "builtin"}[e.source]
            msg = str(err).replace("motion.path: ", "").replace("motion.start_s/end_s: ", "")
            raise MotionDataError(f"motion.clips[{k}].{key}: {msg}") from None
        if not m.segments:
            m = dataclasses.replace(m, segments=[Segment(e.name, 0.0, m.duration_s, "unknown")])
        clips.append(m)
    return clips[0] if len(clips) == 1 else Motion.concatenate(clips)


def load_any(cfg: Any, mjmodel: mujoco.MjModel, cache_dir: str | os.PathLike = "outputs/cache",
             bin_size_s: float = 1.0, lafan_dir: Any = None, control_fps: float = 50.0) -> Motion:
    """The configured motion, a library (`motion.source: library`) or a single motion (`load_motion`,
    same arguments), at the control rate."""
    from bmimic.motion.config import check_two_bins, load_motion, resolve_path

    if getattr(cfg, "source", None) != "library":
        return load_motion(cfg, mjmodel, cache_dir=cache_dir, bin_size_s=bin_size_s, lafan_dir=lafan_dir,
                           control_fps=control_fps)
    motion = load_library(cfg, mjmodel, resolve_path(str(cache_dir)), lafan_dir, control_fps)
    check_two_bins(cfg, motion, bin_size_s)
    return motion


def clip_names(motion_cfg: Any, motion: Motion) -> tuple[str, ...]:
    """The names of the clips of `motion` as configured (a single motion: its `motion.name`)."""
    if getattr(motion_cfg, "source", None) == "library":
        return tuple(e.name for e in library_entries(motion_cfg))
    return (str(getattr(motion_cfg, "name", "motion")),) * int(len(motion.clip_starts))


def clip_weights(motion_cfg: Any) -> list[float] | None:
    """The clips' weights of a library (None for a single motion)."""
    if getattr(motion_cfg, "source", None) != "library":
        return None
    return [e.weight for e in library_entries(motion_cfg)]


__all__ = ["ClipEntry", "ENTRY_KEYS", "clip_names", "clip_weights", "library_entries", "load_any", "load_library"]
