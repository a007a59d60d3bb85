"""One run folder's files, read through bmimic.runs.folder (the owner of the layout, torch-free):
finding run folders, their JSON and Hydra records, and whether a table can be used.
"""

from __future__ import annotations

import os
from pathlib import Path

import pyarrow.parquet as pq
import yaml

from analysis import AnalysisError
from bmimic.runs import safe_read
from bmimic.runs.folder import (
    CHECKPOINTS_DIR,
    HYDRA_DIR,
    RESOLVED_CONFIG,
    RunFolderError,
    is_run_folder,
    load_json,
    table_path,
)
from bmimic.runs.schema import (
    BIN,
    BIN_COLUMNS,
    CONDITION,
    ENV_STEPS,
    ERROR_COLUMNS,
    FAILURE_RATE,
    ITERATION,
    LOGISTICS_KEYS,
    SMOOTHNESS_COLUMNS,
    WALL_TIME_S,
)

REQUIRED_COLUMNS = {
    "train_metrics": [ITERATION, ENV_STEPS, WALL_TIME_S, "mean_episode_length", "mean_reward"],
    "eval": [ITERATION, ENV_STEPS, WALL_TIME_S, BIN, "bin_start_s", "bin_end_s", FAILURE_RATE, "failures"],
    "sampler": [ITERATION, BIN, "probability"],
    "eval_robust": [ITERATION, ENV_STEPS, WALL_TIME_S, BIN, "bin_start_s", "bin_end_s", FAILURE_RATE, "failures"],
    "clip_eval": [ITERATION, "clip", "failed"],
    "whole_clip": [ITERATION, CONDITION, "clip", "clip_duration_s", "rollouts", "completed", "transient_failures",
                   "later_failures"],
    "whole_clip_failures": [ITERATION, CONDITION, "clip", "failure_time_s", "transient"],
}
"""The columns the analysis reads from each table; other columns are carried along untouched."""
ONE_OF_COLUMNS = {"eval": ("start_episodes", "episodes"), "eval_robust": ("start_episodes", "episodes")}
"""Columns of which a table needs one: the episodes started per bin (`episodes` in tables written before
the per-visit accounting), what the overall failure rate divides by."""


def missing_columns(name: str, columns) -> list[str]:
    """The columns the analysis needs that table `name` lacks (its header is `columns`)."""
    missing = [c for c in REQUIRED_COLUMNS[name] if c not in columns]
    either = ONE_OF_COLUMNS.get(name, ())
    if either and not any(c in columns for c in either):
        missing.append(" or ".join(either))
    return missing

_EVAL_OPTIONAL = (*BIN_COLUMNS, "episodes", "segment", "clip", *ERROR_COLUMNS, *SMOOTHNESS_COLUMNS)
REPORT_COLUMNS: dict[str, tuple[str, ...] | None] = {
    "train_metrics": tuple(REQUIRED_COLUMNS["train_metrics"]),
    "eval": (*REQUIRED_COLUMNS["eval"], *_EVAL_OPTIONAL),
    "eval_robust": (*REQUIRED_COLUMNS["eval_robust"], *_EVAL_OPTIONAL),
    "sampler": (*REQUIRED_COLUMNS["sampler"], "bin_start_s", "bin_end_s", "clip", "episodes", "failures",
                "smoothed_failure_rate"),
    "clip_eval": None, "whole_clip": None, "whole_clip_failures": None,
}
"""Every column the analysis reads from each table, the optional ones included (None: the whole table):
what analysis.compact keeps of a committed run. ``episodes`` is the start count of evaluation tables
written before per-visit accounting."""

NEEDED_TABLES = ("train_metrics", "eval")
"""Tables a run must have to be included; ``sampler``, ``eval_robust`` (written with
``eval.robust=true``), ``clip_eval`` (the clip rollouts of phc and protomotions) and the ``whole_clip``
tables (eval.whole_clip) are optional (what uses them skips runs without them)."""

IGNORED_OVERRIDE_KEYS = {*LOGISTICS_KEYS, "task_name"}
"""Override keys that do not define an arm: the run schema's logistics keys (conf/train.yaml's
``exclude_keys``) and ``task_name`` (runs of an earlier bmimic)."""

SKIP_DIRS = {"report", CHECKPOINTS_DIR}
"""Folder names never searched for runs (report output, checkpoints)."""


MAX_SEARCHED_FOLDERS = 10_000
"""Most folders searched for runs under one path (a study of a hundred jobs has a few hundred): `/` or a home
folder is refused in seconds instead of walked for minutes."""


def find_run_dirs(root: str | Path) -> list[Path]:
    """All run folders at or below ``root``, sorted; run folders are not searched further."""
    root = Path(root)
    if not root.exists():
        raise AnalysisError(f"{root}: no such file or folder")
    if is_run_folder(root):
        return [root]
    found = []
    for searched, (dirpath, dirnames, _) in enumerate(os.walk(root)):
        if searched >= MAX_SEARCHED_FOLDERS:
            raise AnalysisError(f"{root}: more than {MAX_SEARCHED_FOLDERS} folders to search for runs; name the study's "
                                "sweep folder or its run folders")
        here = Path(dirpath)
        if here != root and is_run_folder(here):
            found.append(here)
            dirnames[:] = []
            continue
        dirnames[:] = sorted(d for d in dirnames if not d.startswith(".") and d not in SKIP_DIRS)
    return sorted(found)


