"""One job of a training command line: the checks, the run folder, training and the run's record.

`launch(cfg)` is the body of a Hydra app over conf/train.yaml (a single run or one job of a multirun):
`python -m bmimic.train` calls it as it is, `python -m bmimic.race` with a stopping rule. `train` builds
the task through the composition root (bmimic.task), trains, and writes metrics and status; nothing is
written into a run folder before every check has passed.
"""

from __future__ import annotations

import logging
import math
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, cast

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

import bmimic.sweeping.gpu_slots as gpu_slots  # also registers the bmimic.gpu_slots resolver of the launchers
from bmimic.cli.common import first_line, shell_arg, user_errors
from bmimic.cli.console import quiet_stdout, quiet_warp, start_summary
from bmimic.config import interpolated_keys, placed, recorded_config, resolve_runtime, with_schema_defaults
from bmimic.config.budget import check_cpu_budget, cpu_training_s, describe_sizes
from bmimic.config.checks import advisories, check_composed, check_evaluates, validate
from bmimic.runs.folder import (
    TENSORBOARD_DIR,
    RunLockedError,
    read_metrics,
    read_status,
    write_metrics,
    write_status,
)
from bmimic.runs.record import metrics as run_metrics
from bmimic.runs.schema import ENV_STEPS, WALL_TIME_S
from bmimic.runtime import (
    init_distributed,
    process_rank,
    resolve_device,
    seed_everything,
    torchrun_env,
    use_cpu_threads,
)
from bmimic.sweeping.jobs import done_run_differences
from bmimic.sweeping.outcomes import record_job_outcome
from bmimic.task import (
    build_evaluator,
    build_task,
    build_trainer,
    build_training,
    build_whole_clip,
    check_num_envs_fit,
)
from bmimic.training.final_eval import learn_and_evaluate
from bmimic.training.interrupts import StopNow, StopSignals, TrainingInterrupted
from bmimic.training.logger import done_line
from bmimic.training.resume import check_resume_changes, plan_run, refuse_finished, resume_request
from bmimic.training.schedule import whole_clip_wanted
from bmimic.training.session import RunContext, commit, record_failure

if TYPE_CHECKING:
    from bmimic.config.placement import PlacedConfig

log = logging.getLogger("bmimic.train")  # the command line's logger, whichever entry point runs the job


@dataclass(frozen=True)
class Placement:
    """Where and how big this process trains: the device asked for and the one resolved, its torchrun
    rank among `world` ranks, and whether it is a smoke-scale pass (a CPU with no sizes given)."""

    requested: str
    """`device` as the config asked for it (auto, cpu, cuda, cuda:1)."""
    device: str
    """The torch device this process trains on (a torchrun rank's own GPU under NCCL)."""
    rank: int
    """This process's torchrun rank (0 without torchrun); rank 0 evaluates and writes the run folder."""
    world: int
    """Number of torchrun ranks (1 without torchrun)."""
    smoke: bool
    """No GPU and neither num_envs nor max_iterations set: the CPU's smoke-scale pass."""

    @property
    def main_rank(self) -> bool:
        return self.rank == 0


