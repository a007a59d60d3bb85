"""Resume planning: where a launch trains, from which checkpoint, and which config changes it may make.

Everything here reads and decides; nothing writes. `plan_run` picks the run folder and checkpoint,
`check_resume_changes` compares the config with the one the checkpoint was trained with, and a
refused resume raises `ResumeRefusedError` (one line) before any file is touched.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Callable

from bmimic import BmimicError
from bmimic.runs import safe_read
from bmimic.runs.folder import (
    CHECKPOINTS_DIR,
    checkpoint_files,
    checkpoint_iteration,
    checkpoints_dir,
    is_run_folder,
    newest_iteration,
    read_resolved_config,
    read_status,
)
from bmimic.runs.schema import BUDGET_KEYS
from bmimic.training.checkpoints import is_latest, load_checkpoint_file, load_newest_intact

LAUNCH_KEYS = ("resume", "resume_allow_changes")
"""Keys that say how a launch treats an existing run, not how the run trains: never a change of the
run (resumes.json does not list them)."""
RESULT_NEUTRAL_KEYS = (*LAUNCH_KEYS, "device", "progress_bar", "verbose", "logger", "max_cpu_hours", "wandb_project",
                       "run_name", "sweep_name", "ppo.save_interval", "data.lafan_dir", "stop_at_iteration")
"""Keys that say where and how a run is launched and logged, never what it trains or for how long:
runs that differ only in these are the same job (bmimic.sweeping.jobs)."""
FIXED_BUDGET_KEYS = ("num_envs",)
"""Budget keys (runs.schema.BUDGET_KEYS) a resume keeps unless resume_allow_changes names them: the
number of worlds changes what each iteration trains on, not only for how long."""
EVAL_CADENCE_KEYS = ("eval.every_iters",)
"""How often a run is evaluated: not how much it trains (so not a budget key), but its tables depend
on it, and a resume may change it (to evaluate the rest of a run more or less often)."""
RESUME_BUDGET_KEYS = (*(k for k in BUDGET_KEYS if k not in FIXED_BUDGET_KEYS), *EVAL_CADENCE_KEYS)
"""How long a run trains and how often it is evaluated: its results depend on them (a smoke run of 4
iterations is not a study's job), but a resume may change them (to extend a run)."""
RESUME_FREE_KEYS = tuple(k for k in (*RESULT_NEUTRAL_KEYS, *RESUME_BUDGET_KEYS)
                         if k not in ("verbose", "data.lafan_dir"))
"""Keys a resume may change without naming them in resume_allow_changes: where and how long to run
and how to log, not what is trained. Changes are still recorded in resumes.json."""


class ResumeRefusedError(BmimicError):
    """A resume that would change, damage or mismatch the run it continues; nothing was written."""


# --------------------------------------------------------------------------------------------- config changes
def flatten_config(tree: Any, prefix: str = "") -> dict[str, Any]:
    """{'a.b.c': value} for every leaf of a nested dict (lists are leaves)."""
    if isinstance(tree, dict) and tree:
        out: dict[str, Any] = {}
        for key, value in tree.items():
            out.update(flatten_config(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: tree} if prefix else {}


def config_changes(old: dict, new: dict) -> dict[str, tuple[Any, Any]]:
    """{key: (old, new)} for every leaf that differs (missing on one side counts as a change)."""
    a, b = flatten_config(old), flatten_config(new)
    missing = object()
    out = {}
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key, missing), b.get(key, missing)
        if not _same_value(x, y):
            out[key] = (None if x is missing else x, None if y is missing else y)
    return out


def _same_value(x: Any, y: Any) -> bool:
    if isinstance(x, bool) or isinstance(y, bool):
        return x is y
    if isinstance(x, (int, float)) and isinstance(y, (int, float)):
        return x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))
    return x == y


def job_differences(old: dict | None, new: dict) -> dict[str, tuple[Any, Any]]:
    """{key: (old, new)} of every key but RESULT_NEUTRAL_KEYS that the config a run was trained with
    (`old`; None: nothing recorded, so nothing to tell) records and `new` sets otherwise: two configs
    that differ in none train the same job. A key the record lacks is not compared: an earlier bmimic
    had no such option, and a new option keeps the old behaviour by default."""
    if old is None:
        return {}
    recorded = flatten_config(old)
    return {k: v for k, v in config_changes(old, new).items()
            if k in recorded and not key_allowed(k, RESULT_NEUTRAL_KEYS)}


def refused_changes(changes: dict[str, tuple[Any, Any]], allowed: list[str] | tuple[str, ...]) -> list[str]:
    """Changed keys neither free nor named (or under a prefix named) in `allowed`."""
    return [k for k in changes if not key_allowed(k, (*RESUME_FREE_KEYS, *allowed))]


