"""A multirun as `python -m bmimic.train -m <overrides>` would launch it, expanded without running:
Hydra's own config loader and BasicSweeper cross product, every job's config composed and its
folder resolved, so the dry run (`python -m bmimic.launch list`) shows what the sweep will do,
including which jobs are already done.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from omegaconf import DictConfig, OmegaConf, open_dict

from bmimic import CONF_DIR
from bmimic.run_folder import read_status

SWEEPS_DIR = CONF_DIR / "sweep"


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
    import bmimic.sweeping.gpu_slots  # noqa: F401  (registers the bmimic.gpu_slots resolver)

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

    from bmimic.config_checks import check_composed

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
            status = read_status(run_dir)
            state = status.get("status")
            jobs.append(Job(num, tuple(job_overrides), run_dir, "new" if state == "missing" else state,
                            status.get("iteration")))
        return Path(str(master.hydra.sweep.dir)), jobs


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
