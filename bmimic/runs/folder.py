"""The run folder: the one owner of its layout, of the atomic writer and of its small JSON files.

Every name a run folder holds is spelled here once (docs/architecture.md lists them with their
schemas); training writes through these functions, and `bmimic.eval`, `play`, `export`, `sim2sim`,
the sweep tools and `analysis` read through them. This module is torch-free (analysis imports it on
machines without torch): checkpoints are found here by name, read by `bmimic.training.checkpoints`.

Every file bmimic writes goes through `atomic_write` (bmimic.runs.atomic_io, re-exported here: a temp file
in the same folder, fsynced, then renamed over the target), so an interrupted run never leaves a
half-written checkpoint, table or status file behind, and files get the permissions the umask asks
for (0644 under umask 022), so a team can read each other's runs.
"""

from __future__ import annotations

import datetime as _dt
import fcntl
import json
import os
import re
from pathlib import Path
from typing import Any, TextIO

from bmimic import BmimicError
from bmimic.runs import safe_read
from bmimic.runs.atomic_io import (  # noqa: F401  (the writer of every run-folder file, re-exported)
    WriteError,
    atomic_append_text,
    atomic_write,
    atomic_write_bytes,
    atomic_write_csv,
    atomic_write_json,
    atomic_write_parquet,
    atomic_write_text,
    current_umask,
    folder_lock,
    make_folder,
    rewrite_in_place,
)
from bmimic.runs.schema import ITERATION

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
RACE = "race.json"
"""A race's record (bmimic.race writes it, analysis.races reads it)."""
SWEEP_INDEX = "index.csv"
"""A sweep's table of its jobs, at the sweep's root (analysis.index writes it)."""
MULTIRUN_RECORD = "multirun.yaml"
"""Hydra's record of a multirun, at the sweep's root."""
DATA_FOLDER_NAME = "$BMIMIC_LAFAN_DIR"
"""What an absolute data.lafan_dir outside the launch directory reads as in committed records
(analysis.compact's portable_records; a restored state is compared with such a record)."""


def swap_folder(value, old: str, new: str):
    """`value` (a config tree) with every string that is the folder `old` or a path below it starting with
    `new` instead: a committed record's DATA_FOLDER_NAME and this machine's clips' folder, either way."""
    if isinstance(value, dict):
        return {k: swap_folder(v, old, new) for k, v in value.items()}
    if isinstance(value, list):
        return [swap_folder(v, old, new) for v in value]
    if isinstance(value, str) and (value == old or value.startswith(old + "/")):
        return new + value[len(old):]
    return value
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
    "whole_clip": "whole_clip.parquet",
    "whole_clip_survival": "whole_clip_survival.parquet",
    "whole_clip_failures": "whole_clip_failures.parquet",
}
"""Training's tables: name -> file name in the run folder."""
EVALUATION_TABLES = ("eval", "eval_robust", "clip_eval", "whole_clip", "whole_clip_survival", "whole_clip_failures")
"""The TABLES of evaluations: their `iteration` is the number of iterations done before the row; in the
others it is the 0-based index of the iteration that made the row."""
EVAL_DIR = "eval"
"""`python -m bmimic.eval` writes eval/<checkpoint label>/ (EVAL_TABLES)."""
EVAL_TABLES = ("eval_episodes.parquet", "eval_bins.parquet", "eval_segments.csv", "eval_summary.json")
"""One evaluation's files; the summary is written last, so its presence means a complete set."""
EVAL_SUMMARY = EVAL_TABLES[-1]
WHOLE_CLIP_DIR = "whole_clip"
"""`python -m bmimic.eval --whole-clip` writes eval/<checkpoint label>/whole_clip/ (WHOLE_CLIP_FILES);
`python -m bmimic.sim2sim --whole-clip R` sim2sim/<model>/<checkpoint label>/whole_clip/."""
WHOLE_CLIP_SURVIVAL = "whole_clip_survival.csv"
"""Survival over clip time of whole-clip rollouts (runs.schema.WHOLE_CLIP_SURVIVAL_COLUMNS): a view derived
from the clips and failures files (runs.schema.whole_clip_survival), which the analysis derives again and
analysis.compact drops from committed runs, as it does training's whole_clip_survival.parquet."""
WHOLE_CLIP_FILES = ("whole_clip.csv", WHOLE_CLIP_SURVIVAL, "whole_clip_failures.csv", "whole_clip_summary.json")
"""One whole-clip evaluation's files (the columns of training's whole_clip tables without the iteration);
the summary is written last, so its presence means a complete set."""
VIDEOS_DIR = "videos"
SIM2SIM_DIR = "sim2sim"
"""`python -m bmimic.sim2sim` writes sim2sim/<model>/<checkpoint label>/ (EVAL_TABLES and SIM2SIM_GAP)."""
SIM2SIM_GAP = "sim2sim_gap_bins.csv"
"""sim2sim's per-bin gap to the MuJoCo-Warp evaluation of the same checkpoint."""
SIM2SIM_WHOLE_CLIP = WHOLE_CLIP_DIR
"""`python -m bmimic.sim2sim --whole-clip R` writes sim2sim/<model>/<checkpoint label>/whole_clip/: EVAL_TABLES
(rows: rollouts, bins and segments by condition), WHOLE_CLIP_SURVIVAL and SIM2SIM_WHOLE_CLIP_GAP."""
SIM2SIM_WHOLE_CLIP_GAP = "sim2sim_gap_clips.csv"
"""Per condition and clip: native whole-clip success, bmimic's of the same checkpoint where known, the gap."""

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
    # (a latest.pt that is not a regular file, a FIFO or a link to a device, is listed: its reader refuses it
    # in its words, where passing it over would evaluate an older checkpoint as the run's newest)
    return ([latest] if latest.is_symlink() or latest.exists() else []) + found


