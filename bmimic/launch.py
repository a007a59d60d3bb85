"""Sweep support: the dry run, GPU slots for parallel jobs, the sweep index callback, error history.

    python -m bmimic.launch list +sweep=gamma                 # the jobs of a study, their folders and status
    python -m bmimic.launch list +sweep=gamma seed=0 sampler.gamma=0.5,0.9   # with overrides, as for train

The dry run expands a multirun exactly as `python -m bmimic.train -m <same overrides>` would (Hydra's
own config loader and BasicSweeper cross product), composes every job's config and resolves its
folder, so what it prints is what the sweep will do, including which jobs are already done.

Parallel jobs on one machine (`hydra/launcher=joblib_gpus`) run in joblib's worker processes, which
are reused from job to job. A CUDA context binds a process to the GPUs visible when it was created,
so each worker claims one GPU slot the first time it runs a job, keeps it for its lifetime, and
makes only that slot's GPU visible before torch or warp touch CUDA. Slots are claimed with file
locks, so two workers never hold the same slot even when jobs finish out of order; slot k uses GPU
k mod (number of GPUs), so n_jobs = 2 x GPUs puts two jobs on every GPU.

This module is imported by bmimic.train at start-up and by Hydra (the callback), so it keeps torch
and the simulator out of its imports.
"""

from __future__ import annotations

import argparse
import contextlib
import datetime as _dt
import fcntl
import hashlib
import logging
import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, open_dict

from bmimic import CONF_DIR

log = logging.getLogger("bmimic.launch")

SWEEPS_DIR = CONF_DIR / "sweep"
ERRORS_LOG = "errors.log"


# --------------------------------------------------------------------------------------------- dry run
@dataclass(frozen=True)
class Job:
    """One job of a multirun as the dry run sees it."""

    num: int
    """Hydra's job number (`hydra.job.num`), in launch order."""
    overrides: tuple[str, ...]
    """The job's task overrides: sweeper params and command line, one value per key."""
    run_dir: Path
    """The job's folder: `<hydra.sweep.dir>/<hydra.sweep.subdir>`."""
    status: str
    """`new` (no status.json yet), or status.json's `running` / `done` / `failed`."""
    iteration: int | None
    """Last iteration recorded in status.json (None for new jobs)."""


class SweepListError(Exception):
    """The overrides do not describe a sweep that can be listed (one-line message)."""


def available_studies() -> list[str]:
    """Study names in sweeps/ (the options of `+sweep=`)."""
    return sorted(p.stem for p in SWEEPS_DIR.glob("*.yaml"))


