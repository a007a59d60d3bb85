"""How the jobs of a multirun ended: each job records its outcome (done, done before, locked, refused,
failed), and the callback prints the summary once every job has returned and exits non-zero when any
job failed or was refused.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path
from typing import Any, Sequence

from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from bmimic.cli.common import shell_arg
from bmimic.runs import safe_read
from bmimic.runs.folder import atomic_write_json

log = logging.getLogger("bmimic.launch")

OUTCOMES_ENV = "BMIMIC_SWEEP_OUTCOMES"
"""Folder where the jobs of the running multirun record how they ended (set by the callback for the
launcher's processes: in-process, joblib workers and submitit jobs inherit the environment)."""
FAILED_OUTCOMES = ("failed", "refused")


def record_job_outcome(job_dir: str | os.PathLike, outcome: str, message: str | None = None) -> None:
    """Record one job's end for the multirun summary: done, done before, locked, refused or failed."""
    folder = os.environ.get(OUTCOMES_ENV)
    if not folder:
        return
    job_dir = Path(job_dir).resolve()
    name = hashlib.sha1(str(job_dir).encode()).hexdigest()[:16]
    try:
        atomic_write_json(Path(folder) / f"{name}.json", {"job": str(job_dir), "outcome": outcome,
                                                          "message": message})
    except OSError as e:  # the summary is a convenience; the job's own status.json is the record
        log.warning("could not record the outcome of %s: %s", job_dir, e)


def read_job_outcomes(folder: Path) -> list[dict]:
    """The outcomes the jobs recorded in `folder`."""
    out = []
    for path in sorted(Path(folder).glob("*.json")):
        try:
            item = safe_read.read_json(path)
        except (OSError, ValueError):
            continue
        if isinstance(item, dict):
            out.append(item)
    return out


def outcome_summary(outcomes: Sequence[dict], sweep_dir: Path) -> tuple[str, list[str]]:
    """(one summary line, one line per failed or refused job) of a multirun's outcomes."""
    counts: dict[str, int] = {}
    for o in outcomes:
        counts[o["outcome"]] = counts.get(o["outcome"], 0) + 1
    line = f"{len(outcomes)} job{'' if len(outcomes) == 1 else 's'}: " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items()))
    failed = []
    for o in outcomes:
        if o["outcome"] in FAILED_OUTCOMES:
            job = Path(o["job"])
            rel = job.relative_to(sweep_dir.resolve()) if job.is_relative_to(sweep_dir.resolve()) else job
            failed.append(f"  {o['outcome']}: {rel}: {o.get('message') or ''}")
    return line, failed



class SweepOutcomesCallback(Callback):
    """Prints how the jobs of a multirun ended once every job has returned, and exits non-zero (after
    every job ran) when any failed or was refused (conf/train.yaml lists it; the sweep's index.csv is
    analysis.index.SweepIndexCallback's)."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Give the jobs a folder to record their outcomes in (through OUTCOMES_ENV)."""
        sweep_dir = Path(str(config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)  # on the shared filesystem, for SLURM jobs too
        self._outcomes = Path(tempfile.mkdtemp(prefix=".outcomes-", dir=sweep_dir))
        self._previous_env = os.environ.get(OUTCOMES_ENV)
        os.environ[OUTCOMES_ENV] = str(self._outcomes)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Print how the jobs ended; exit 1 when any failed or was refused."""
        sweep_dir = Path(str(config.hydra.sweep.dir))
        folder = getattr(self, "_outcomes", None)
        if folder is None:
            return
        outcomes = read_job_outcomes(folder)
        shutil.rmtree(folder, ignore_errors=True)
        if self._previous_env is None:
            os.environ.pop(OUTCOMES_ENV, None)
        else:
            os.environ[OUTCOMES_ENV] = self._previous_env
        if not outcomes:
            return
        line, failed = outcome_summary(outcomes, sweep_dir)
        # The one closing line of a multirun; its command pastes back into a shell (shell_arg).
        print(f"{line} -> {sweep_dir}; next: bmimic-report {shell_arg(sweep_dir)}")
        if failed:
            print(f"{len(failed)} job(s) failed or were refused:", *failed, sep="\n", file=sys.stderr)
            sys.exit(1)