def train(cfg: DictConfig, launch_dir: Path, sweep_job: bool = False, ctx: RunContext | None = None,
          stop_rule: Callable | None = None, stop: StopSignals | None = None) -> float:
    """Train in a fresh run folder (`launch_dir`) or continue the run `cfg.resume` names; returns the
    final evaluated failure rate. `stop_rule(trainer, summary) -> bool`, if given, is called after each
    periodic evaluation and ends training when it returns True (bmimic.race). A signal (`stop`) ends the
    current iteration: the run gets a checkpoint, its tables and status `interrupted`, and
    TrainingInterrupted is raised.

    Nothing is written into any run folder until every check has passed, the checkpoint (if any) is
    loaded into the built trainer and the config is compared with the one it was trained with: a
    refused resume leaves the run it names byte-identical.
    """
    ctx = ctx if ctx is not None else RunContext(launch_dir)
    if stop is not None:  # nothing is written until commit: a signal ends the set-up at once (StopNow)
        stop.begin_at_once()
    run_cfg, place = place_job(cfg, stop_rule)
    plan, resolved, changes = plan_job(run_cfg, launch_dir, sweep_job, ctx, place)
    # Distinct worlds per rank (rsl-rl broadcasts the policy); the config keeps the run's seed, which its
    # checkpoints record and every rank's resume compares with.
    seed_everything(run_cfg.seed + place.rank)
    task = build_task(run_cfg, device=place.device)
    if place.main_rank:  # before the environment is built: its first start compiles Warp kernels (minutes)
        log.info(start_summary(run_cfg, place.requested, place.world, place.smoke, task.motion, task.layout,
                               plan.run_dir))
    trainer = build_job(run_cfg, task, place, plan, resolved, stop_rule)
    env = trainer.env
    try:
        if stop is not None:
            stop.end_at_once()  # from here the run has something to save: a signal ends the iteration
        if place.main_rank:
            commit(ctx, plan, resolved, place.device, changes, task.motion)
        final, robust = learn_and_evaluate(trainer, place.main_rank, lambda: build_evaluator(task, robust=True), stop)
        if trainer.interrupted:
            if place.main_rank:
                trainer.checkpoint.save()  # the tables first, then model_<it>.pt and latest.pt
                write_status(plan.run_dir, "interrupted", trainer.progress.iteration)
            raise TrainingInterrupted(cast(StopSignals, stop), trainer.progress.iteration, plan.run_dir)
        if place.main_rank:
            trainer.checkpoint.save(final=True)
    finally:
        try:
            trainer.close()
        finally:
            env.close()
            if trainer.whole_clip is not None:
                trainer.whole_clip.close()
            if place.world > 1:
                import torch

                torch.distributed.destroy_process_group()
    return finish_job(run_cfg, trainer, task, place, plan.run_dir, final, robust, sweep_job)


def place_job(cfg: DictConfig, stop_rule: Callable | None = None) -> tuple[PlacedConfig, Placement]:
    """Resolve the device (and the torchrun rank's) and fill in the runtime values of `cfg` (sizes for
    this machine), then check them (launch's check_config read every key); returns `cfg` read-only and
    typed (bmimic.config.placed), the one config everything after this reads, and where it runs."""
    import torch

    requested = cfg.device
    smoke_defaults = cfg.num_envs is None and cfg.max_iterations is None
    default_budget = cfg.max_iterations is None
    quiet_warp(cfg.verbose)
    device = resolve_device(requested)
    use_cpu_threads(device)
    rank, world = init_distributed()
    if rank != 0 and not cfg.verbose:  # under torchrun rank 0 speaks for the run; the others only warn
        logging.getLogger().setLevel(logging.WARNING)
    if world > 1:
        if torch.distributed.get_backend() == "nccl":
            device = f"cuda:{torchrun_env()[2]}"
    resolve_runtime(cfg, device)
    validate(cfg, composed_checked=True)  # launch's check_config read every key; the runtime filled in values
    if stop_rule is not None:  # bmimic.race: it times evaluations, so one must run before the budget ends
        check_evaluates(cfg, default_budget and not device.startswith("cuda"))
    if rank == 0:
        for note in advisories(cfg):
            log.warning(note)
    return placed(cfg), Placement(requested, device, rank, world, smoke=not device.startswith("cuda") and smoke_defaults)


def plan_job(cfg: PlacedConfig, launch_dir: Path, sweep_job: bool, ctx: RunContext, place: Placement):
    """The run folder this job trains in and what it continues: (plan, the resolved config as a dict, the
    config changes a resume was allowed). Refuses a resume that changes what it may not, a finished run,
    and on a CPU a size that cannot fit or would train past max_cpu_hours; then rank 0 locks the folder."""
    resolved = cast(dict, OmegaConf.to_container(cfg, resolve=True))
    ctx.hydra_record = record_values(ctx.hydra_record, ctx.composed_config, resolved)
    allowed = list(cfg.resume_allow_changes or [])
    plan = plan_run(cfg.resume, launch_dir, sweep_job,
                    pinned=ctx.claim is not None and ctx.claim.pinned, config=resolved, allowed=allowed,
                    fill_defaults=with_schema_defaults)
    if plan.note:
        log.warning(plan.note)
    changes = check_resume_changes(plan, resolved, allowed, fill_defaults=with_schema_defaults)
    if plan.continues:
        refuse_finished(plan, cfg.max_iterations, cfg.stop_at_iteration)
    if place.device == "cpu" and not sweep_job:  # a sweep's jobs were estimated together when it started (cli)
        from bmimic.robot import load_mjmodel

        # A size that cannot fit in memory is refused as such first (its training time is moot).
        check_num_envs_fit(cfg, load_mjmodel(cfg=cfg.robot), place.device, cfg.num_envs, cfg.ppo.num_steps_per_env)
        done = int(plan.state.get("iter", 0)) if plan.state else 0
        check_cpu_budget([cpu_training_s(cfg, done)], cfg.max_cpu_hours, describe_sizes([cfg]))
    if place.main_rank and not ctx.holds(plan.run_dir):
        ctx.lock(plan.run_dir)
    return plan, resolved, changes