@contextlib.contextmanager
def _config_loader(config_dir: str | os.PathLike, config_name: str):
    """Hydra's config loader for `config_dir`, initialised as for `python -m bmimic.train`."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    import bmimic.config  # noqa: F401  (registers the config schemas and the bmimic.arm_dir resolver)

    with initialize_config_dir(config_dir=str(Path(config_dir).resolve()), version_base="1.3",
                               job_name=config_name):
        yield GlobalHydra.instance().config_loader()


def _expand(loader, config_name: str, overrides: Sequence[str]) -> tuple[DictConfig, list[list[str]]]:
    """(master config, each job's overrides) as `-m` would make them: the sweeper params crossed
    with the command line, where a command-line key replaces the params' entry (BasicSweeper)."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.types import RunMode

    overrides = [o for o in overrides if o not in ("-m", "--multirun")]
    master = loader.load_configuration(config_name, overrides, run_mode=RunMode.MULTIRUN)
    sweeper = master.hydra.sweeper
    if not str(sweeper.get("_target_", "")).endswith("BasicSweeper"):
        raise SweepListError(f"the dry run expands Hydra's basic sweeper only, not {sweeper._target_}")
    params = sweeper.get("params") or {}
    arguments = [f"{k}={v}" for k, v in params.items()] + list(master.hydra.overrides.task)
    parsed = OverridesParser.create(config_loader=loader).parse_overrides(arguments)
    (batch,) = BasicSweeper.split_arguments(parsed, None)
    return master, batch


def sweep_overrides(overrides: Sequence[str], config_dir: str | os.PathLike = CONF_DIR,
                    config_name: str = "train") -> list[list[str]]:
    """Each job's overrides for `python -m bmimic.train -m <overrides>`, in launch order (cheap:
    composes the primary config once)."""
    with _config_loader(config_dir, config_name) as loader:
        return _expand(loader, config_name, overrides)[1]


def list_jobs(overrides: Sequence[str], config_dir: str | os.PathLike = CONF_DIR,
              config_name: str = "train") -> tuple[Path, list[Job]]:
    """(sweep folder, jobs) of `python -m bmimic.train -m <overrides>`, without running anything.

    Builds every job's config with Hydra's sweep loader, as the launcher does (about a second per
    job), so the folders are resolved exactly and a job that would not compose fails here.
    """
    from hydra.core.hydra_config import HydraConfig

    from bmimic.config import check_composed

    with _config_loader(config_dir, config_name) as loader:
        master, batch = _expand(loader, config_name, overrides)
        jobs = []
        for num, job_overrides in enumerate(batch):
            cfg = loader.load_sweep_config(master, list(job_overrides))
            with open_dict(cfg):
                cfg.hydra.job.num = num
                cfg.hydra.job.id = f"{cfg.hydra.job.name}_{num}"
            HydraConfig.instance().set_config(cfg)  # as the launcher does: subdir may use ${hydra:...}
            check_composed(cfg, cfg.hydra.runtime.choices)  # what the job would refuse, refused here
            run_dir = Path(str(cfg.hydra.sweep.dir)) / str(OmegaConf.select(cfg, "hydra.sweep.subdir"))
            status = _read_status(run_dir)
            jobs.append(Job(num, tuple(job_overrides), run_dir, status.get("status", "new"),
                            status.get("iteration")))
        return Path(str(master.hydra.sweep.dir)), jobs


def _read_status(run_dir: Path) -> dict:
    import json

    try:
        data = json.loads((run_dir / "status.json").read_text())
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def format_jobs(sweep_dir: Path, jobs: Sequence[Job]) -> str:
    """The dry run's report: shared overrides once, then one line per job, then status counts."""
    common = [o for o in jobs[0].overrides if all(o in j.overrides for j in jobs)] if jobs else []
    lines = [f"sweep folder: {sweep_dir}", f"every job: {' '.join(common) or '(no overrides)'}",
             f"{'#':>4}  {'status':<8} {'iter':>6}  job folder (under the sweep folder)"]
    for job in jobs:
        rel = job.run_dir.relative_to(sweep_dir) if job.run_dir.is_relative_to(sweep_dir) else job.run_dir
        it = "" if job.iteration is None else str(job.iteration)
        lines.append(f"{job.num:>4}  {job.status:<8} {it:>6}  {rel}")
    counts: dict[str, int] = {}
    for job in jobs:
        counts[job.status] = counts.get(job.status, 0) + 1
    done = counts.get("done", 0)
    summary = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    lines.append(f"{len(jobs)} jobs ({summary}); a run would train {len(jobs) - done} and skip {done} done")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bmimic.launch",
        description="Dry run of a sweep: list the jobs `python -m bmimic.train -m OVERRIDES` would run, "
                    "their folders and status, without running anything.",
        epilog=f"studies: {', '.join(available_studies())}",
    )
    parser.add_argument("command", choices=["list"], help="list: print the jobs of the sweep")
    parser.add_argument("overrides", nargs="*", help="Hydra overrides, as for bmimic.train (e.g. +sweep=gamma)")
    args = parser.parse_args(argv)
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from bmimic import BmimicError

    try:
        sweep_dir, jobs = list_jobs(args.overrides)
    except (SweepListError, HydraException, OmegaConfBaseException, BmimicError) as e:
        msg = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        if "sweep" in msg and "Could not" in msg:
            msg += f" (studies: {', '.join(available_studies())})"
        print(f"error: {msg}", file=sys.stderr)
        return 2
    print(format_jobs(sweep_dir, jobs))
    return 0


# --------------------------------------------------------------------------------------------- GPU slots
def parse_visible_devices(value: str) -> list[str]:
    """Device ids in a CUDA_VISIBLE_DEVICES value, as CUDA reads it (stops at an empty or negative entry)."""
    devices = []
    for item in value.split(","):
        item = item.strip()
        if not item or item.startswith("-"):
            break
        devices.append(item)
    return devices


def visible_gpus(environ: dict[str, str] | None = None) -> list[str]:
    """GPUs this process may use, without initialising CUDA: CUDA_VISIBLE_DEVICES, else nvidia-smi."""
    environ = os.environ if environ is None else environ
    if "CUDA_VISIBLE_DEVICES" in environ:
        return parse_visible_devices(environ["CUDA_VISIBLE_DEVICES"])
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=index", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=30, check=True)
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in out.stdout.splitlines() if line.strip()]