def key_allowed(key: str, allowed: list[str] | tuple[str, ...]) -> bool:
    """`key` is one of `allowed` or under one of them (`env` allows `env.rewards.x.weight`)."""
    return any(key == a or key.startswith(a + ".") for a in allowed)


# --------------------------------------------------------------------------------------------- the plan
def resume_request(resume: Any) -> str | None:
    """None (start fresh), "latest" (resume=true) or a path, from the `resume` config value."""
    if resume is None or resume is False or str(resume).strip().lower() in ("false", "none", "null", "no", "0", ""):
        return None
    if resume is True or str(resume).strip().lower() in ("true", "latest", "1", "yes"):
        return "latest"
    return str(resume)


@dataclasses.dataclass
class RunPlan:
    """Where a launch writes and what it continues from, decided before anything is written."""

    run_dir: Path
    """The folder this launch trains in."""
    launch_dir: Path
    """The folder Hydra made for this launch (run_dir, or removed when continuing another run)."""
    checkpoint: Path | None = None
    """The checkpoint loaded (None: a fresh run)."""
    state: dict | None = None
    """Its contents (read with weights_only)."""
    continues: bool = False
    """run_dir is an existing run that this launch continues (not a new folder)."""
    note: str = ""
    """What the planner had to do that the user must hear (e.g. passed over a damaged latest.pt)."""


def plan_run(resume: Any, launch_dir: Path, sweep_job: bool = False, pinned: bool = False,
             config: dict | None = None, allowed: list[str] | tuple[str, ...] = (),
             fill_defaults: Callable[[dict], dict] | None = None) -> RunPlan:
    """Decide where to train and from which checkpoint, reading but never writing.

    - no resume: a fresh run in launch_dir;
    - resume=true: a sweep job, and a single run whose folder was pinned (hydra.run.dir), continue
      their own folder, or start fresh there when it holds no checkpoint; another single run
      continues the newest run of the same run_name (launch_dir's siblings) whose config matches
      `config` (the launch's resolved config) up to the budget and logistics keys and `allowed`
      (ResumeRefusedError listing the candidates when none does); with no run at all, a fresh run;
    - resume=RUN_FOLDER or a checkpoint in one: continues that run from its newest intact checkpoint;
      an older checkpoint of a run starts a new run in launch_dir from it (a branch), and so does a
      checkpoint outside any run folder.

    A damaged latest.pt is passed over for the newest intact model_<it>.pt (`note` says so); a
    checkpoint refused as unsafe never is. Raises ResumeRefusedError / CheckpointError (one line).
    """
    launch_dir = Path(launch_dir)
    request = resume_request(resume)
    if request is None:
        return RunPlan(launch_dir, launch_dir)
    if request == "latest":
        if sweep_job or pinned or checkpoint_files(checkpoints_dir(launch_dir)):
            target = launch_dir
        else:
            parent = launch_dir.parent
            siblings = sorted((p for p in parent.iterdir() if p != launch_dir and p.is_dir()
                               and checkpoint_files(checkpoints_dir(p))), key=lambda p: p.name) \
                if parent.is_dir() else []
            if not siblings:
                return RunPlan(launch_dir, launch_dir, note=f"resume=true: no run with a checkpoint under "
                                                             f"{parent}; starting a fresh run")
            target = siblings[-1] if config is None else matching_run(siblings, config, allowed, fill_defaults)
        if not checkpoint_files(checkpoints_dir(target)):
            note = "" if sweep_job else f"resume=true: {target} holds no checkpoint; starting a fresh run there"
            return RunPlan(launch_dir, launch_dir, note=note)  # (a sweep job that never reached a checkpoint)
        path, state, note = load_newest_intact(checkpoints_dir(target))
        return RunPlan(target, launch_dir, path, state, True, note)

    path = Path(request).expanduser()
    if not path.exists():
        raise ResumeRefusedError(f"resume: {path} does not exist")
    if path.is_dir():
        ckpt_dir = checkpoints_dir(path) if checkpoints_dir(path).is_dir() else path
        run = ckpt_dir.parent if ckpt_dir.name == CHECKPOINTS_DIR else None
        checkpoint, state, note = load_newest_intact(ckpt_dir)
    else:
        ckpt_dir = path.parent
        run = ckpt_dir.parent if ckpt_dir.name == CHECKPOINTS_DIR else None
        if is_latest(path):
            checkpoint, state, note = load_newest_intact(ckpt_dir)
        else:
            checkpoint, state, note = path, load_checkpoint_file(path, "cpu"), ""
    if run is None or not is_run_folder(run):
        return RunPlan(launch_dir, launch_dir, checkpoint, state, False, note)
    run = run.resolve()
    newest = newest_iteration(ckpt_dir)
    older = not is_latest(checkpoint) and checkpoint_iteration(checkpoint) < newest
    if not older:
        return RunPlan(run, launch_dir, checkpoint, state, True, note)
    if launch_dir.resolve() == run:
        raise ResumeRefusedError(
            f"resume: {checkpoint.name} is older than {run}'s newest checkpoint (model_{newest}.pt); continuing "
            "that run from it would discard its later iterations; resume into a new folder instead")
    return RunPlan(launch_dir, launch_dir, checkpoint, state, False, note)


