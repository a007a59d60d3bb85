"""A multirun as `python -m bmimic.train -m <overrides>` would launch it, expanded without running:
Hydra's own config loader and BasicSweeper cross product, every job's config composed and its
folder resolved, so the dry run (`python -m bmimic.launch list`) shows what the sweep will do,
including which jobs are already done.
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

from omegaconf import DictConfig, OmegaConf, open_dict

from bmimic import CONF_DIR, BmimicError
from bmimic.run_folder import lock_held, read_status
from bmimic.run_schema import ITERATION

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
    """`new` (no status.json yet), status.json's `running` / `done` / `interrupted` / `failed`, or `dead`
    (running, but no process holds its lock)."""
    iteration: int | None
    """Last iteration recorded in status.json (None for new jobs)."""
    config: Any = field(default=None, compare=False, repr=False)
    """The job's composed config, without its `hydra` node (bmimic.budget estimates from it)."""


class SweepListError(BmimicError):
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
    from hydra.types import RunMode

    overrides = [o for o in overrides if o not in ("-m", "--multirun")]
    master = loader.load_configuration(config_name, overrides, run_mode=RunMode.MULTIRUN)
    return master, _batch(loader, master)


def _batch(loader, master: DictConfig) -> list[list[str]]:
    """Each job's overrides of the multirun whose master config is `master`."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    sweeper = master.hydra.sweeper
    if not str(sweeper.get("_target_", "")).endswith("BasicSweeper"):
        raise SweepListError(f"the dry run expands Hydra's basic sweeper only, not {sweeper._target_}")
    params = sweeper.get("params") or {}
    arguments = [f"{k}={v}" for k, v in params.items()] + list(master.hydra.overrides.task)
    parsed = OverridesParser.create(config_loader=loader).parse_overrides(arguments)
    (batch,) = BasicSweeper.split_arguments(parsed, None)
    return batch


def sweep_overrides(overrides: Sequence[str], config_dir: str | os.PathLike = CONF_DIR,
                    config_name: str = "train") -> list[list[str]]:
    """Each job's overrides for `python -m bmimic.train -m <overrides>`, in launch order (cheap:
    composes the primary config once)."""
    with _config_loader(config_dir, config_name) as loader:
        return _expand(loader, config_name, overrides)[1]


def list_jobs(overrides: Sequence[str], config_dir: str | os.PathLike = CONF_DIR,
              config_name: str = "train") -> tuple[Path, list[Job]]:
    """(sweep folder, jobs) of `python -m bmimic.train -m <overrides>`, without running anything.

    Builds and checks every job's config with Hydra's sweep loader, as the sweep itself does before
    its first job (bmimic.launch_guard), so what is listed is what the sweep runs: a job that would be
    refused, or two jobs sharing a folder, fail here with the same line.
    """
    with _config_loader(config_dir, config_name) as loader:
        master, _ = _expand(loader, config_name, overrides)
        jobs = expand_jobs(loader, master)
        sweep_dir = Path(str(master.hydra.sweep.dir))
        check_jobs(jobs, sweep_dir, f"{master.hydra.job.name}.log")
        return sweep_dir, jobs


def expand_jobs(loader, master: DictConfig) -> list[Job]:
    """Every job of the multirun whose master config is `master`: composed, its folder resolved and
    its config checked as the job itself would check it before training (check_job); raises
    SweepListError (one line naming the job) for the first job that would be refused."""
    from hydra.core.hydra_config import HydraConfig

    from bmimic.config_checks import check_seed

    batch = _batch(loader, master)
    saved = HydraConfig.instance().cfg
    jobs = []
    checked: set[tuple[str, ...]] = set()
    try:
        for num, job_overrides in enumerate(batch):
            try:
                cfg = loader.load_sweep_config(master, list(job_overrides))
                with open_dict(cfg):
                    cfg.hydra.job.num = num
                    cfg.hydra.job.id = f"{cfg.hydra.job.name}_{num}"
                HydraConfig.instance().set_config(cfg)  # as the launcher does: subdir may use ${hydra:...}
                arm = tuple(o for o in job_overrides if not o.startswith("seed="))
                if arm in checked:  # an arm's jobs differ only in the seed: the other checks hold for all
                    check_seed(cfg)
                else:
                    check_job(cfg)
                    checked.add(arm)
                run_dir = Path(str(cfg.hydra.sweep.dir)) / str(OmegaConf.select(cfg, "hydra.sweep.subdir"))
            except Exception as e:  # noqa: BLE001 - Hydra, OmegaConf and bmimic errors alike: one line
                text = str(e).strip()
                msg = text.splitlines()[0] if text else type(e).__name__
                raise SweepListError(f"job {num} ({' '.join(job_overrides)}): {msg}") from None
            status = read_status(run_dir)
            state = status.get("status")
            if state == "running" and not lock_held(run_dir):
                state = "dead"  # its status says running, but no process holds its lock: killed
            jobs.append(Job(num, tuple(job_overrides), run_dir, "new" if state == "missing" else state,
                            status.get(ITERATION), OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])))
    finally:
        if saved is not None:
            HydraConfig.instance().cfg = saved
    return jobs


def check_job(cfg: DictConfig) -> None:
    """What a sweep job checks before it trains, without a device or a motion: the composed config
    (unknown keys, NaN, the sampler group) and its meaning (ranges, terms), resolved as on a CPU."""
    from bmimic.config import resolve_runtime
    from bmimic.config_checks import check_composed, validate

    check_composed(cfg, cfg.hydra.runtime.choices)
    task = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    device = str(task.device) if str(task.device).startswith("cuda") else "cpu"
    resolve_runtime(task, device)
    validate(task)


def check_jobs(jobs: Sequence[Job], sweep_dir: str | os.PathLike | None = None, log_name: str | None = None) -> None:
    """Refuse a multirun in which two jobs map to one folder: the second would be skipped as done or
    locked and the sweep would report success for an arm it never trained. With `sweep_dir`, also one
    whose sweep folder or a job's folder holds files that are not bmimic's (bmimic.run_claim: a launch
    writes only into its own folders; `log_name`: Hydra's log of a job, which a killed job leaves), or a
    job whose folder would lie outside the sweep folder."""
    from bmimic.run_claim import check_sweep_folder, foreign_entries, holds_run

    if sweep_dir is not None:
        if not any(job.run_dir.is_dir() and holds_run(job.run_dir) for job in jobs):  # else: this sweep's folder
            check_sweep_folder(sweep_dir)
        root = os.path.abspath(sweep_dir)
        for job in jobs:
            folder = os.path.abspath(job.run_dir)
            if os.path.commonpath([root, folder]) != root or folder == root:
                raise SweepListError(f"job {job.num} ({' '.join(job.overrides)}): its folder {job.run_dir} lies outside "
                                     f"the sweep folder {sweep_dir}")
            held = not job.run_dir.is_dir() or holds_run(job.run_dir)
            foreign = [] if held else foreign_entries(job.run_dir, log_name)
            if foreign:
                raise SweepListError(f"job {job.num} ({' '.join(job.overrides)}): its folder {job.run_dir} holds files "
                                     f"that are not a bmimic run ({', '.join(foreign[:4])}); a sweep writes only into "
                                     "new or empty folders or its own jobs: choose another sweep_name")
    seen: dict[Path, Job] = {}
    for job in jobs:
        key = job.run_dir.resolve()
        if key in seen:
            first = seen[key]
            differ = sorted({o.split("=", 1)[0] for o in set(first.overrides) ^ set(job.overrides)})
            raise SweepListError(
                f"jobs {first.num} and {job.num} map to one folder ({job.run_dir}): they differ only in "
                f"{', '.join(differ) or 'nothing'}, which job folder names leave out (budget and logistics keys); "
                "sweep over such keys in separate sweeps (sweep_name=...)")
        seen[key] = job


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
    lines.append(f"{len(jobs)} job{'' if len(jobs) == 1 else 's'} ({summary}); a run would train {len(jobs) - done} "
                 f"and skip {done} done")
    return "\n".join(lines)
