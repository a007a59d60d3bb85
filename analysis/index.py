"""``index.csv`` at a sweep's root: one row per job folder, rebuilt from the run folders alone.

``SweepIndexCallback`` (a Hydra callback listed in conf/train.yaml, so bmimic never imports the
analysis) rebuilds it at the end of every job of a multirun and once all have returned;
``python -m analysis.index SWEEP`` rebuilds it by hand. Two jobs finishing together are safe: each rebuild holds an advisory
lock while it reads the folders and writes a unique temp file that os.replace moves into place, so
the file is always complete and the last rebuild saw every status written before it started.
"""

from bmimic.cli.startup import leave_working_directory

leave_working_directory(__spec__.name)  # first: under `python -m` (bmimic.cli.startup); no MuJoCo here

import logging
import sys
from pathlib import Path
from typing import Any

import pandas as pd
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from analysis import REFUSED, AnalysisError, error_line
from analysis.files import write_csv
from analysis.load import load_runs
from analysis.run_files import find_run_dirs
from bmimic.cli.common import path_arg
from bmimic.runs.atomic_io import folder_lock
from bmimic.runs.folder import (
    MULTIRUN_RECORD,
    SWEEP_INDEX,
    is_run_folder,
    lock_held,
    read_hydra_config,
    read_metrics,
    read_provenance,
    read_resolved_config,
)
from bmimic.runs.schema import BUDGET_KEYS, ENV_STEPS, ITERATION, WALL_TIME_S

log = logging.getLogger("analysis.index")

INDEX_NAME = SWEEP_INDEX

METRIC_KEYS = (
    "final_eval_failure_rate", "final_eval_success_rate", "final_robust_eval_failure_rate", "iterations",
    ENV_STEPS, WALL_TIME_S, "mean_episode_length", "max_episode_length", "num_bins",
)
"""metrics.json keys copied into the index (absent keys stay empty, e.g. for running jobs)."""

BUDGET_COLUMNS = BUDGET_KEYS
"""The budget each job trained under (its resolved config, else its composed one): budgets stay out of
job folder names, so this is where a smoke run's 4 iterations show beside a study's 10,000."""

INDEX_COLUMNS = [
    "job", "arm", "seed", "status", "error", ITERATION, "sampler", "overrides", "included", "problem",
    *METRIC_KEYS, *BUDGET_COLUMNS, "git_commit", "git_dirty",
]
"""Columns of index.csv; ``job`` is the run folder relative to the sweep (e.g. ``sampler=uniform/seed=0``)."""


def build_index(sweep_dir: str | Path) -> pd.DataFrame:
    """One row per job folder under ``sweep_dir`` with INDEX_COLUMNS (empty frame when there is none).

    ``arm``, ``seed``, ``status`` etc. are as in analysis.load.load_runs; the final metrics come
    from each job's metrics.json and ``git_commit``/``git_dirty`` from its provenance.json.
    """
    sweep_dir = Path(sweep_dir).resolve()
    if not find_run_dirs(sweep_dir):
        return pd.DataFrame(columns=INDEX_COLUMNS)
    runs = load_runs(sweep_dir, compare=False)  # a listing: runs of other bin layouts or budgets are listed too
    runs = runs[runs["status"] != "missing"].reset_index(drop=True)
    rows = []
    for run in runs.itertuples(index=False):
        run_dir = Path(run.run_dir)
        metrics = read_metrics(run_dir)  # {} when absent or broken: the run's status says why
        config = read_resolved_config(run_dir) or read_hydra_config(run_dir) or {}
        provenance = read_provenance(run_dir)
        git_entry = provenance.get("git")
        git = git_entry if isinstance(git_entry, dict) else {}
        dead = run.status == "running" and not lock_held(run_dir)  # killed: no process holds its lock
        rows.append({
            "job": run_dir.relative_to(sweep_dir).as_posix() if run_dir != sweep_dir else ".",
            **{c: getattr(run, c) for c in ("arm", "seed", "status", "error", "iteration", "sampler",
                                             "overrides", "included", "problem")},
            **({"status": "dead"} if dead else {}),
            **{k: metrics.get(k) for k in METRIC_KEYS},
            **{k: config.get(k) for k in BUDGET_COLUMNS},
            "git_commit": provenance.get("git_commit", git.get("commit")),
            "git_dirty": provenance.get("git_dirty", git.get("dirty")),
        })
    index = pd.DataFrame(rows, columns=INDEX_COLUMNS)
    for key in (*METRIC_KEYS, *BUDGET_COLUMNS):  # numbers, also where no job has the key yet (e.g. no robust evaluation)
        index[key] = pd.to_numeric(index[key], errors="coerce")
    return index