def build_job(cfg: PlacedConfig, task, place: Placement, plan, resolved: dict, stop_rule: Callable | None = None):
    """The training environment, sampler, evaluators and trainer of `task` (with the race's `stop_rule`),
    with the checkpoint that `plan` continues restored: the trainer, which holds them all."""
    from bmimic.sampling.config import describe as describe_sampler

    training = build_training(cfg, place.device, task)
    for line in describe_sampler(cfg.sampler, task.layout, training.sampler):
        log.info("%s", line)
    evaluator = build_evaluator(task) if place.main_rank else None  # rank 0 evaluates
    whole_clip = build_whole_clip(task) if place.main_rank and whole_clip_wanted(cfg) else None
    if whole_clip is not None:
        whole_clip.build()
    with quiet_stdout(cfg.verbose):  # rsl-rl prints its observation sets and models while building
        trainer = build_trainer(training, evaluator, plan.run_dir, is_main_rank=place.main_rank, run_config=resolved,
                                whole_clip=whole_clip, after_evaluation=stop_rule)
    if plan.state is not None:
        trainer.checkpoint.load(plan.state, plan.checkpoint, list(cfg.resume_allow_changes or []))
        if place.world > 1:
            # A checkpoint holds rank 0's random state alone, which the restore gave every rank: each
            # rank draws a stream of its own again (its worlds' resets, noise and actions), one that
            # differs from every earlier segment's.
            stream = (cfg.seed + place.rank + 1_000_003 * trainer.progress.iteration) % 2**62
            seed_everything(stream)
            log.info("rank %d: random streams reseeded from %d (the run's seed + rank + 1000003 x %d iterations)",
                     place.rank, stream, trainer.progress.iteration)
    return trainer


def finish_job(cfg: PlacedConfig, trainer, task, place: Placement, run_dir: Path, final: dict, robust: dict,
               sweep_job: bool) -> float:
    """metrics.json and status `done` (rank 0), the closing lines; returns the final failure rate."""
    env = trainer.env
    train_rows = trainer.record.rows("train_metrics")
    metrics = run_metrics(final, robust, {
        "iterations": trainer.progress.iteration,
        ENV_STEPS: trainer.progress.env_steps,
        WALL_TIME_S: trainer.progress.wall_time_s,
        "mean_episode_length": train_rows[-1]["mean_episode_length"] if train_rows else math.nan,
        "max_episode_length": env.max_episode_length,
        "num_bins": task.layout.num_bins,
        "num_envs": env.num_envs,  # what was built (the env owns its size)
        "device": place.device,
        **trainer.total_resets,
        "overflow_world_steps": trainer.overflow_world_steps,
    })
    if not place.main_rank:
        log.info("rank %d done: %d iterations, %d env steps, learning rate %.6e (rank 0 evaluates and writes %s)",
                 place.rank, trainer.progress.iteration, trainer.progress.env_steps, trainer.alg.learning_rate,
                 run_dir)
        return float(metrics["final_eval_failure_rate"])
    write_metrics(run_dir, metrics)
    write_status(run_dir, "done", trainer.progress.iteration)
    broken = sum(trainer.total_resets.values())
    overflow = trainer.overflow_world_steps
    log.info("%s", done_line(metrics, WALL_TIME_S, run_dir, broken, overflow))
    if not sweep_job:  # a sweep's closing line names the report instead (bmimic.sweeping.outcomes)
        folder = shell_arg(run_dir)  # pasted back into a shell: a folder with a space stays one argument
        log.info("next: bmimic-eval %s (evaluate), bmimic-report %s (report)%s", folder, folder,
                 f", tensorboard --logdir {shell_arg(run_dir / TENSORBOARD_DIR)} (curves)" if cfg.logger == "tensorboard"
                 else "")
    return float(metrics["final_eval_failure_rate"])


