"""The run folder: the one owner of its layout, of the atomic writer and of its small JSON files.

Every name a run folder holds is spelled here once (docs/architecture.md lists them with their
schemas); training writes through these functions, and `bmimic.eval`, `play`, `export`, `sim2sim`,
the sweep tools and `analysis` read through them. This module is torch-free (analysis imports it on
machines without torch): checkpoints are found here by name, read by `bmimic.training.checkpoints`.

Every file bmimic writes goes through `atomic_write` (a temp file in the same folder, fsynced, then
renamed over the target, then the folder fsynced), so an interrupted run never leaves a half-written
checkpoint, table or status file behind, and files get the permissions the umask asks for (0644 under
umask 022), so a team can read each other's runs.
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import fcntl
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

from bmimic import BmimicError

# --------------------------------------------------------------------------------------------- layout
HYDRA_DIR = ".hydra"
"""Hydra's record of the launch: config.yaml (as composed), hydra.yaml, overrides.yaml."""
HYDRA_FILES = ("config.yaml", "hydra.yaml", "overrides.yaml")
STATUS = "status.json"
METRICS = "metrics.json"
PROVENANCE = "provenance.json"
RESOLVED_CONFIG = "resolved_config.json"
RESUMES = "resumes.json"
MOTION_SEGMENTS = "motion_segments.json"
ERRORS_LOG = "errors.log"
LOCK = ".bmimic.lock"
"""Empty; flock-ed while a process trains the run (the lock dies with the process)."""
TENSORBOARD_DIR = "tensorboard"
CHECKPOINTS_DIR = "checkpoints"
LATEST_CHECKPOINT = "latest.pt"
TABLES = {
    "train_metrics": "train_metrics.parquet",
    "sampler": "sampler.parquet",
    "eval": "eval.parquet",
    "eval_robust": "eval_robust.parquet",
    "clip_eval": "clip_eval.parquet",
}
"""Training's tables: name -> file name in the run folder."""
EVAL_DIR = "eval"
"""`python -m bmimic.eval` writes eval/<checkpoint label>/ (EVAL_TABLES)."""
EVAL_TABLES = ("eval_episodes.parquet", "eval_bins.parquet", "eval_segments.csv", "eval_summary.json")
"""One evaluation's files; the summary is written last, so its presence means a complete set."""
EVAL_SUMMARY = EVAL_TABLES[-1]
VIDEOS_DIR = "videos"
SIM2SIM_DIR = "sim2sim"
"""`python -m bmimic.sim2sim` writes sim2sim/<model>/<checkpoint label>/ (EVAL_TABLES and the gap)."""

_CHECKPOINT = re.compile(r"model_(\d+)\.pt")
MOTION_POLICY = re.compile(r"motion_policy_(\d+)\.onnx$")
"""File name of the BeyondMimic-compatible ONNX export of a checkpoint."""


def checkpoint_name(iteration: int) -> str:
    """`model_<it>.pt`, the checkpoint written at iteration `it`."""
    return f"model_{int(iteration)}.pt"


def checkpoint_label(iteration: int) -> str:
    """The name of a checkpoint's results (eval/<label>/, sim2sim/<model>/<label>/): `model_<it>`."""
    return f"model_{int(iteration)}"


def policy_onnx_name(iteration: int) -> str:
    """The deterministic actor, obs -> actions."""
    return f"policy_{int(iteration)}.onnx"


def motion_policy_onnx_name(iteration: int) -> str:
    """BeyondMimic's deployment format: (obs, time_step) -> actions and the reference, motion baked in."""
    return f"motion_policy_{int(iteration)}.onnx"


def checkpoints_dir(run_dir: str | os.PathLike) -> Path:
    """The run's checkpoints/ folder (checkpoints and their ONNX exports)."""
    return Path(run_dir) / CHECKPOINTS_DIR


def latest_checkpoint(run_dir: str | os.PathLike) -> Path:
    """checkpoints/latest.pt (a copy of the newest model_<it>.pt)."""
    return checkpoints_dir(run_dir) / LATEST_CHECKPOINT


