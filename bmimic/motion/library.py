"""A motion library (`motion.source: library`): several clips, each loaded as a single motion is, then
back to back on one time axis (`Motion.concatenate`) with their boundaries kept (`clip_starts`).

Entries of `motion.clips` (a list of mappings) name exactly one source each:

- `path`: a CSV (LAFAN1 G1) or npz file, relative to the folder the command was started in;
- `clip`: a LAFAN1 clip name in `data.lafan_dir`;
- `builtin`: a built-in generated sequence ("graded" or "easy_only", with `seed` and `duration_s`);

with an optional window (`start_s`, `end_s`, seconds within that clip), a `weight` (> 0, the clip's
share under `sampler.clip_balance=clips`) and a `name` (default: the clip name, the file's stem, or
"<builtin>_<seed>"). `motion.glob` adds every CSV/npz file matching a pattern and `motion.folder`
every CSV/npz file directly in a folder (`motion=lafan_folder`: data.lafan_dir), each sorted by name and
named after its file; `motion.include` / `motion.exclude` (fnmatch patterns on the file name or stem)
keep or drop some of those files. Each clip is converted and cached on its own (a changed clip
re-converts only itself). A bad entry or file is one line naming it, e.g. `motion.clips[1].path: b.npz:
file not found` or `motion.folder: g1/x.csv: row 3, column 37: found 38 columns, ...`; nothing is skipped:
an empty folder, a pattern matching no file, a file of the folder that is unreadable, malformed or
shorter than one time bin is refused.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import glob as globlib
import os
from pathlib import Path
from typing import Any, cast

import mujoco

from bmimic.motion.config import MotionConfig
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
    origin: str = ""
    """Where the entry comes from, for messages: "motion.clips[k]", "motion.glob" or "motion.folder"."""


CLIP_SUFFIXES = (".csv", ".npz")
"""Files of `motion.glob` and `motion.folder` that are clips."""


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
    # optional=False: a number, never None
    weight = cast(float, _number(f"{where}.weight", raw.get("weight", 1.0), positive=True, optional=False))
    duration = cast(float, _number(f"{where}.duration_s", raw.get("duration_s", 10.0), positive=True, optional=False))
    source = {"path": "file", "clip": "lafan", "builtin": "builtin"}[key]
    default_name = {"file": Path(value).stem, "lafan": Path(value).stem, "builtin": f"{value}_{seed}"}[source]
    name = raw.get("name") if raw.get("name") is not None else default_name
    return ClipEntry(str(name), source, value, seed, duration, start, end, weight, origin=where)


def _patterns(cfg: MotionConfig, key: str) -> list[str]:
    raw = _plain(getattr(cfg, key, None))
    if raw is None:
        return []
    items = [raw] if isinstance(raw, str) else raw
    if not isinstance(items, list) or not all(isinstance(x, str) and x.strip() for x in items):
        raise MotionDataError(f"motion.{key}: expected a pattern or a list of patterns like [walk*, run*], got {raw!r}")
    return items


def _matches(path: Path, pattern: str) -> bool:
    return fnmatch.fnmatchcase(path.name, pattern) or fnmatch.fnmatchcase(path.stem, pattern)


def _shown(path: str | os.PathLike) -> str:
    """`path` printable: bytes that are not UTF-8 shown escaped (\\xff), as the OS holds them."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def _utf8_names(origin: str, where: str | os.PathLike, files: list[Path]) -> None:
    """MotionDataError naming `where` and the first file whose name is not valid UTF-8: a clip is named
    after its file in the run's tables and records, which hold text (refused before anything runs, not
    when the first table is written)."""
    for path in files:
        try:
            path.name.encode("utf-8")
        except UnicodeEncodeError:
            raise MotionDataError(f"{origin}: {_shown(where)}: the file name {os.fsencode(path.name)!r} is not valid "
                                  "UTF-8 (a clip is named after its file in the run's tables); rename it") from None


