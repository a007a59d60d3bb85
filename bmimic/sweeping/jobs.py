"""A multirun as `python -m bmimic.train -m <overrides>` would launch it, expanded without running:
Hydra's own config loader and BasicSweeper cross product, every job's config composed and its
folder resolved, so the dry run (`python -m bmimic.launch list`) shows what the sweep will do,
including which jobs are already done.
"""

from __future__ import annotations

import copy
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence, cast

from omegaconf import DictConfig, OmegaConf, open_dict

from bmimic import CONF_DIR, BmimicError
from bmimic.config import config_loader, override_error
from bmimic.runs.folder import lock_held, read_status
from bmimic.runs.schema import ITERATION

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
    """The job's composed config, without its `hydra` node (bmimic.config.budget estimates from it)."""
    differs: dict = field(default_factory=dict, compare=False)
    """{key: (recorded, this job's)} where the run already in the folder was trained with other
    settings that change results (a smoke run's budget, another motion...): it is not this job."""


class SweepListError(BmimicError):
    """The overrides do not describe a sweep that can be listed (one-line message)."""


def available_studies() -> list[str]:
    """Study names in sweeps/ (the options of `+sweep=`)."""
    return sorted(p.stem for p in SWEEPS_DIR.glob("*.yaml"))


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
    with config_loader(config_dir, config_name) as loader:
        return _expand(loader, config_name, overrides)[1]


def list_jobs(overrides: Sequence[str], config_dir: str | os.PathLike = CONF_DIR,
              config_name: str = "train") -> tuple[Path, list[Job]]:
    """(sweep folder, jobs) of `python -m bmimic.train -m <overrides>`, without running anything.

    Builds and checks every job's config with Hydra's sweep loader, as the sweep itself does before
    its first job (bmimic.launch_guard), so what is listed is what the sweep runs: a job that would be
    refused, or two jobs sharing a folder, fail here with the same line.
    """
    with config_loader(config_dir, config_name) as loader:
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

    from bmimic.config.checks import check_seed

    batch = _batch(loader, master)
    saved = HydraConfig.instance().cfg
    jobs = []
    arms: dict[tuple[str, ...], DictConfig] = {}
    try:
        for num, job_overrides in enumerate(batch):
            arm = tuple(o for o in job_overrides if not o.startswith("seed="))
            try:
                seed = _plain_seed(job_overrides)
                if arm in arms and seed is not None:
                    # An arm's jobs differ only in the seed: its first job's config with this seed (composing
                    # each job again costs ~0.4 s on a small machine and yields the same config), and the
                    # other checks hold for all of them.
                    cfg = copy.deepcopy(arms[arm])
                    OmegaConf.set_readonly(cfg.hydra, None)  # (set_config below made it read-only)
                    cfg.hydra.overrides.task = list(job_overrides)
                    cfg.seed = seed
                else:
                    cfg = loader.load_sweep_config(master, list(job_overrides))
                with open_dict(cfg):
                    cfg.hydra.job.num = num
                    cfg.hydra.job.id = f"{cfg.hydra.job.name}_{num}"
                HydraConfig.instance().set_config(cfg)  # as the launcher does: subdir may use ${hydra:...}
                if arm in arms:
                    check_seed(cfg)
                else:
                    check_job(cfg)
                    arms[arm] = cfg
                run_dir = Path(str(cfg.hydra.sweep.dir)) / str(OmegaConf.select(cfg, "hydra.sweep.subdir"))
            except Exception as e:  # noqa: BLE001 - Hydra, OmegaConf and bmimic errors alike: one line
                msg = str(e) if isinstance(e, BmimicError) else override_error(e, job_overrides)
                raise SweepListError(f"job {num} ({' '.join(job_overrides)}): "
                                     f"{(msg.strip().splitlines() or [type(e).__name__])[0]}") from None
            status = read_status(run_dir)
            state = status.get("status")
            if state == "running" and not lock_held(run_dir):
                state = "dead"  # its status says running, but no process holds its lock: killed
            task = OmegaConf.masked_copy(cfg, [str(k) for k in cfg if k != "hydra"])
            differs = recorded_differences(run_dir, task) if state != "missing" else {}
            jobs.append(Job(num, tuple(job_overrides), run_dir, "new" if state == "missing" else cast(str, state),
                            status.get(ITERATION), task, differs))
    finally:
        if saved is not None:
            HydraConfig.instance().cfg = saved
    return jobs


