"""A launch's claim on its run folder, made before Hydra creates or writes anything in it.

Hydra makes a single run's folder (`hydra.run.dir`) and opens its log there before any of bmimic's
code runs, so `bmimic.launch_guard.LaunchGuard` (a Hydra callback) claims the folder first:

- a generated folder (the default `outputs/runs/<run_name>/<timestamp>`) is created here, exclusively:
  a second launch in the same second gets `<timestamp>_1`, and so on, never the first one's folder;
- a folder the user pinned (`hydra.run.dir=...`) that holds a run (started, failed or finished) is
  refused without `resume`, and so is one that another process is training; one that holds anything
  else (a user's own files: a launch writes metrics.json, provenance.json, checkpoints/ ...) is refused
  even with `resume`: a launch writes only into a new or empty folder, or into its own run;
- what the launch created (folders, its log file, the lock file) is recorded in a `RunClaim`, so that
  a refused launch removes exactly that and nothing else, and a launch that continues another run
  carries over only the log lines it wrote itself.

Torch-free; nothing here writes into a folder the launch did not create, except its own log lines.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from pathlib import Path

from bmimic import BmimicError
from bmimic.runs.folder import (
    LOCK,
    MULTIRUN_RECORD,
    SWEEP_INDEX,
    checkpoint_files,
    checkpoints_dir,
    holds_lock,
    is_run_folder,
    lock_run,
    read_status,
)
from bmimic.runs.schema import ITERATION

MAX_SUFFIX = 1000
"""Most `_<n>` suffixes tried for a generated folder taken in the same second."""


class ClaimError(BmimicError):
    """The launch cannot have the run folder it names (one line; nothing was written)."""


@dataclass
class RunClaim:
    """What a launch found and created at its run folder before Hydra wrote anything."""

    run_dir: Path
    """The launch's folder (absolute)."""
    pinned: bool
    """The user named the folder (hydra.run.dir without a ${now:} timestamp)."""
    created: list[Path] = field(default_factory=list)
    """Folders this launch created, outermost first."""
    log_path: Path | None = None
    """Hydra's log file of the launch in run_dir (`<job name>.log`)."""
    log_offset: int | None = None
    """Bytes the log held before this launch (None: the launch created it)."""
    lock_existed: bool = True
    """run_dir held a lock file before this launch."""

    def own_log(self) -> str:
        """The lines this launch wrote to its log so far."""
        if self.log_path is None:
            return ""
        try:
            with open(self.log_path, "rb") as f:
                f.seek(self.log_offset or 0)
                return f.read().decode("utf-8", errors="replace")
        except OSError:
            return ""

    def release(self, lock_file=None) -> bool:
        """Remove what this launch created in its folder, and nothing else: its log lines (the file,
        when the launch created it), the lock file when the launch created it and still holds it
        (`lock_file`), the folders it created when they are then empty. Returns whether run_dir is gone."""
        if self.log_path is not None:
            with contextlib.suppress(OSError):
                if self.log_offset is None:
                    self.log_path.unlink()
                elif self.log_path.stat().st_size > self.log_offset:
                    os.truncate(self.log_path, self.log_offset)
        if not self.lock_existed and holds_lock(lock_file, self.run_dir):
            with contextlib.suppress(OSError):
                (self.run_dir / LOCK).unlink()  # still holding it: no other process can have taken it
        for folder in reversed(self.created):
            try:
                folder.rmdir()  # only when empty
            except OSError:
                break
        return not self.run_dir.exists()

    def release_observed(self) -> bool:
        """For a launch that observed its folder (`observe`: a torchrun rank other than 0 refused, e.g. its
        peers never came): remove the folders its Hydra made and the log in them, when the folder holds
        nothing else (rank 0, had it come, would have put its record there). Returns whether it is gone."""
        if not self.created or self.log_path is None:
            return False
        try:
            if set(os.listdir(self.run_dir)) - {self.log_path.name}:
                return False
        except OSError:
            return False
        return self.release()