def _folder_files(folder: Any) -> list[Path]:
    """The clip files directly in `folder` (hidden files are not clips, as for a shell's `*`)."""
    from bmimic.motion.config import LAFAN_ENV, LAFAN_SOURCE, resolve_path

    if folder is None or not str(folder).strip():
        return []
    path = resolve_path(str(folder))
    if not path.is_dir():
        raise MotionDataError(f"motion.folder: {path} is not a folder (motion=lafan_folder reads data.lafan_dir, "
                              f"${LAFAN_ENV}: {LAFAN_SOURCE})")
    try:
        names = sorted(os.listdir(path))
    except OSError as err:
        raise MotionDataError(f"motion.folder: {path}: cannot list ({err.strerror or err})") from None
    files = [path / n for n in names if not n.startswith(".") and Path(n).suffix.lower() in CLIP_SUFFIXES]
    if not files:
        raise MotionDataError(f"motion.folder: {path} holds no .csv or .npz file")
    _utf8_names("motion.folder", path, files)
    return files


def _selected(files: list[tuple[str, Path]], cfg: MotionConfig) -> list[tuple[str, Path]]:
    """`files` ((origin, path) of motion.glob and motion.folder) kept by motion.include / motion.exclude;
    a pattern that matches none of them is refused, as is a selection that keeps none."""
    include, exclude = _patterns(cfg, "include"), _patterns(cfg, "exclude")
    if not files:
        if include or exclude:
            raise MotionDataError("motion.include/exclude: select among the files of motion.folder or motion.glob, "
                                  "and neither is set")
        return []
    for key, patterns in (("include", include), ("exclude", exclude)):
        for pattern in patterns:
            if not any(_matches(p, pattern) for _, p in files):
                raise MotionDataError(f"motion.{key}: {pattern!r} matches none of the {len(files)} files "
                                      f"({', '.join(p.name for _, p in files[:4])}{', ...' if len(files) > 4 else ''})")
    kept = [(o, p) for o, p in files if (not include or any(_matches(p, x) for x in include))
            and not any(_matches(p, x) for x in exclude)]
    if not kept:
        raise MotionDataError(f"motion.exclude: leaves none of the {len(files)} files that motion.include selects")
    return kept


def library_entries(cfg: MotionConfig) -> list[ClipEntry]:
    """The checked entries of a library config: `motion.clips`, then the files of `motion.glob`, then
    those of `motion.folder` (both kept or dropped by `motion.include` / `motion.exclude`)."""
    from bmimic.motion.config import LAFAN_ENV, LAFAN_SOURCE

    raw = _plain(getattr(cfg, "clips", None)) or []
    if not isinstance(raw, list):
        raise MotionDataError(f"motion.clips: expected a list of entries, got {raw!r}")
    entries = [_entry(k, r) for k, r in enumerate(raw)]
    files: list[tuple[str, Path]] = []
    pattern = getattr(cfg, "glob", None)
    if pattern:
        from bmimic.motion.config import resolve_path

        base = resolve_path(".")
        full = str(pattern) if os.path.isabs(str(pattern)) else str(base / str(pattern))
        found = sorted(p for p in globlib.glob(full) if Path(p).suffix.lower() in CLIP_SUFFIXES)
        if not found:
            raise MotionDataError(f"motion.glob: {pattern!r} matches no .csv or .npz file")
        _utf8_names("motion.glob", str(pattern), [Path(f) for f in found])
        files += [("motion.glob", Path(f)) for f in found]
    files += [("motion.folder", p) for p in _folder_files(getattr(cfg, "folder", None))]
    entries += [ClipEntry(p.stem, "file", str(p), origin=o) for o, p in _selected(files, cfg)]
    if not entries:
        # (a folder, when set, gave files or was refused above)
        raise MotionDataError("motion.clips: a library needs at least one clip: motion.clips and motion.glob give "
                              "none and motion.folder is not set (motion=lafan_folder sets it to data.lafan_dir: "
                              f"download {LAFAN_SOURCE} and set {LAFAN_ENV}=/path/to/g1)")
    names = [e.name for e in entries]
    dupes = sorted({n for n in names if names.count(n) > 1})
    if dupes:
        raise MotionDataError(f"motion.clips: clip names must be unique, {dupes} repeat; give entries a name "
                              "(or drop a file with motion.exclude)")
    return entries