def write_index(sweep_dir: str | Path) -> Path:
    """Rebuild ``<sweep_dir>/index.csv`` from the job folders, atomically; return its path."""
    sweep_dir = Path(sweep_dir)
    if not sweep_dir.is_dir():
        raise AnalysisError(f"{sweep_dir}: sweep folder does not exist")
    if is_run_folder(sweep_dir):
        raise AnalysisError(f"{sweep_dir}: is a run folder, not a sweep folder (give the folder that holds the jobs)")
    index = sweep_dir / INDEX_NAME
    if index.is_file() and not written_by_index(index):
        raise AnalysisError(f"{index}: a file bmimic did not write (its first columns are not {', '.join(INDEX_COLUMNS[:3])}); "
                            "it is left as it is and nothing is written")
    if (any(sweep_dir.iterdir()) and not any((sweep_dir / name).is_file() for name in (MULTIRUN_RECORD, SWEEP_INDEX))
            and not find_run_dirs(sweep_dir)):
        raise AnalysisError(f"{sweep_dir}: holds files but is not a sweep folder (no {MULTIRUN_RECORD}, {SWEEP_INDEX} "
                            "or run folders); nothing is written there")
    with folder_lock(sweep_dir):  # a flock on the folder itself: no lock file left in the user's sweep
        return write_csv(sweep_dir / INDEX_NAME, build_index(sweep_dir))


def written_by_index(path: Path) -> bool:
    """Whether an existing index.csv is one this module wrote (any version: its header begins with job, arm
    and has status), so that rebuilding it replaces nothing of the user's (issue 77's second round: a
    user's own index.csv was replaced by an empty index)."""
    try:
        with open(path, "rb") as f:
            header = f.read(4096).split(b"\n", 1)[0].decode("utf-8", "replace").strip().split(",")
    except OSError:
        return False
    return header[:2] == ["job", "arm"] and "status" in header


class SweepIndexCallback(Callback):
    """Rebuilds ``<sweep>/index.csv`` when a job of a multirun ends (in the job's process) and once
    every job has returned; the index is rebuildable, so a failure here never fails a job or a sweep."""

    def on_job_end(self, config: DictConfig, job_return: Any = None, **kwargs: Any) -> None:
        if OmegaConf.select(config, "hydra.mode") != RunMode.MULTIRUN:
            return
        try:
            write_index(Path(str(config.hydra.sweep.dir)))
        except Exception as e:  # noqa: BLE001 - the index is rebuildable; never fail a job over it
            log.warning("could not update the sweep index: %s", e)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        if not sweep_dir.is_dir():
            return
        try:
            path = write_index(sweep_dir)
            # One closing line per multirun is bmimic.sweeping.outcomes' (with the report command).
            log.debug("sweep index: %s%s", path, _status_summary(path))
        except Exception as e:  # noqa: BLE001 - rebuildable with python -m analysis.index; never fail the sweep
            log.warning("could not write the sweep index of %s: %s", sweep_dir, e)


def _status_summary(index_csv: Path) -> str:
    statuses = pd.read_csv(index_csv)["status"].fillna("").astype(str).tolist()
    counts: dict[str, int] = {}
    for s in statuses:
        counts[s] = counts.get(s, 0) + 1
    return f" ({len(statuses)} jobs: " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + ")"


def main(argv: list[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m analysis.index", description="Rebuild a sweep's index.csv "
                                     "from its job folders.")
    parser.add_argument("sweep", type=path_arg, help="the sweep folder (outputs/sweeps/<sweep_name>)")
    args = parser.parse_args(argv)
    try:
        path = write_index(args.sweep)
    except REFUSED as e:
        print(error_line(e), file=sys.stderr)
        return 2
    print(f"index written to {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
