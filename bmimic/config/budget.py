"""How long training would take on a CPU, and the one-line refusal of a run or sweep that would take
days there (a study's 10,000 iterations are hours on a GPU and weeks on a laptop).

The estimate is training alone, from a cost model of full PPO iterations (collection and update) on a
CPU, measured: each control step of the batch costs CPU_S_PER_STEP plus CPU_S_PER_ENV_STEP per env,
ppo.num_steps_per_env steps per iteration (capped by time_limit_s). Evaluations, the one-time kernel
compile and other processes on the same cores come on top. Only CPU runs are checked: on a GPU the
same budgets are what the studies are for. Torch-free, except the device resolution of a sweep.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Sequence

from bmimic import BmimicError
from bmimic.training.config import launch_end_iteration

CPU_S_PER_STEP = 0.011
"""Seconds of one control step of a training iteration on a CPU whatever the env count (Python, torch
and the PPO update's share): 0.6 s per 24-step iteration at 8 envs and 3.0 s at 64 envs on the 2-core
development CPU, Warp's CPU backend, machine otherwise idle (docs/benchmarks.md, 2026-11-25)."""
CPU_S_PER_ENV_STEP = 0.0018
"""Seconds each env adds to a control step on a CPU (the same measurement; Warp's CPU backend runs one
thread, so more cores change it little)."""

SMOKE_HINT = "max_iterations=4"
"""The override that makes any study a smoke run on a CPU (with the CPU's default of 8 envs)."""


class BudgetError(BmimicError):
    """A run or sweep whose estimated CPU training time is over max_cpu_hours."""


def optional_key(cfg: Any, key: str) -> Any:
    """`cfg`'s value of a top-level key that older run configs and plain namespaces may lack (None then)."""
    return cfg.get(key) if hasattr(cfg, "get") else getattr(cfg, key, None)


def cpu_training_s(cfg: Any, done_iterations: int = 0) -> float:
    """Estimated seconds of training on a CPU for `cfg` after runtime resolution (num_envs and
    max_iterations filled), from `done_iterations` on (a resume) to max_iterations or stop_at_iteration."""
    end = launch_end_iteration(cfg.max_iterations, optional_key(cfg, "stop_at_iteration"))
    iterations = max(0, end - int(done_iterations))
    seconds = iterations * int(cfg.ppo.num_steps_per_env) * (CPU_S_PER_STEP + CPU_S_PER_ENV_STEP * int(cfg.num_envs))
    limit = optional_key(cfg, "time_limit_s")
    return min(seconds, float(limit)) if limit else seconds


def _hours(seconds: float) -> str:
    hours = seconds / 3600.0
    return f"{hours:.0f} h" if hours >= 10 else f"{hours:.1f} h" if hours >= 0.1 else f"{seconds / 60:.0f} min"


def check_cpu_budget(seconds: Sequence[float], limit_h: float | None, sizes: str) -> None:
    """Raise BudgetError when the jobs' summed estimate (`seconds`, one per job, run one after another)
    is over `limit_h` hours (None: no limit). `sizes` says what was estimated, for the message."""
    total = float(sum(seconds))
    if limit_h is None or total <= float(limit_h) * 3600.0:
        return
    what = "this run" if len(seconds) == 1 else f"this sweep's {len(seconds)} jobs, one after another,"
    raise BudgetError(
        f"{what} would train for about {_hours(total)} on this CPU ({sizes}; ~{_hours(total / len(seconds))} a "
        f"job at a measured CPU rate), over max_cpu_hours={float(limit_h):g}: add {SMOKE_HINT} for a smoke run, or accept it with "
        f"max_cpu_hours={max(1, math.ceil(total / 3600.0))} (null: no limit)")


def describe_sizes(cfgs: Sequence[Any]) -> str:
    """`10000 iterations x 8 envs x 24 steps` (of the largest job of several)."""
    c = max(cfgs, key=lambda c: int(c.max_iterations) * int(c.num_envs) * int(c.ppo.num_steps_per_env))
    largest = "the largest job: " if len(cfgs) > 1 else ""
    return f"{largest}{c.max_iterations} iterations x {c.num_envs} envs x {c.ppo.num_steps_per_env} steps"


def check_sweep(jobs: Sequence[Any], resolve: Callable[[str], str] | None = None) -> None:
    """A multirun's jobs (bmimic.sweeping.jobs.Job, each with its composed config), resolved for this
    machine, refused together (BudgetError) when their CPU training would exceed max_cpu_hours; jobs
    already done are not counted. bmimic.launch_guard calls it before any job runs. `resolve`: the device
    resolution (default bmimic.runtime.resolve_device, which imports torch; a dry run passes guess_device)."""
    from omegaconf import OmegaConf

    from bmimic.config import resolve_runtime
    from bmimic.runtime import resolve_device

    resolve = resolve or resolve_device
    cfgs: list = []
    devices: dict = {}
    for job in jobs:
        if job.config is None or job.status == "done":
            continue
        requested = str(job.config.device)
        device = devices.setdefault(requested, resolve(requested))
        if device == "cpu":
            cfg = OmegaConf.create(OmegaConf.to_container(job.config, resolve=True))
            resolve_runtime(cfg, device)
            cfgs.append((cfg, job.iteration if job.status != "new" else 0))
    if cfgs:
        limits = {c.max_cpu_hours for c, _ in cfgs}
        check_cpu_budget([cpu_training_s(c, done or 0) for c, done in cfgs], None if None in limits else min(limits),
                         describe_sizes([c for c, _ in cfgs]))


__all__ = ["CPU_S_PER_ENV_STEP", "CPU_S_PER_STEP", "SMOKE_HINT", "BudgetError", "check_cpu_budget", "check_sweep", "cpu_training_s",
           "describe_sizes"]