def matching_run(runs: list[Path], config: dict, allowed: list[str] | tuple[str, ...] = (),
                 fill_defaults: Callable[[dict], dict] | None = None) -> Path:
    """The newest of `runs` (sorted oldest first) whose resolved config differs from `config` only in
    keys a resume may change (RESUME_FREE_KEYS, `allowed`); ResumeRefusedError naming the candidates
    and their differences when none does."""
    reasons = []
    for run in reversed(runs):
        old = read_resolved_config(run)
        if old is None:
            reasons.append(f"{run.name} (no readable resolved_config.json)")
            continue
        if fill_defaults is not None:
            old = fill_defaults(old)
        refused = refused_changes(config_changes(old, config), allowed)
        if not refused:
            return run
        refused.sort(key=lambda k: (not k.endswith((".name", ".kind")) and k != "seed", k))  # what tells runs apart
        reasons.append(f"{run.name} ({', '.join(refused[:3])}{', ...' if len(refused) > 3 else ''})")
    shown = "; ".join(reasons[:5]) + (f"; and {len(reasons) - 5} more" if len(reasons) > 5 else "")
    raise ResumeRefusedError(
        f"resume=true: none of the {len(runs)} run(s) with a checkpoint under {runs[0].parent} was trained with "
        f"this config (candidates, differing keys: {shown}); name one with resume=<folder> (with "
        "resume_allow_changes=[...] for a deliberate change), or drop resume=true to start a new run")


def previous_config(plan: RunPlan) -> dict | None:
    """The resolved config the checkpoint was trained with (stored in it from format 2 on; else the
    run folder's resolved_config.json)."""
    text = (plan.state or {}).get("config")
    if isinstance(text, str):
        try:
            cfg = safe_read.parse_json(text, "the checkpoint's config")
        except ValueError:
            cfg = None
        if isinstance(cfg, dict):
            return cfg
    if plan.continues:
        return read_resolved_config(plan.run_dir)
    return None


def check_resume_changes(plan: RunPlan, new_config: dict, allowed: list[str] | tuple[str, ...],
                         fill_defaults: Callable[[dict], dict] | None = None) -> dict:
    """{key: (old, new)} of the accepted config changes of a resume; ResumeRefusedError listing the
    keys that changed without being named in resume_allow_changes. `fill_defaults` gives the old
    config the schema's defaults for keys it predates (a newer bmimic's options are no change)."""
    old = previous_config(plan)
    if plan.state is None or old is None:
        return {}
    if fill_defaults is not None:
        old = fill_defaults(old)
    # `resume` itself (null -> "true") and its companions describe this launch, not the run: no change.
    changes = {k: v for k, v in config_changes(old, new_config).items() if not key_allowed(k, LAUNCH_KEYS)}
    refused = refused_changes(changes, allowed)
    if refused:
        shown = ", ".join(f"{k} ({_short(changes[k][0])} -> {_short(changes[k][1])})" for k in refused[:8])
        more = f" and {len(refused) - 8} more" if len(refused) > 8 else ""
        raise ResumeRefusedError(
            f"resume: the config differs from the one {plan.checkpoint} was trained with: {shown}{more}; "
            f"to continue anyway, add resume_allow_changes=[{','.join(refused)}]")
    return changes


def _short(value: Any) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= 40 else text[:37] + "..."


def refuse_finished(plan: RunPlan, max_iterations: int, stop_at_iteration: int | None = None) -> None:
    """Continuing a run that already reached max_iterations, or the iteration it is asked to pause at,
    would only rewrite its files."""
    iteration = int(plan.state.get("iter", -1)) if plan.state else -1
    if read_status(plan.run_dir).get("status") == "done" and iteration >= max_iterations:
        raise ResumeRefusedError(
            f"resume: {plan.run_dir} is done at iteration {iteration} (max_iterations={max_iterations}); "
            "raise max_iterations to train it further")
    if stop_at_iteration is not None and iteration >= stop_at_iteration:
        raise ResumeRefusedError(
            f"resume: {plan.run_dir} is at iteration {iteration}, so stop_at_iteration={stop_at_iteration} leaves "
            "nothing to train; raise it or leave it out")