def _plain_seed(job_overrides: Sequence[str]) -> int | None:
    """The job's `seed=<n>` as an int when it is a plain decimal integer (what a sweep's seeds are), else
    None (the job is then composed as Hydra would, with its own errors)."""
    values = [o.split("=", 1)[1].strip() for o in job_overrides if o.startswith("seed=")]
    if len(values) != 1 or not re.fullmatch(r"0|[1-9][0-9]*", values[0]):
        return None
    return int(values[0])


def check_job(cfg: DictConfig) -> None:
    """What a sweep job checks before it trains, without a device or a motion: the composed config
    (unknown keys, NaN, the sampler group) and its meaning (ranges, terms), resolved as on a CPU."""
    from bmimic.config import resolve_runtime
    from bmimic.config.checks import check_composed, validate

    check_composed(cfg, cfg.hydra.runtime.choices)
    task = OmegaConf.masked_copy(cfg, [str(k) for k in cfg if k != "hydra"])
    device = str(task.device) if str(task.device).startswith("cuda") else "cpu"
    resolve_runtime(task, device)
    validate(task, composed_checked=True)


def recorded_differences(run_dir: Path, task: DictConfig, device: str | None = None) -> dict[str, tuple[Any, Any]]:
    """{key: (recorded, this job's)} of the settings that change results in which the run in a job's
    folder differs from the job (`task`: its composed config without `hydra`); {} for the same job.

    The run's resolved_config.json (kept current by accepted resume changes) is compared with the
    job's config resolved for `device`, by default the kind of device the run trained on, so keys
    left to the machine (num_envs: null) compare as that run saw them (the job itself compares again
    on its own device before it skips a done run, bmimic.job); a run without one (an earlier
    bmimic's) is compared by its composed .hydra/config.yaml."""
    from bmimic.config import resolve_runtime
    from bmimic.runs.folder import read_hydra_config, read_resolved_config
    from bmimic.training.resume import job_differences

    recorded = read_resolved_config(run_dir)
    if recorded is not None:
        resolved = copy.deepcopy(task)
        kind = device or ("cuda" if str(recorded.get("device", "")).startswith("cuda") else "cpu")
        resolve_runtime(resolved, kind)
        new = cast(dict, OmegaConf.to_container(resolved, resolve=True))
    else:
        recorded = read_hydra_config(run_dir)
        new = cast(dict, OmegaConf.to_container(task, resolve=False))
    return job_differences(recorded, new)


def describe_differences(differs: dict[str, tuple[Any, Any]], limit: int = 4) -> str:
    """`key recorded -> this`, for the first `limit` keys (the budget's first: what a smoke run changes)."""
    from bmimic.runs.schema import BUDGET_KEYS
    from bmimic.training.resume import RESUME_BUDGET_KEYS

    keys = sorted(differs, key=lambda k: (k not in (*BUDGET_KEYS, *RESUME_BUDGET_KEYS), k))
    shown = [f"{k} {_short(differs[k][0])} -> {_short(differs[k][1])}" for k in keys[:limit]]
    return ", ".join(shown) + (f" and {len(keys) - limit} more" if len(keys) > limit else "")


def _short(value: Any) -> str:
    text = "null" if value is None else str(value)
    return text if len(text) <= 40 else text[:37] + "..."


def check_job_runs(jobs: Sequence[Job]) -> None:
    """Refuse a multirun in which a job's folder already holds a run trained with other settings
    (Job.differs): a smoke run of 4 iterations, say, would be skipped as done by the study and
    reported as one of its seeds. With resume=true a run whose differences a resume may make (its
    budget, the job's resume_allow_changes) is continued to this sweep's settings instead, as
    `resume=true max_iterations=N` continues a single run. SweepListError (one line) names the
    first such job, its folder, the keys and the ways out."""
    refused = [j for j in jobs if j.differs and not _continues(j)]
    if not refused:
        return
    first = refused[0]
    more = f" (and {len(refused) - 1} more job folder{'s' if len(refused) > 2 else ''})" if len(refused) > 1 else ""
    ways = "give a smoke test or variant its own sweep_name=..., or move that folder away"
    if _extendable(first):
        ways += ", or add resume=true to continue those runs with this sweep's budget"
    raise SweepListError(
        f"job {first.num} ({' '.join(first.overrides)}): its folder {first.run_dir} holds a run "
        f"({first.status}{'' if first.iteration is None else f' at iteration {first.iteration}'}) trained with other "
        f"settings ({describe_differences(first.differs)}){more}, which this sweep would take for its own; {ways}")


