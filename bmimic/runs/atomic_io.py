"""Atomic writes: the one writer of the project (every file bmimic writes goes through `atomic_write`).

A temp file in the target's folder is written, fsynced and renamed over the target, then the folder is
fsynced: an interrupted run never leaves a half-written checkpoint, table or status file behind, and
files get the permissions the umask asks for (0644 under umask 022). A write the operating system
refuses (a full disk, a quota, a read-only or immutable folder) is a `WriteError`: one line naming
the file. Torch-free; bmimic.runs.folder re-exports these names.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import math
import os
import shutil
import signal
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable, Iterator

from bmimic import BmimicError


class WriteError(BmimicError, OSError):
    """The operating system refused a write (disk full, quota, read-only or immutable folder,
    permissions): one line naming the file; still an OSError with the original errno."""

    @classmethod
    def of(cls, path: str | os.PathLike, e: OSError) -> "WriteError":
        err = cls(f"{path}: cannot write: {e.strerror or e}")
        err.errno, err.strerror, err.filename = e.errno, e.strerror, str(path)
        return err

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "cannot write"


def current_umask() -> int:
    """The process umask, read without changing it where Linux allows (os.umask is not thread-safe)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_path(path: str | os.PathLike, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(path, flags)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some filesystems cannot fsync a folder; the rename is still atomic
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, write: Callable[[str], object]) -> Path:
    """Call `write(tmp_path)`, fsync, and rename the result onto `path`; the one writer of the project.

    The temp file `.<name>.tmp-<random><ext>` lies in the target's folder (so the rename is atomic) and
    ends in the target's own extension, so writers that pick a format by suffix (ffmpeg, np.savez,
    matplotlib) behave as for the real name. Its permissions are those a plain open() would give
    (0666 & ~umask), not mkstemp's 0600. On any failure the temp file is removed and the old file, if
    any, is left as it was.
    """
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", suffix=path.suffix, dir=path.parent)
        os.close(fd)
        os.chmod(tmp, 0o666 & ~current_umask())
        write(tmp)
        _fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException as e:
        if tmp is not None:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        if isinstance(e, OSError) and not isinstance(e, WriteError):
            raise WriteError.of(path, e) from None
        raise
    _fsync_path(path.parent, directory=True)
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write `data` to `path` atomically."""
    def _w(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)

    return atomic_write(path, _w)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write `text` (UTF-8) to `path` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def json_values(obj: Any) -> Any:
    """`obj` with every float that is not finite (NaN, infinity; numpy's too) as None: JSON has no NaN,
    and a file holding a bare `NaN` is refused by strict readers (other languages, jq, browsers)."""
    if isinstance(obj, dict):
        return {k: json_values(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_values(v) for v in obj]
    if isinstance(obj, float) or (hasattr(obj, "dtype") and getattr(obj, "ndim", None) == 0):
        try:
            value = float(obj)
        except (TypeError, ValueError):
            return obj
        if isinstance(obj, float) or getattr(obj.dtype, "kind", "") == "f":
            return value if math.isfinite(value) else None
    return obj


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write `obj` as indented, key-sorted JSON to `path` atomically; a number that is not finite is
    written as null (json_values), so the file is valid JSON."""
    text = json.dumps(json_values(obj), indent=2, sort_keys=True, default=str, allow_nan=False)
    return atomic_write_text(path, text + "\n")


def atomic_write_parquet(path: str | os.PathLike, df) -> Path:
    """Write a pandas frame (no index) to `path` atomically."""
    return atomic_write(path, lambda tmp: df.to_parquet(tmp, index=False))


def atomic_write_csv(path: str | os.PathLike, df) -> Path:
    """Write a pandas frame as CSV (no index) to `path` atomically."""
    return atomic_write(path, lambda tmp: df.to_csv(tmp, index=False))


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[None]:
    """Serialise read-modify-write of files in `folder` between processes (flock on the folder).

    Where the filesystem cannot lock a folder (some network filesystems) it goes on unlocked: the
    atomic rename still keeps every file whole.
    """
    fd = None
    try:
        fd = os.open(folder, os.O_RDONLY)
        fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError:
        pass
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)  # closing drops the lock


def atomic_append_text(path: str | os.PathLike, text: str) -> Path:
    """Append `text` to a log file as one atomic replace, serialised against other appenders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with folder_lock(path.parent):
        try:
            old = path.read_bytes()
        except FileNotFoundError:
            old = b""
        return atomic_write_bytes(path, old + text.encode("utf-8"))


def rewrite_in_place(path: str | os.PathLike, data: bytes) -> None:
    """Overwrite an existing small file in the blocks it already holds (not atomic): the fallback of
    a record that must be written when no new file can be created (a full disk)."""
    try:
        fd = os.open(path, os.O_WRONLY)
    except OSError as e:
        raise WriteError.of(path, e) from None
    try:
        os.write(fd, data)
        os.ftruncate(fd, len(data))
        os.fsync(fd)
    except OSError as e:
        raise WriteError.of(path, e) from None
    finally:
        os.close(fd)


def make_folder(path: str | os.PathLike) -> Path:
    """Create the output folder `path` (and its parents): a file in its place, or a folder the system
    will not create, is one line naming it (BmimicError, WriteError)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise BmimicError(f"{path}: is a file, not a folder")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise WriteError.of(path, e) from None
    return path


@contextlib.contextmanager
def _terminate_raises() -> Iterator[None]:
    """SIGTERM raises SystemExit(143) in this block, so that its cleanup runs (the default action ends the
    process where it stands: a report stopped by SIGTERM left its stage behind). Only where nothing else
    handles SIGTERM, and only in the main thread (where handlers can be set)."""
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) != signal.SIG_DFL:
        yield
        return

    def stop(signum: int, frame: object) -> None:
        raise SystemExit(128 + signum)

    signal.signal(signal.SIGTERM, stop)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)


@contextlib.contextmanager
def staged_folder(out: str | os.PathLike) -> Iterator[Path]:
    """A hidden folder beside `out` to write a command's several files into. When the block ends, each file
    moves into `out` (made if missing) by a rename over any file of its name; when it raises (a full disk at
    the fifth figure, say), the stage goes and so does every folder made for it: a refused command leaves
    `out` and its parents as they were, never half a report."""
    out = Path(out)
    missing = [p for p in (out, *out.parents) if not p.exists()]
    stage = None
    with _terminate_raises():  # a SIGTERM mid-way: the cleanup below runs too
        try:
            make_folder(out.parent)
            try:
                stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.partial-", dir=out.parent))
            except OSError as e:
                raise WriteError.of(out.parent, e) from None
            yield stage
            make_folder(out)
            for f in sorted(p for p in stage.rglob("*") if not p.is_dir()):
                dest = out / f.relative_to(stage)
                dest.parent.mkdir(parents=True, exist_ok=True)
                os.replace(f, dest)
            _fsync_path(out, directory=True)
        except BaseException:
            if stage is not None:
                shutil.rmtree(stage, ignore_errors=True)
            if missing:  # the topmost folder made for it, with everything below it
                shutil.rmtree(missing[-1], ignore_errors=True)
            raise
        else:
            shutil.rmtree(stage, ignore_errors=True)  # its folders, emptied by the moves