def hydra_record(cfg: DictConfig) -> dict[str, str] | None:
    """The .hydra files of this launch, from the config as composed (before runtime resolution); train()
    records the values of its interpolations (record_values)."""
    if not HydraConfig.initialized():
        return None
    hc: Any = HydraConfig.instance().cfg
    return {"config.yaml": OmegaConf.to_yaml(cfg), "hydra.yaml": OmegaConf.to_yaml(hc),
            "overrides.yaml": OmegaConf.to_yaml(hc.hydra.overrides.task)}


def record_values(record: dict[str, str] | None, composed: dict, resolved: dict) -> dict[str, str] | None:
    """The .hydra record with config.yaml's interpolations replaced by the values the run trained with
    (bmimic.config.recorded_config); unchanged when the config interpolates nothing."""
    if record is None or not interpolated_keys(composed):
        return record
    return {**record, "config.yaml": OmegaConf.to_yaml(OmegaConf.create(recorded_config(composed, resolved)))}


def check_config(cfg: DictConfig) -> None:
    """bmimic.config.check_composed with Hydra's group choices (no device; a library's files, not loaded)."""
    check_composed(cfg, HydraConfig.get().runtime.choices if HydraConfig.initialized() else None, motion_files=True)


def launch(cfg: DictConfig, stop_rule: Callable | None = None) -> float:
    """The body of `main` (one job of a run or multirun), also for sibling entry points (bmimic.race)."""
    hc = HydraConfig.get()
    launch_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    ctx = RunContext(launch_dir)
    ctx.hydra_record = hydra_record(cfg)
    ctx.composed_config = cast(dict, OmegaConf.to_container(cfg, resolve=False))
    outcome, message = "failed", None
    stop = StopSignals()
    try:
        stop.__enter__()  # from here a signal ends the current iteration, not the process (interrupts.py)
        check_config(cfg)
        if multirun:
            if read_status(launch_dir).get("status") == "done":
                differs = done_run_differences(cfg, launch_dir)
                if not differs:
                    log.info("skipping %s: already done", launch_dir)
                    outcome = "done before"
                    failure = read_metrics(launch_dir).get("final_eval_failure_rate")  # null: not a number
                    return float(failure) if isinstance(failure, int | float) else math.nan
                if differs is not True:  # a run of other settings: never taken for this job's result
                    outcome, message = "refused", differs
                    print(f"error: {launch_dir}: {message}", file=sys.stderr)
                    return math.nan
            try:
                ctx.lock(launch_dir)
            except RunLockedError as e:
                outcome, message = "locked", str(e)
                print(f"skipping {launch_dir}: being trained by another process", file=sys.stderr)
                return math.nan
            if resume_request(cfg.resume) is None:
                cfg.resume = "true"  # an interrupted job continues from its own last checkpoint
            gpu_slots.pin_job_to_gpu()  # joblib workers: one GPU per slot, before anything initialises CUDA
        result = train(cfg, launch_dir, sweep_job=multirun, ctx=ctx, stop_rule=stop_rule, stop=stop)
        outcome = "done"
        return result
    except (TrainingInterrupted, StopNow) as e:  # the run has its checkpoint, tables and status; a sweep stops too
        if isinstance(e, StopNow):  # during the set-up: nothing was written
            e = TrainingInterrupted(stop, None, launch_dir)
        outcome, message = "interrupted", str(e)
        if e.iteration is None and not multirun and process_rank() == 0:
            ctx.discard()  # nothing was written: the launch removes what it created, as a refusal does
            ctx.release()
        if process_rank() == 0:
            print(message, file=sys.stderr)
        stop.chain()  # a launcher's handler of this signal (submitit: requeue the job, then exit)
        sys.exit(e.exit_code)
    except user_errors() as e:
        message = first_line(e)
        if record_failure(ctx, multirun, message, error=e):  # rank 0's line, or a rank's own rendezvous
            print(f"error: {message}", file=sys.stderr)
        if multirun:
            return math.nan
        sys.exit(2)
    except Exception as e:
        message = f"{type(e).__name__}: {e}"
        record_failure(ctx, multirun, message, traceback.format_exc())
        if multirun:  # one broken job must not end the sweep; its error is kept in status.json
            log.error("job failed:\n%s", traceback.format_exc())
            return math.nan
        raise
    finally:
        stop.__exit__()
        ctx.release()
        if multirun:  # analysis.index.SweepIndexCallback then rebuilds the sweep's index.csv
            record_job_outcome(launch_dir, outcome, message)