_CURRENT: RunClaim | None = None


def current(run_dir: str | os.PathLike) -> RunClaim | None:
    """The claim this process made for `run_dir` (None: none, e.g. a sweep job)."""
    if _CURRENT is not None and _CURRENT.run_dir == Path(run_dir).resolve():
        return _CURRENT
    return None


def _mkdirs(path: Path, exist_ok: bool) -> list[Path]:
    """Create `path` and its missing parents; returns the folders created, outermost first. When a folder
    cannot be made (no permission, a full disk, a name too long) those it made are removed first."""
    if not exist_ok and path.exists():
        raise FileExistsError(path)
    missing = []
    p = path
    while not p.exists():
        missing.append(p)
        if p.parent == p:
            break
        p = p.parent
    created: list[Path] = []
    try:
        for folder in reversed(missing):
            try:
                folder.mkdir()
            except FileExistsError:
                if folder == path and not exist_ok:
                    raise
                continue
            created.append(folder)
        if not path.is_dir():
            raise NotADirectoryError(f"{path}: not a folder")
    except OSError:
        for folder in reversed(created):
            with contextlib.suppress(OSError):
                folder.rmdir()
        raise
    return created


def check_path(key: str, path: str | os.PathLike) -> None:
    """ClaimError (one line) for a folder path the OS would refuse by its length (ENAMETOOLONG), before
    anything is made: a name longer than its file system allows, or a path longer than PATH_MAX."""
    text = os.fsencode(os.path.abspath(path))
    probe = Path(os.path.abspath(path))
    while probe.parent != probe:  # the file system the folder would be made on: its nearest existing folder
        try:
            if probe.exists():
                break
        except OSError:  # (the name too long to look up)
            pass
        probe = probe.parent
    try:
        name_max, path_max = os.pathconf(probe, "PC_NAME_MAX"), os.pathconf(probe, "PC_PATH_MAX")
    except (OSError, ValueError):
        name_max, path_max = 255, 4096
    shown = f"{os.fsdecode(text[:60])}..." if len(text) > 80 else os.fsdecode(text)
    longest = max(Path(os.fsdecode(text)).parts, key=lambda part: len(os.fsencode(part)))
    if len(os.fsencode(longest)) > name_max:
        raise ClaimError(f"{key}={shown}: a folder name of {len(os.fsencode(longest))} bytes, more than the "
                         f"{name_max} this file system allows")
    if len(text) >= path_max:
        raise ClaimError(f"{key}={shown}: {len(text)} bytes, more than the {path_max - 1} a path may have")


def claim(run_dir: str | os.PathLike, pinned: bool, resume: bool, log_name: str | None) -> RunClaim:
    """Claim the launch's folder (see the module doc); raises ClaimError with one line."""
    global _CURRENT
    check_path("hydra.run.dir", run_dir)
    path = Path(os.path.abspath(run_dir))
    if pinned:
        if path.exists() and not path.is_dir():
            raise ClaimError(f"hydra.run.dir={run_dir}: is a file, not a folder")
        held = holds_run(path) if path.is_dir() else ""
        if held and not resume:
            raise ClaimError(f"hydra.run.dir={run_dir}: already holds a run ({held}); add resume=true to "
                             "continue it, or choose another folder")
        foreign = [] if held or not path.is_dir() else foreign_entries(path, log_name)
        if foreign:
            raise ClaimError(f"hydra.run.dir={run_dir}: holds files that are not a bmimic run ("
                             f"{', '.join(foreign[:4])}{', ...' if len(foreign) > 4 else ''}); a launch writes only "
                             "into a new or empty folder, or continues its own run: choose another folder")
        if path.is_dir() and (path / LOCK).exists():
            probe = lock_run(path)
            if probe is None:
                raise ClaimError(f"hydra.run.dir={run_dir}: is being trained by another process (its {LOCK} is "
                                 "held); wait for it or stop it first")
            probe.close()  # the lock was free: let it go at once
        try:
            created = _mkdirs(path, exist_ok=True)
        except OSError as e:
            raise ClaimError(f"hydra.run.dir={run_dir}: cannot create the folder: {e.strerror or e}") from None
    else:
        created = []
        for n in range(MAX_SUFFIX):
            candidate = path if n == 0 else path.with_name(f"{path.name}_{n}")
            try:
                created = _mkdirs(candidate, exist_ok=False)
            except FileExistsError:
                continue  # another launch took it (same second): the next suffix
            except OSError as e:
                raise ClaimError(f"hydra.run.dir={candidate}: cannot create the folder: {e.strerror or e}") from None
            path = candidate
            break
        else:
            raise ClaimError(f"hydra.run.dir={path}: {MAX_SUFFIX} launches in the same second; wait a second")
    log_path = path / log_name if log_name else None
    offset = log_path.stat().st_size if log_path is not None and log_path.is_file() else None
    _CURRENT = RunClaim(path, pinned, created, log_path, offset, (path / LOCK).exists())
    return _CURRENT