def read_json(path: Path) -> dict | list | None:
    """The parsed JSON at ``path``, or None when the file is absent; AnalysisError when unreadable."""
    try:
        return load_json(path)
    except RunFolderError as e:
        raise AnalysisError(str(e)) from e


def read_config(run_dir: Path) -> dict:
    """The composed config from ``.hydra/config.yaml`` as a plain dict ({} when absent)."""
    path = run_dir / HYDRA_DIR / "config.yaml"
    if not path.is_file():
        return {}
    try:
        cfg = safe_read.read_yaml(path)
    except (OSError, ValueError, yaml.YAMLError) as e:  # ValueError: not UTF-8
        raise AnalysisError(f"{path}: not valid YAML ({e})") from e
    if not isinstance(cfg, dict):
        raise AnalysisError(f"{path}: expected a mapping at the top level, got {type(cfg).__name__}")
    resolved = read_json(run_dir / RESOLVED_CONFIG)
    return _with_values(cfg, resolved) if isinstance(resolved, dict) else cfg


def _with_values(cfg: dict, resolved: dict) -> dict:
    """`cfg` with each value written as an interpolation (`seed: ${oc.env:SLURM_ARRAY_TASK_ID}`, in runs
    recorded before bmimic recorded values) replaced by the run's resolved value (resolved_config.json)."""
    out = {}
    for key, value in cfg.items():
        if isinstance(value, dict):
            nested = resolved.get(key)
            out[key] = _with_values(value, nested if isinstance(nested, dict) else {})
        elif isinstance(value, str) and "${" in value and key in resolved:
            out[key] = resolved[key]
        else:
            out[key] = value
    return out


def _override_items(run_dir: Path) -> list[tuple[str, str]]:
    """``.hydra/overrides.yaml`` as (key, raw value) pairs in order, Hydra's ``+``/``++`` prefixes dropped and
    ``~key`` deletions (no value) skipped; empty when the file is absent."""
    path = run_dir / HYDRA_DIR / "overrides.yaml"
    if not path.is_file():
        return []
    try:
        items = safe_read.read_yaml(path) or []
    except (OSError, ValueError, yaml.YAMLError) as e:  # ValueError: not UTF-8
        raise AnalysisError(f"{path}: not valid YAML ({e})") from e
    if not isinstance(items, list):
        raise AnalysisError(f"{path}: expected a list of 'key=value' strings")
    out = []
    for item in items:
        text = str(item)
        if text.startswith("~") or "=" not in text:
            continue
        key, value = text.split("=", 1)
        out.append((key.lstrip("+"), value))
    return out


def read_sweep_file(run_dir: Path) -> str | None:
    """The ``sweep`` (or ``+sweep``) choice in ``.hydra/overrides.yaml``: the sweeps/ file a job was
    launched from, or None. A logistics key, so not part of the arm; it tells which jobs share a grid."""
    try:
        return next((value for key, value in _override_items(run_dir) if key == "sweep"), None)
    except AnalysisError:
        return None  # read_overrides names the problem


def read_overrides(run_dir: Path) -> dict[str, str]:
    """``.hydra/overrides.yaml`` as {key: raw value}, without seed/bookkeeping keys and deletions.

    Hydra's ``+``/``++`` prefixes are dropped; ``~key`` deletions carry no value and are skipped.
    """
    return {key: value for key, value in _override_items(run_dir)
            if key not in IGNORED_OVERRIDE_KEYS and not key.startswith("hydra.")}


def config_value(cfg: dict, dotted: str):
    """``cfg['a']['b']`` for ``'a.b'``, or None when any part is missing."""
    node = cfg
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


def parse_value(raw: str):
    """A command-line override value as int, float or bool where it reads as one, else the string."""
    for cast in (int, float):
        try:
            return cast(raw)
        except ValueError:
            pass
    if raw.lower() in ("true", "false"):
        return raw.lower() == "true"
    return raw


def seed_from_name(run_dir: Path) -> int | None:
    """The seed in a ``seed=<int>`` folder name, else None."""
    name = run_dir.name
    if name.startswith("seed="):
        try:
            return int(name.split("=", 1)[1])
        except ValueError:
            return None
    return None


def table_problem(run_dir: Path, name: str) -> str | None:
    """Why ``name`` cannot be used from ``run_dir`` (absent, unreadable, missing columns), or None."""
    path = table_path(run_dir, name)
    if not path.is_file():
        return f"no {path.name}"
    try:
        columns = set(pq.read_schema(safe_read.regular_file(path, run_dir)).names)
    except safe_read.UnsafeFileError as e:  # a FIFO, a device or a link out of the run: never opened by pyarrow
        return f"{path.name} refused: {str(e).partition(': ')[2]}"
    except Exception as e:  # pyarrow raises several types for truncated or foreign files
        return f"{path.name} unreadable ({type(e).__name__})"
    missing = missing_columns(name, columns)
    if missing:
        return f"{path.name} lacks columns {missing}"
    return None
