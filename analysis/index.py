"""``index.csv`` at a sweep's root: one row per job folder, rebuilt from the run folders alone.

Training calls ``write_index(sweep_dir)`` at the end of every job; ``python -m analysis.index
SWEEP`` rebuilds it by hand. Two jobs finishing together are safe: each rebuild holds an advisory
lock while it reads the folders and writes a unique temp file that os.replace moves into place, so
the file is always complete and the last rebuild saw every status written before it started.
"""

from __future__ import annotations

import contextlib
import fcntl
import sys
from pathlib import Path

import pandas as pd

from analysis import AnalysisError
from analysis.files import write_csv
from analysis.load import find_run_dirs, load_runs, read_json

INDEX_NAME = "index.csv"
LOCK_NAME = ".index.lock"

METRIC_KEYS = (
    "final_eval_failure_rate", "final_eval_success_rate", "final_robust_eval_failure_rate", "iterations",
    "env_steps", "wall_time_s", "mean_episode_length", "max_episode_length", "num_bins",
)
"""metrics.json keys copied into the index (absent keys stay empty, e.g. for running jobs)."""

INDEX_COLUMNS = [
    "job", "arm", "seed", "status", "error", "iteration", "sampler", "overrides", "included", "problem",
    *METRIC_KEYS, "git_commit", "git_dirty",
]
"""Columns of index.csv; ``job`` is the run folder relative to the sweep (e.g. ``sampler=uniform/seed=0``)."""


def _json_or_empty(path: Path) -> dict:
    try:
        data = read_json(path)
    except AnalysisError:
        return {}  # a broken file is reported by the run's status; the index still lists the job
    return data if isinstance(data, dict) else {}


def build_index(sweep_dir: str | Path) -> pd.DataFrame:
    """One row per job folder under ``sweep_dir`` with INDEX_COLUMNS (empty frame when there is none).

    ``arm``, ``seed``, ``status`` etc. are as in analysis.load.load_runs; the final metrics come
    from each job's metrics.json and ``git_commit``/``git_dirty`` from its provenance.json.
    """
    sweep_dir = Path(sweep_dir).resolve()
    if not find_run_dirs(sweep_dir):
        return pd.DataFrame(columns=INDEX_COLUMNS)
    runs = load_runs(sweep_dir)
    runs = runs[runs["status"] != "missing"].reset_index(drop=True)
    rows = []
    for run in runs.itertuples(index=False):
        run_dir = Path(run.run_dir)
        metrics = _json_or_empty(run_dir / "metrics.json")
        provenance = _json_or_empty(run_dir / "provenance.json")
        git = provenance.get("git") if isinstance(provenance.get("git"), dict) else {}
        rows.append({
            "job": run_dir.relative_to(sweep_dir).as_posix() if run_dir != sweep_dir else ".",
            **{c: getattr(run, c) for c in ("arm", "seed", "status", "error", "iteration", "sampler",
                                             "overrides", "included", "problem")},
            **{k: metrics.get(k) for k in METRIC_KEYS},
            "git_commit": provenance.get("git_commit", git.get("commit")),
            "git_dirty": provenance.get("git_dirty", git.get("dirty")),
        })
    index = pd.DataFrame(rows, columns=INDEX_COLUMNS)
    for key in METRIC_KEYS:  # numbers, also where no job has the key yet (e.g. no robust evaluation)
        index[key] = pd.to_numeric(index[key], errors="coerce")
    return index


@contextlib.contextmanager
def _lock(sweep_dir: Path):
    """An exclusive advisory lock on ``<sweep>/.index.lock``; a no-op where the filesystem lacks locks."""
    with open(sweep_dir / LOCK_NAME, "a") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX)
        except OSError:
            pass  # e.g. some network filesystems: the atomic replace alone still keeps the file whole
        try:
            yield
        finally:
            with contextlib.suppress(OSError):
                fcntl.flock(f, fcntl.LOCK_UN)


def write_index(sweep_dir: str | Path) -> Path:
    """Rebuild ``<sweep_dir>/index.csv`` from the job folders, atomically; return its path."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise AnalysisError(f"{sweep_dir}: sweep folder does not exist")
    with _lock(sweep_dir):
        return write_csv(sweep_dir / INDEX_NAME, build_index(sweep_dir))


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) != 1 or argv[0].startswith("-"):
        print("usage: python -m analysis.index SWEEP_DIR", file=sys.stderr)
        return 2
    try:
        path = write_index(argv[0])
    except AnalysisError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"index written to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
