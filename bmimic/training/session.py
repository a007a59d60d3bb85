"""A training launch's hold on its run folder: what it may write and when.

A launch writes nothing until every check has passed (`RunContext` holds the run locks meanwhile);
`commit` then makes its first writes; `record_failure` records a failed attempt where it cannot
damage anything; what the launch created for a run that it then continued elsewhere (or that was
refused) is removed (`RunContext.discard`, after bmimic.runs.claim's record of what it created), its
own log lines carried over (`move_file_logs`).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path
from typing import Any, TextIO

from bmimic.runs.claim import RunClaim
from bmimic.runs.claim import current as current_claim
from bmimic.runs.folder import (
    HYDRA_DIR,
    LOCK,
    RESOLVED_CONFIG,
    RunLockedError,
    append_error_log,
    append_resume,
    checkpoint_files,
    checkpoints_dir,
    has_hydra_record,
    lock_run,
    read_status,
    write_hydra_record,
    write_motion_segments,
    write_provenance,
    write_resolved_config,
    write_status,
)
from bmimic.runs.schema import ITERATION
from bmimic.runtime import DistributedSetupError, process_rank, provenance
from bmimic.training.resume import RunPlan

log = logging.getLogger("bmimic.train")


class RunContext:
    """What a launch may write (nothing until `commit`, then its run folder) and the run locks it
    holds (released by `release` or when the process ends)."""

    def __init__(self, launch_dir: Path) -> None:
        self.launch_dir = Path(launch_dir)
        """The folder Hydra made for this launch."""
        self.run_dir: Path | None = None
        """The run folder this launch writes; None until committed."""
        self.hydra_record: dict[str, str] | None = None
        """This launch's .hydra files (written at commit into a new run)."""
        self.composed_config: dict = {}
        """The config as composed, unresolved (its interpolations get their values in hydra_record)."""
        self.claim: RunClaim | None = current_claim(launch_dir)
        """What the launch found and created at launch_dir (bmimic.runs.claim; None for a sweep job)."""
        self._locks: dict[Path, TextIO] = {}

    def holds(self, run_dir: Path) -> bool:
        """This launch holds the lock of `run_dir`."""
        return Path(run_dir).resolve() in self._locks

    def lock(self, run_dir: Path) -> None:
        """Take `run_dir`'s lock; RunLockedError when another process holds it."""
        f = lock_run(run_dir)
        if f is None:
            raise RunLockedError(f"{run_dir}: is being trained by another process (its {LOCK} is held); "
                                 "wait for it or stop it first")
        self._locks[Path(run_dir).resolve()] = f

    def release(self, run_dir: Path | None = None) -> None:
        """Release the lock of `run_dir` (all locks when None)."""
        for key in [k for k in self._locks if run_dir is None or k == Path(run_dir).resolve()]:
            self._locks.pop(key).close()

    def discard(self) -> None:
        """Remove what this launch created at launch_dir (its log lines, the lock file it created and
        holds, the folders it created), then release its lock there; without a claim, nothing."""
        if self.claim is not None:
            self.claim.release(self._locks.get(self.launch_dir.resolve()))
        self.release(self.launch_dir)


def commit(ctx: RunContext, plan: RunPlan, resolved: dict, device: str, changes: dict, motion) -> None:
    """The first writes of a launch, once every check has passed."""
    run_dir = plan.run_dir
    if run_dir.resolve() != ctx.launch_dir.resolve():
        move_file_logs(ctx.launch_dir, run_dir, ctx.claim)  # a resumed run logs into its own folder
        ctx.discard()  # no empty timestamped folder is left behind
    ctx.run_dir = run_dir
    entry: dict[str, Any] = {"checkpoint": str(plan.checkpoint), ITERATION: int((plan.state or {}).get("iter", 0)),
             "changes": {k: list(v) for k, v in changes.items()}, "note": plan.note or None}
    note_previous_attempt(run_dir, read_status(run_dir))  # a sweep job's killed or failed attempt
    if plan.continues:
        append_resume(run_dir, {**entry, "provenance": provenance(device)})
        if changes or not (run_dir / RESOLVED_CONFIG).exists():
            write_resolved_config(run_dir, resolved)
        if not has_hydra_record(run_dir):
            write_hydra_record(run_dir, ctx.hydra_record)
        elif ctx.hydra_record and not (run_dir / HYDRA_DIR / "hydra.yaml").is_file():
            # a record compacted elsewhere (analysis.compact drops hydra.yaml) and resumed here: this launch's
            # names this machine's folders, so that compacting the record again makes them portable
            write_hydra_record(run_dir, {"hydra.yaml": ctx.hydra_record["hydra.yaml"]})
        if changes:
            log.info("resume: accepted config changes %s (recorded in resumes.json)",
                     ", ".join(f"{k}: {json.dumps(a, default=str)} -> {json.dumps(b, default=str)}"
                               for k, (a, b) in changes.items()))
    else:
        write_hydra_record(run_dir, ctx.hydra_record)
        write_provenance(run_dir, provenance(device))
        write_resolved_config(run_dir, resolved)
        if plan.state is not None:  # a new run that starts from another run's checkpoint
            append_resume(run_dir, entry)
    write_status(run_dir, "running", entry[ITERATION])
    write_motion_segments(run_dir, [s._asdict() for s in motion.segments])