def observe(run_dir: str | os.PathLike, pinned: bool, log_name: str | None = None) -> RunClaim:
    """Record the folder of a launch that does not own it (a torchrun rank other than 0), before its Hydra
    makes the folder and opens its log there: the folders missing now are the ones that Hydra makes, which
    a refusal of this rank removes only while nothing but its log is in them (`release_observed`)."""
    global _CURRENT
    path = Path(os.path.abspath(run_dir))
    missing: list[Path] = []
    with contextlib.suppress(OSError):
        p = path
        while not p.exists() and p.parent != p:
            missing.insert(0, p)
            p = p.parent
    log_path = path / log_name if log_name else None
    _CURRENT = RunClaim(path, pinned, missing, log_path, None, True)
    return _CURRENT


def foreign_entries(path: Path, log_name: str | None = None) -> list[str]:
    """The entries of the folder `path` that no launch left there (sorted): everything but a launch's
    lock file and its log (`log_name`, which a launch only appends to), which a launch killed before it
    wrote anything leaves behind."""
    try:
        names = sorted(os.listdir(path))
    except OSError as e:
        return [f"(its entries cannot be listed: {e.strerror or e})"]
    return [n for n in names if n not in (LOCK, log_name)]


def check_sweep_folder(sweep_dir: str | os.PathLike) -> None:
    """A multirun's folder (`hydra.sweep.dir`) is new, empty or a sweep's (Hydra's multirun.yaml or the
    sweep's index.csv at its root); ClaimError otherwise: Hydra writes multirun.yaml there and the jobs
    their folders, so a folder of the user's own files is never written into."""
    check_path("hydra.sweep.dir", sweep_dir)
    path = Path(sweep_dir)
    if path.exists() and not path.is_dir():
        raise ClaimError(f"hydra.sweep.dir={sweep_dir}: is a file, not a folder")
    if not path.is_dir() or any((path / name).is_file() for name in (MULTIRUN_RECORD, SWEEP_INDEX)):
        return
    foreign = foreign_entries(path)
    if foreign:
        raise ClaimError(f"hydra.sweep.dir={sweep_dir}: holds files that are not a bmimic sweep ("
                         f"{', '.join(foreign[:4])}{', ...' if len(foreign) > 4 else ''}; no {MULTIRUN_RECORD} or "
                         f"{SWEEP_INDEX}); a sweep writes only into a new or empty folder or its own: choose another "
                         "sweep_name or hydra.sweep.dir")


def holds_run(path: Path) -> str:
    """What makes `path` a run (its status and checkpoints), or '' when it holds none."""
    ckpts = checkpoint_files(checkpoints_dir(path))
    if not is_run_folder(path) and not ckpts:
        return ""
    status = read_status(path)
    what = f"status {status.get('status')}"
    if status.get(ITERATION) is not None:
        what += f" at iteration {status.get(ITERATION)}"
    return what + (f", {len(ckpts)} checkpoint file(s)" if ckpts else "")