def checkpoint_path(run_dir: str | os.PathLike, iteration: int) -> Path:
    """checkpoints/model_<it>.pt of the run."""
    return checkpoints_dir(run_dir) / checkpoint_name(iteration)


def table_path(run_dir: str | os.PathLike, name: str) -> Path:
    """A training table (a key of TABLES)."""
    return Path(run_dir) / TABLES[name]


def checkpoint_iteration(path: str | os.PathLike) -> int:
    """Iteration in a `model_<it>.pt` name (-1 for other names)."""
    m = _CHECKPOINT.fullmatch(Path(path).name)
    return int(m.group(1)) if m else -1


def checkpoint_files(ckpt_dir: str | os.PathLike) -> list[Path]:
    """latest.pt, then model_<it>.pt newest first: the order a resume tries them in (unread)."""
    ckpt_dir = Path(ckpt_dir)
    if not ckpt_dir.is_dir():
        return []
    found = sorted((p for p in ckpt_dir.glob("model_*.pt") if checkpoint_iteration(p) >= 0),
                   key=checkpoint_iteration, reverse=True)
    latest = ckpt_dir / LATEST_CHECKPOINT
    return ([latest] if latest.is_file() else []) + found


def newest_iteration(ckpt_dir: str | os.PathLike) -> int:
    """The largest `model_<it>.pt` iteration in `ckpt_dir` (-1 when there is none)."""
    return max((checkpoint_iteration(p) for p in Path(ckpt_dir).glob("model_*.pt")), default=-1)


def newest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The checkpoint a tool uses for a run folder: latest.pt, else the newest model_<it>.pt."""
    files = checkpoint_files(checkpoints_dir(run_dir))
    return files[0] if files else None


def is_run_folder(path: str | os.PathLike) -> bool:
    """A folder training wrote: it has status.json, resolved_config.json or .hydra/config.yaml."""
    path = Path(path)
    return any((path / name).is_file() for name in (STATUS, RESOLVED_CONFIG, f"{HYDRA_DIR}/config.yaml"))


# --------------------------------------------------------------------------------------------- atomic I/O
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


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Call `write(tmp_path)`, fsync, and rename the result onto `path`; the one writer of the project.

    The temp file `.<name>.tmp-<random><ext>` lies in the target's folder (so the rename is atomic) and
    ends in the target's own extension, so writers that pick a format by suffix (ffmpeg, np.savez,
    matplotlib) behave as for the real name. Its permissions are those a plain open() would give
    (0666 & ~umask), not mkstemp's 0600. On any failure the temp file is removed and the old file, if
    any, is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~current_umask())
        write(tmp)
        _fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
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


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """Write `obj` as indented, key-sorted JSON to `path` atomically."""
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


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


def read_json(path: str | os.PathLike, default: Any = None) -> Any:
    """The parsed JSON at `path`, or `default` when it is absent or unreadable."""
    try:
        with open(path) as f:
            return json.load(f)
    except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError, IsADirectoryError):
        return default


class RunFolderError(BmimicError):
    """A run-folder file that exists but cannot be read (one line naming it)."""


def load_json(path: str | os.PathLike) -> Any:
    """The parsed JSON at `path`, None when it is absent; RunFolderError when it cannot be read."""
    path = Path(path)
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise RunFolderError(f"{path}: not valid JSON ({e})") from e


# --------------------------------------------------------------------------------------------- the JSON files
def now() -> str:
    """The time stamps of the run folder's records: UTC, ISO 8601, seconds."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def write_status(run_dir: str | os.PathLike, status: str, iteration: int = 0, error: str | None = None) -> None:
    """status.json: `running`, `done` or `failed` (with the error's one-line message)."""
    atomic_write_json(Path(run_dir) / STATUS,
                      {"status": status, "iteration": int(iteration), "error": error, "updated": now()})