def note_previous_attempt(run_dir: str | os.PathLike, status: dict) -> None:
    """Before retrying a sweep job, record how its previous attempt ended when it did not finish."""
    state = status.get("status")
    if state == "failed":
        append_error_log(run_dir, f"retrying after a failed attempt (iteration {status.get(ITERATION)}, "
                                  f"updated {status.get('updated')}): {status.get('error')}")
    elif state == "running":
        append_error_log(run_dir, f"previous attempt stopped while running (iteration {status.get(ITERATION)}, "
                                  f"updated {status.get('updated')}): killed, preempted or timed out; resuming")
    elif state == "interrupted":
        append_error_log(run_dir, f"previous attempt interrupted by a signal after iteration {status.get(ITERATION)} "
                                  f"(updated {status.get('updated')}), with a checkpoint there; resuming")


def record_failure(ctx: RunContext, multirun: bool, message: str, details: str = "",
                   error: BaseException | None = None) -> bool:
    """Record a failed attempt where it cannot damage anything: in the run once committed; before
    that only in a sweep job folder without checkpoints that is not done; a single run's launch
    removes what it created (under torchrun a rank other than 0 what its Hydra made, when rank 0 never
    wrote there). Never raises for a write the disk refuses (the failure being recorded may be that
    very disk being full): status.json is rewritten in place, the error log is skipped. Returns whether
    this process says the error: rank 0 does (every rank refuses a config alike), and any rank its own
    torchrun rendezvous (`error`), which only it knows."""
    try:
        if ctx.run_dir is not None:
            write_status(ctx.run_dir, "failed", read_status(ctx.run_dir).get(ITERATION, 0) or 0, error=message)
            with contextlib.suppress(OSError):  # the status says it; the log is a convenience
                append_error_log(ctx.run_dir, f"attempt failed: {message}", details)
        elif multirun:
            # A sweep job that holds no checkpoint and is not done has nothing to damage: keep its history.
            previous = read_status(ctx.launch_dir)
            if previous.get("status") != "done" and not checkpoint_files(checkpoints_dir(ctx.launch_dir)):
                with contextlib.suppress(OSError):
                    note_previous_attempt(ctx.launch_dir, previous)
                write_status(ctx.launch_dir, "failed", error=message)
                with contextlib.suppress(OSError):
                    append_error_log(ctx.launch_dir, f"attempt failed: {message}", details)
        elif process_rank() == 0:  # under torchrun, rank 0 owns the folder
            ctx.discard()
            ctx.release()
        elif ctx.claim is not None:
            ctx.claim.release_observed()
    except OSError as e:
        log.warning("could not record the failure: %s", e)
    return process_rank() == 0 or isinstance(error, DistributedSetupError)


def move_file_logs(src_dir: Path, dst_dir: Path, claim: RunClaim | None = None) -> None:
    """Point the logging file handlers writing into `src_dir` at the same file names in `dst_dir`
    (appended), carrying over the lines this launch logged so far (`claim`: only those; a log that
    was in `src_dir` before the launch stays there): a resumed run logs into its own folder."""
    src_dir, dst_dir = Path(src_dir).resolve(), Path(dst_dir)
    root = logging.getLogger()
    for handler in list(root.handlers):
        if not isinstance(handler, logging.FileHandler):
            continue
        old = Path(handler.baseFilename)
        if old.parent != src_dir:
            continue
        handler.flush()
        handler.close()
        root.removeHandler(handler)
        new = logging.FileHandler(dst_dir / old.name, mode="a", encoding=handler.encoding)
        new.setLevel(handler.level)
        new.setFormatter(handler.formatter)
        for f in handler.filters:
            new.addFilter(f)
        if claim is not None and claim.log_path == old:
            earlier = claim.own_log()
        elif claim is None:
            try:
                earlier = old.read_text()
            except OSError:
                earlier = ""
        else:
            earlier = ""
        if earlier and new.stream is not None:
            new.stream.write(earlier)
            new.flush()
        root.addHandler(new)