def gpu_slots(jobs_per_gpu: int = 1) -> int:
    """Concurrent jobs for `jobs_per_gpu` jobs on each visible GPU (at least 1: CPU-only machines)."""
    if int(jobs_per_gpu) < 1:
        raise ValueError(f"jobs_per_gpu must be >= 1, got {jobs_per_gpu}")
    return max(1, len(visible_gpus()) * int(jobs_per_gpu))


if not OmegaConf.has_resolver("bmimic.gpu_slots"):
    OmegaConf.register_new_resolver("bmimic.gpu_slots", gpu_slots)


def slot_order(job_num: int, num_slots: int) -> list[int]:
    """Slots in the order a job tries them: its own `job_num % num_slots` first, then the next ones."""
    if num_slots < 1:
        raise ValueError(f"num_slots must be >= 1, got {num_slots}")
    first = job_num % num_slots
    return [(first + i) % num_slots for i in range(num_slots)]


def slot_gpu(slot: int, gpus: Sequence[str]) -> str:
    """The GPU of a slot: round robin, so the first len(gpus) slots cover every GPU once."""
    if not gpus:
        raise ValueError("no GPUs to assign")
    return gpus[slot % len(gpus)]


def claim_slot(lock_dir: Path, job_num: int, num_slots: int) -> tuple[int, Any] | None:
    """Lock the first free slot in `slot_order`; (slot, open lock file) or None when all are taken.

    The lock lives as long as the returned file stays open (the process's lifetime for a worker);
    the OS drops it when the process dies, so a crashed worker never leaks its slot.
    """
    lock_dir.mkdir(parents=True, exist_ok=True)
    for slot in slot_order(job_num, num_slots):
        f = open(lock_dir / f"slot_{slot}.lock", "a")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        return slot, f
    return None


_claimed: dict[str, Any] = {}  # this process's slot: {"slot", "gpu", "lock"}; set once per process


def pin_job_to_gpu() -> str | None:
    """In a joblib worker, make one GPU visible to this process; returns it (None: nothing pinned).

    Call at the start of the job, before anything initialises CUDA. Only the joblib launchers pin:
    the basic launcher runs jobs one after another in the launching process, and SLURM gives each
    submitit job its own GPUs.
    """
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    if "joblib" not in str(hc.launcher.get("_target_", "")):
        return None
    if _claimed:  # a reused worker: its CUDA context (if any) is bound to the GPU pinned first
        log.info("GPU slot %d: CUDA_VISIBLE_DEVICES=%s (held by worker pid %d since its first job)",
                 _claimed["slot"], _claimed["gpu"], os.getpid())
        return _claimed["gpu"]
    gpus = visible_gpus()
    if not gpus:
        return None
    from joblib import effective_n_jobs

    num_slots = max(1, effective_n_jobs(int(hc.launcher.n_jobs)))
    key = hashlib.sha1(str(Path(str(hc.sweep.dir)).resolve()).encode()).hexdigest()[:16]
    lock_dir = Path(tempfile.gettempdir()) / "bmimic-gpu-slots" / key
    claim = claim_slot(lock_dir, int(hc.job.num), num_slots)
    if claim is None:  # more live workers than n_jobs: should not happen; share rather than stall
        slot, lock = int(hc.job.num) % num_slots, None
        log.warning("all %d GPU slots are held; job %d shares slot %d", num_slots, hc.job.num, slot)
    else:
        slot, lock = claim
    gpu = slot_gpu(slot, gpus)
    if "torch" in sys.modules and sys.modules["torch"].cuda.is_initialized():
        log.warning("CUDA was initialised before the GPU slot was chosen; CUDA_VISIBLE_DEVICES=%s "
                    "may not take effect in this process", gpu)
    os.environ["CUDA_VISIBLE_DEVICES"] = gpu
    _claimed.update(slot=slot, gpu=gpu, lock=lock)
    log.info("GPU slot %d of %d: CUDA_VISIBLE_DEVICES=%s (worker pid %d)", slot, num_slots, gpu, os.getpid())
    return gpu


# --------------------------------------------------------------------------------------------- error history
def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def append_error_log(run_dir: str | os.PathLike, headline: str, details: str = "") -> Path:
    """Add a timestamped entry to `<run_dir>/errors.log` (kept across retries; status.json is not),
    as one atomic replace serialised against concurrent appenders."""
    from bmimic.runs import atomic_append_text

    entry = f"=== {_now()} {headline}\n{details.rstrip()}\n" if details.strip() else f"=== {_now()} {headline}\n"
    return atomic_append_text(Path(run_dir) / ERRORS_LOG, entry)