def read_status(run_dir: str | os.PathLike) -> dict:
    """status.json, or {"status": "missing"} when it is absent or unreadable."""
    status = read_json(Path(run_dir) / STATUS, default=None)
    return status if isinstance(status, dict) else {"status": "missing"}


def write_metrics(run_dir: str | os.PathLike, metrics: dict) -> None:
    """metrics.json: the run's final numbers (docs/architecture.md lists the keys)."""
    atomic_write_json(Path(run_dir) / METRICS, metrics)


def read_metrics(run_dir: str | os.PathLike) -> dict:
    """metrics.json ({} when absent or unreadable: a run that has not finished)."""
    metrics = read_json(Path(run_dir) / METRICS, default=None)
    return metrics if isinstance(metrics, dict) else {}


def write_provenance(run_dir: str | os.PathLike, info: dict) -> None:
    """provenance.json (bmimic.runtime.provenance: code and library versions, hardware, command line)."""
    atomic_write_json(Path(run_dir) / PROVENANCE, info)


def read_provenance(run_dir: str | os.PathLike) -> dict:
    """provenance.json ({} when absent or unreadable)."""
    info = read_json(Path(run_dir) / PROVENANCE, default=None)
    return info if isinstance(info, dict) else {}


def write_resolved_config(run_dir: str | os.PathLike, config: dict) -> None:
    """resolved_config.json: the config after runtime resolution."""
    atomic_write_json(Path(run_dir) / RESOLVED_CONFIG, config)


def read_resolved_config(run_dir: str | os.PathLike) -> dict | None:
    """resolved_config.json (None when absent or unreadable)."""
    cfg = read_json(Path(run_dir) / RESOLVED_CONFIG)
    return cfg if isinstance(cfg, dict) else None


def write_motion_segments(run_dir: str | os.PathLike, segments: list[dict]) -> None:
    """motion_segments.json: the segments of the motion trained on."""
    atomic_write_json(Path(run_dir) / MOTION_SEGMENTS, segments)


def append_resume(run_dir: str | os.PathLike, entry: dict) -> None:
    """Append one resume (checkpoint, iteration, accepted config changes, provenance) to resumes.json."""
    path = Path(run_dir) / RESUMES
    with folder_lock(path.parent):
        history = read_json(path, default=[])
        history = history if isinstance(history, list) else []
        atomic_write_json(path, [*history, {"time": now(), **entry}])


def append_error_log(run_dir: str | os.PathLike, headline: str, details: str = "") -> Path:
    """Add a timestamped entry to errors.log (kept across retries; status.json is not), as one atomic
    replace serialised against concurrent appenders."""
    entry = f"=== {now()} {headline}\n{details.rstrip()}\n" if details.strip() else f"=== {now()} {headline}\n"
    return atomic_append_text(Path(run_dir) / ERRORS_LOG, entry)


def write_hydra_record(run_dir: str | os.PathLike, record: dict[str, str] | None) -> None:
    """.hydra/{config,hydra,overrides}.yaml as Hydra writes them (conf/train.yaml sets
    hydra.output_subdir=null so that Hydra itself never rewrites a finished run's record)."""
    for name, text in (record or {}).items():
        atomic_write_text(Path(run_dir) / HYDRA_DIR / name, text)


def has_hydra_record(run_dir: str | os.PathLike) -> bool:
    """The run holds .hydra/config.yaml (what eval, play and export reload)."""
    return (Path(run_dir) / HYDRA_DIR / "config.yaml").is_file()


# --------------------------------------------------------------------------------------------- run lock
class RunLockedError(BmimicError):
    """Another live process is training in this run folder."""


def lock_run(run_dir: str | os.PathLike):
    """Take the exclusive lock of a run folder; returns the open lock file (the lock lives while it is
    open and dies with the process, so a killed run never leaves a stale lock), or None when another
    process holds it."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    f = open(run_dir / LOCK, "a")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        return None
    except OSError:  # a filesystem without locks: cannot tell, so do not block the run
        return f
    return f