def load_library(cfg: MotionConfig, mjmodel: mujoco.MjModel, cache_dir: str | os.PathLike, lafan_dir: Any,
                 control_fps: float, min_file_s: float = 0.0) -> Motion:
    """Every clip of the library at the control rate, concatenated; each clip's segments are kept (a
    clip without segments gets one named after the clip). A file of `motion.glob` or `motion.folder`
    shorter than `min_file_s` (one time bin) is refused: in a folder nobody listed by hand, that is a
    truncated or misplaced file (an entry of `motion.clips` may be shorter: it becomes one bin)."""
    from bmimic.motion.config import MotionConfig, load_motion

    if getattr(cfg, "start_s", None) is not None or getattr(cfg, "end_s", None) is not None:
        raise MotionDataError("motion.start_s/end_s: a library windows each clip instead (motion.clips[k].start_s)")
    clips = []
    for e in library_entries(cfg):
        one = MotionConfig(name=e.name, source=e.source, start_s=e.start_s, end_s=e.end_s,
                           fps_in=float(getattr(cfg, "fps_in", 30.0)),
                           assume_model_order=bool(getattr(cfg, "assume_model_order", False)),
                           check_plausible=bool(getattr(cfg, "check_plausible", True)),
                           path=e.value if e.source == "file" else None, clip=e.value if e.source == "lafan" else None,
                           builtin=e.value if e.source == "builtin" else "graded", seed=e.seed, duration_s=e.duration_s)
        # an entry of motion.clips is named by its key (motion.clips[1].path), a file of a folder or glob by
        # its path, which the loader's message already starts with
        where = (f"{e.origin}." + {"file": "path", "lafan": "clip", "builtin": "builtin"}[e.source]
                 if e.origin.startswith("motion.clips") else e.origin)
        try:
            m = load_motion(one, mjmodel, cache_dir=cache_dir, bin_size_s=0.0, lafan_dir=lafan_dir,
                            control_fps=control_fps)
        except MotionDataError as err:
            msg = str(err).replace("motion.path: ", "").replace("motion.start_s/end_s: ", "")
            raise MotionDataError(f"{where}: {msg}") from None
        if not e.origin.startswith("motion.clips") and m.duration_s < min_file_s - 1e-9:
            raise MotionDataError(f"{where}: {e.value}: {m.duration_s:.2f} s is shorter than one time bin of "
                                  f"sampler.bin_size_seconds={min_file_s:g} s; drop it (motion.exclude=[{e.name}]) "
                                  "or use smaller bins")
        if not m.segments:
            m = dataclasses.replace(m, segments=[Segment(e.name, 0.0, m.duration_s, "unknown")])
        clips.append(m)
    return clips[0] if len(clips) == 1 else Motion.concatenate(clips)


def load_any(cfg: MotionConfig, mjmodel: mujoco.MjModel, cache_dir: str | os.PathLike = "outputs/cache",
             bin_size_s: float = 1.0, lafan_dir: Any = None, control_fps: float = 50.0) -> Motion:
    """The configured motion, a library (`motion.source: library`) or a single motion (`load_motion`,
    same arguments), at the control rate."""
    from bmimic.motion.config import check_two_bins, load_motion, resolve_path

    if getattr(cfg, "source", None) != "library":
        return load_motion(cfg, mjmodel, cache_dir=cache_dir, bin_size_s=bin_size_s, lafan_dir=lafan_dir,
                           control_fps=control_fps)
    motion = load_library(cfg, mjmodel, resolve_path(str(cache_dir)), lafan_dir, control_fps, min_file_s=bin_size_s)
    check_two_bins(cfg, motion, bin_size_s)
    return motion


def clip_names(motion_cfg: MotionConfig, motion: Motion) -> tuple[str, ...]:
    """The names of the clips of `motion` as configured (a single motion: its `motion.name`)."""
    if getattr(motion_cfg, "source", None) == "library":
        return tuple(e.name for e in library_entries(motion_cfg))
    return (str(getattr(motion_cfg, "name", "motion")),) * int(len(motion.clip_starts))


def clip_weights(motion_cfg: MotionConfig) -> list[float] | None:
    """The clips' weights of a library (None for a single motion)."""
    if getattr(motion_cfg, "source", None) != "library":
        return None
    return [e.weight for e in library_entries(motion_cfg)]


__all__ = ["CLIP_SUFFIXES", "ClipEntry", "ENTRY_KEYS", "clip_names", "clip_weights", "library_entries", "load_any", "load_library"]