def _extendable(job: Job) -> bool:
    """Every way the run in the job's folder differs is one a resume may make (its budget)."""
    from bmimic.training.resume import RESUME_FREE_KEYS, key_allowed

    allowed = (*RESUME_FREE_KEYS, *(OmegaConf.select(job.config, "resume_allow_changes") or []))
    return all(key_allowed(k, allowed) for k in job.differs)


def _continues(job: Job) -> bool:
    """The job continues the run of other settings in its folder (resume=true, _extendable)."""
    from bmimic.training.resume import resume_request

    return resume_request(OmegaConf.select(job.config, "resume")) is not None and _extendable(job)


def check_jobs(jobs: Sequence[Job], sweep_dir: str | os.PathLike | None = None, log_name: str | None = None) -> None:
    """Refuse a multirun in which two jobs map to one folder: the second would be skipped as done or
    locked and the sweep would report success for an arm it never trained. With `sweep_dir`, also one
    whose sweep folder or a job's folder holds files that are not bmimic's (bmimic.runs.claim: a launch
    writes only into its own folders; `log_name`: Hydra's log of a job, which a killed job leaves), or a
    job whose folder would lie outside the sweep folder."""
    from bmimic.runs.claim import check_path, check_sweep_folder, foreign_entries, holds_run

    if sweep_dir is not None:
        check_path("hydra.sweep.dir", sweep_dir)  # a path the OS refuses by its length: one line, before any look-up
        for job in jobs:
            check_path(f"job {job.num}'s folder (hydra.sweep.dir and its overrides)", job.run_dir)
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
        other = f"  (holds a run with other settings: {describe_differences(job.differs, 2)})" if job.differs else ""
        lines.append(f"{job.num:>4}  {job.status:<8} {it:>6}  {rel}{other}")
    counts: dict[str, int] = {}
    for job in jobs:
        counts[job.status] = counts.get(job.status, 0) + 1
    done = sum(1 for job in jobs if job.status == "done" and not job.differs)
    summary = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    refused = sum(1 for job in jobs if job.differs and not _continues(job))
    continued = sum(1 for job in jobs if job.differs and _continues(job))
    outcome = (f"a run would refuse to start: {refused} job folder{'s hold runs' if refused > 1 else ' holds a run'} "
               "with other settings" if refused else
               f"a run would train {len(jobs) - done} and skip {done} done"
               + (f" (continuing {continued} run{'s' if continued > 1 else ''} with this budget)" if continued else ""))
    lines.append(f"{len(jobs)} job{'' if len(jobs) == 1 else 's'} ({summary}); {outcome}")
    return "\n".join(lines)


def done_run_differences(cfg: DictConfig, run_dir: Path) -> str | bool:
    """Whether a sweep job may skip the done run in its folder: False (the same job: skip it), True
    (other settings that a resume may change, and the job says resume=true: continue it), or the
    one-line reason it must not touch it (a run of other settings, e.g. a smoke run's budget).
    Compared on this job's device, as the job would train (recorded_differences)."""
    from bmimic.runtime import resolve_device
    from bmimic.training.resume import RESUME_FREE_KEYS, key_allowed, resume_request

    task = OmegaConf.masked_copy(cfg, [str(k) for k in cfg if k != "hydra"])
    differs = recorded_differences(run_dir, task, resolve_device(cfg.device))
    if not differs:
        return False
    allowed = (*RESUME_FREE_KEYS, *(cfg.resume_allow_changes or []))
    extendable = all(key_allowed(k, allowed) for k in differs)
    if extendable and resume_request(cfg.get("resume")) is not None:
        return True
    return (f"holds a run done with other settings ({describe_differences(differs)}); this job leaves it as it "
            "is" + ("; resume=true continues it with this job's budget" if extendable else "")
            + " (a smoke test or variant belongs under its own sweep_name=...)")
