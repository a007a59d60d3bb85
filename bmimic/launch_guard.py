"""`LaunchGuard`: the Hydra callback (conf/train.yaml, listed first) that checks a launch before Hydra
creates or writes anything.

- A single run (`on_run_start`): the folder names are plain names, the run folder is claimed
  (bmimic.runs.claim: a fresh folder per launch, a pinned folder holding a run refused without
  resume), and a study's sweep parameters that the run does not follow without `-m` are said to be
  ignored (those the command line sets, or that the config already holds, are followed).
- A multirun (`on_multirun_start`): `sweep_name` is a plain name (the sweep folder stays under
  outputs/sweeps/), and every job is expanded, composed and checked as `python -m bmimic.launch list`
  does (bmimic.sweeping.jobs.check_jobs): a job that would be refused, or two jobs that map to one
  folder, stop the sweep before any job runs; so does a job folder that holds a run trained with
  other settings (a smoke run's budget: bmimic.sweeping.jobs.check_job_runs), and a sweep whose jobs
  would train longer on this CPU than max_cpu_hours (bmimic.config.budget).
- Both: a CUDA_VISIBLE_DEVICES that names a GPU twice (CUDA then sees none) is refused first.

A refusal is one `error:` line and exit status 2; nothing has been written.
"""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Any, cast

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf, read_write

from bmimic import BmimicError


def _refuse(e: BaseException) -> None:
    from bmimic.cli.common import first_line

    # (an OSError of the file system: the guard must refuse, since Hydra turns a callback's error into a warning
    # and goes on without it)
    said = f"{e.filename}: {e.strerror}" if isinstance(e, OSError) and e.strerror and e.filename else first_line(e)
    print(f"error: {said}", file=sys.stderr)
    sys.exit(2)


def ignored_sweep_params(config: DictConfig) -> list[str]:
    """The study's sweep parameters (hydra.sweeper.params) that a single run does not follow: those the
    command line does not set and whose sweep the run's config does not already hold (several values, or one
    the config has otherwise). A study that also sets a parameter's one value at the top level, for its
    torchrun jobs, leaves nothing ignored there."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    params = OmegaConf.select(config, "hydra.sweeper.params") or {}
    given = {o.split("=", 1)[0].lstrip("+~") for o in (OmegaConf.select(config, "hydra.overrides.task") or [])}
    choices = OmegaConf.select(config, "hydra.runtime.choices") or {}
    parser = OverridesParser.create()
    ignored = []
    for key, values in params.items():
        key = str(key)
        name = key.lstrip("+~")  # a sweep may add a key (+key): the command line then names it either way
        if name in given:
            continue
        try:
            override = parser.parse_override(f"{key}={values}")
        except Exception:  # noqa: BLE001 - Hydra's multirun reports a malformed sweep in its own words
            ignored.append(key)
            continue
        if not override.is_sweep_override():
            try:
                held = choices[name] if name in choices else OmegaConf.select(config, name, default=None)
            except Exception:  # noqa: BLE001 - an unresolvable value: the config checks report it in their words
                held = None
            if held is not None and str(held) == str(override.value()):
                continue
        ignored.append(key)
    return ignored


def _folder_name(config: DictConfig, key: str) -> None:
    from bmimic.runs.folder import check_folder_name

    try:
        value = config[key]
    except Exception:  # noqa: BLE001 - an unresolvable value: the config checks report it in their words
        return
    problem = check_folder_name(key, value)
    if problem:
        raise BmimicError(problem)


class LaunchGuard(Callback):
    """Checks and claims before Hydra writes (module doc)."""

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        from bmimic.runs.claim import claim, observe
        from bmimic.runtime import process_rank
        from bmimic.sweeping.gpu_slots import check_visible_devices
        from bmimic.training.resume import resume_request

        template = str(cast(dict, OmegaConf.to_container(config.hydra.run, resolve=False)).get("dir", ""))
        pinned = "${now:" not in template
        job_logging = config.hydra.get("job_logging") or {}
        log_name = f"{config.hydra.job.name}.log" if "file" in (job_logging.get("handlers") or {}) else None
        if process_rank() != 0:
            with contextlib.suppress(Exception):  # under torchrun rank 0 owns the (pinned) folder
                observe(str(config.hydra.run.dir), pinned, log_name)
            return
        try:
            check_visible_devices()
            if not pinned:
                _folder_name(config, "run_name")
            try:
                run_dir = str(config.hydra.run.dir)
                resume = resume_request(config.get("resume")) is not None
            except Exception as e:  # noqa: BLE001 - an interpolation that does not resolve
                raise BmimicError(f"hydra.run.dir: cannot be resolved: {str(e).splitlines()[0]}") from None
            claimed = claim(run_dir, pinned, resume, log_name)
        except (BmimicError, OSError) as e:
            _refuse(e)
            return
        if str(claimed.run_dir) != os.path.abspath(run_dir):
            with read_write(config.hydra.run):
                config.hydra.run.dir = str(claimed.run_dir)
        ignored = ignored_sweep_params(config)
        if ignored:
            study = OmegaConf.select(config, "hydra.runtime.choices.sweep") or "the study"
            print(f"warning: +sweep={study} sweeps {', '.join(ignored)}, which only a multirun expands; this "
                  f"single run ignores them (give each a value, or run the study with -m)", file=sys.stderr)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from hydra.core.global_hydra import GlobalHydra

        from bmimic.cli.extras import require_slurm
        from bmimic.config.budget import check_sweep
        from bmimic.sweeping.gpu_slots import check_visible_devices
        from bmimic.sweeping.jobs import check_job_runs, check_jobs, expand_jobs

        try:
            if str(OmegaConf.select(config, "hydra.launcher._target_") or "").endswith("SlurmLauncher"):
                require_slurm("the sweep's SLURM launcher")  # (one set in a sweep file, not on the command line)
            check_visible_devices()  # before the budget check, which would blame the CPU
            _folder_name(config, "sweep_name")
            jobs = expand_jobs(GlobalHydra.instance().config_loader(), config)
            check_jobs(jobs, str(config.hydra.sweep.dir), f"{config.hydra.job.name}.log")
            check_job_runs(jobs)  # a smoke run's folder is not the study's job
            check_sweep(jobs)  # a sweep that would train for a day or more on this CPU
        except (BmimicError, OSError) as e:
            _refuse(e)