def note_previous_attempt(run_dir: str | os.PathLike, status: dict) -> None:
    """Before retrying a sweep job, record how its previous attempt ended when it did not finish."""
    state = status.get("status")
    if state == "failed":
        append_error_log(run_dir, f"retrying after a failed attempt (iteration {status.get('iteration')}, "
                                  f"updated {status.get('updated')}): {status.get('error')}")
    elif state == "running":
        append_error_log(run_dir, f"previous attempt stopped while running (iteration {status.get('iteration')}, "
                                  f"updated {status.get('updated')}): killed, preempted or timed out; resuming")


# --------------------------------------------------------------------------------------------- job outcomes
OUTCOMES_ENV = "BMIMIC_SWEEP_OUTCOMES"
"""Folder where the jobs of the running multirun record how they ended (set by the callback for the
launcher's processes: in-process, joblib workers and submitit jobs inherit the environment)."""
FAILED_OUTCOMES = ("failed", "refused")


def record_job_outcome(job_dir: str | os.PathLike, outcome: str, message: str | None = None) -> None:
    """Record one job's end for the multirun summary: done, done before, locked, refused or failed."""
    folder = os.environ.get(OUTCOMES_ENV)
    if not folder:
        return
    from bmimic.runs import atomic_write_json

    job_dir = Path(job_dir).resolve()
    name = hashlib.sha1(str(job_dir).encode()).hexdigest()[:16]
    try:
        atomic_write_json(Path(folder) / f"{name}.json", {"job": str(job_dir), "outcome": outcome,
                                                          "message": message})
    except OSError as e:  # the summary is a convenience; the job's own status.json is the record
        log.warning("could not record the outcome of %s: %s", job_dir, e)


def read_job_outcomes(folder: Path) -> list[dict]:
    import json

    out = []
    for path in sorted(Path(folder).glob("*.json")):
        try:
            item = json.loads(path.read_text())
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
    line = f"{len(outcomes)} jobs: " + ", ".join(f"{n} {k}" for k, n in sorted(counts.items()))
    failed = []
    for o in outcomes:
        if o["outcome"] in FAILED_OUTCOMES:
            job = Path(o["job"])
            rel = job.relative_to(sweep_dir.resolve()) if job.is_relative_to(sweep_dir.resolve()) else job
            failed.append(f"  {o['outcome']}: {rel}: {o.get('message') or ''}")
    return line, failed


# --------------------------------------------------------------------------------------------- sweep index
class SweepIndexCallback(Callback):
    """Writes `<sweep>/index.csv` once every job of a multirun has returned, prints how the jobs
    ended, and exits non-zero (after every job ran) when any failed or was refused (conf/train.yaml)."""

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)  # on the shared filesystem, for SLURM jobs too
        self._outcomes = Path(tempfile.mkdtemp(prefix=".outcomes-", dir=sweep_dir))
        self._previous_env = os.environ.get(OUTCOMES_ENV)
        os.environ[OUTCOMES_ENV] = str(self._outcomes)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(str(config.hydra.sweep.dir))
        failed: list[str] = []
        folder = getattr(self, "_outcomes", None)
        if folder is not None:
            outcomes = read_job_outcomes(folder)
            shutil.rmtree(folder, ignore_errors=True)
            if self._previous_env is None:
                os.environ.pop(OUTCOMES_ENV, None)
            else:
                os.environ[OUTCOMES_ENV] = self._previous_env
            if outcomes:
                line, failed = outcome_summary(outcomes, sweep_dir)
                print(line)
        if sweep_dir.is_dir():
            try:
                from analysis.index import write_index

                path = write_index(sweep_dir)
                print(f"sweep index: {path}{_status_summary(path)}")
            except Exception as e:  # the index is rebuildable (python -m analysis.index); never fail the sweep
                log.warning("could not write the sweep index of %s: %s", sweep_dir, e)
        if failed:
            print(f"{len(failed)} job(s) failed or were refused:", *failed, sep="\n", file=sys.stderr)
            sys.exit(1)


def _status_summary(index_csv: Path) -> str:
    import csv

    with open(index_csv, newline="") as f:
        statuses = [row.get("status", "") for row in csv.DictReader(f)]
    counts: dict[str, int] = {}
    for s in statuses:
        counts[s] = counts.get(s, 0) + 1
    return f" ({len(statuses)} jobs: " + ", ".join(f"{n} {s}" for s, n in sorted(counts.items())) + ")"


if __name__ == "__main__":
    sys.exit(main())