def newest_iteration(ckpt_dir: str | os.PathLike) -> int:
    """The largest `model_<it>.pt` iteration in `ckpt_dir` (-1 when there is none)."""
    return max((checkpoint_iteration(p) for p in Path(ckpt_dir).glob("model_*.pt")), default=-1)


def newest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """The checkpoint a tool uses for a run folder: latest.pt, else the newest model_<it>.pt."""
    files = checkpoint_files(checkpoints_dir(run_dir))
    return files[0] if files else None


def portable_path(path: str | os.PathLike) -> str:
    """``path`` relative to the working directory when it lies below it (how a record names a run folder
    without the machine's own paths), else as given."""
    return os.path.relpath(path) if Path(path).is_relative_to(Path.cwd()) else str(path)


def is_run_folder(path: str | os.PathLike) -> bool:
    """A folder training wrote: it has status.json, resolved_config.json or .hydra/config.yaml."""
    path = Path(path)
    return any((path / name).is_file() for name in (STATUS, RESOLVED_CONFIG, f"{HYDRA_DIR}/config.yaml"))


def read_json(path: str | os.PathLike, default: Any = None) -> Any:
    """The parsed JSON at `path`, or `default` when it is absent or unreadable."""
    try:
        return safe_read.read_json(path)
    except (OSError, ValueError):  # absent, a folder, a FIFO or device, too deep or large, not JSON, not UTF-8
        return default


class RunFolderError(BmimicError):
    """A run-folder file that exists but cannot be read (one line naming it)."""


def load_json(path: str | os.PathLike) -> Any:
    """The parsed JSON at `path`, None when it is absent; RunFolderError when it cannot be read."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        return safe_read.read_json(path)
    except safe_read.UnsafeFileError as e:
        raise RunFolderError(str(e)) from None
    except (OSError, ValueError) as e:
        raise RunFolderError(f"{path}: not valid JSON ({e})") from e


# --------------------------------------------------------------------------------------------- the JSON files
def now() -> str:
    """The time stamps of the run folder's records: UTC, ISO 8601, seconds."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def write_status(run_dir: str | os.PathLike, status: str, iteration: int = 0, error: str | None = None) -> None:
    """status.json: `running`, `done`, `interrupted` (stopped by a signal after `iteration`, with a
    checkpoint there) or `failed` (with the error's one-line message).

    On a full disk the atomic write (a new file) fails; the status is then rewritten in place, in the
    blocks the file already holds, so that a run stopped by a full disk is never left `running`."""
    path = Path(run_dir) / STATUS
    record = {"status": status, ITERATION: int(iteration), "error": error, "updated": now()}
    try:
        atomic_write_json(path, record)
    except WriteError:
        if not path.is_file():
            raise
        rewrite_in_place(path, (json.dumps(record, indent=2, sort_keys=True, default=str) + "\n").encode("utf-8"))


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


def read_hydra_config(run_dir: str | os.PathLike) -> dict | None:
    """.hydra/config.yaml, the composed config of the run's launch (None when absent or unreadable)."""
    import yaml

    try:
        cfg = safe_read.read_yaml(Path(run_dir) / HYDRA_DIR / "config.yaml")
    except (OSError, ValueError, yaml.YAMLError):
        return None
    return cfg if isinstance(cfg, dict) else None


def has_hydra_record(run_dir: str | os.PathLike) -> bool:
    """The run holds .hydra/config.yaml (what eval, play and export reload)."""
    return (Path(run_dir) / HYDRA_DIR / "config.yaml").is_file()


# --------------------------------------------------------------------------------------------- run lock
class RunLockedError(BmimicError):
    """Another live process is training in this run folder."""


def lock_run(run_dir: str | os.PathLike) -> TextIO | None:
    """Take the exclusive lock of a run folder; returns the open lock file (the lock lives while it is
    open and dies with the process, so a killed run never leaves a stale lock), or None when another
    process holds it.

    The lock is the flock of the file `.bmimic.lock` *now at that path*: a file unlinked (or replaced)
    while it was being locked is not the run's lock, so the lock is taken again on the file the path
    names; a lock file is only ever removed by the process holding it (bmimic.runs.claim)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    path = run_dir / LOCK
    for _ in range(100):
        f = open(path, "a")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.close()
            return None
        except OSError:  # a filesystem without locks: cannot tell, so do not block the run
            return f
        if _same_file(f, path):
            return f
        f.close()  # removed or replaced while we locked it: lock the file the path names now
    raise RunLockedError(f"{path}: the lock file keeps being replaced; is another process removing it?")


def holds_lock(f, run_dir: str | os.PathLike) -> bool:
    """Whether the open lock file `f` (from lock_run) is still the run folder's lock file."""
    return f is not None and not f.closed and _same_file(f, Path(run_dir) / LOCK)


def _same_file(f, path: Path) -> bool:
    try:
        a, b = os.fstat(f.fileno()), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def lock_held(run_dir: str | os.PathLike) -> bool:
    """A live process holds the run's lock (trains it); probed with a shared lock, released at once. No
    lock file, or a filesystem without locks: not held."""
    try:
        with open(Path(run_dir) / LOCK) as f:
            fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)  # closing the file releases it
    except BlockingIOError:
        return True
    except OSError:
        return False
    return False


def check_folder_name(key: str, name: object) -> str | None:
    """Why `name` (run_name, sweep_name) is not a plain folder name, or None when it is one."""
    text = str(name)
    if not text or "/" in text or "\\" in text or text in (".", "..") or text != text.strip() or "\0" in text:
        return f"{key}: must be a plain folder name (no '/', not empty, '.' or '..'), got {text!r}"
    return None
