"""`python -m bmimic.train [overrides]`: train a tracking policy under a motion sampler.

    python -m bmimic.train                                   # embedded default motion, adaptive sampler
    python -m bmimic.train sampler=uniform seed=3
    python -m bmimic.train motion=lafan_dance1 sampler.gamma=0.8 num_envs=8192
    python -m bmimic.train -m +sweep=sampler_ablation        # a study from sweeps/
    python -m bmimic.train --help                            # groups and options
    python -m bmimic.train --cfg job                         # the composed config

Single runs write outputs/runs/<run_name>/<timestamp>/, multirun jobs
outputs/sweeps/<sweep_name>/<overrides>/seed=<seed>/. Returns the final evaluated failure rate
(lower is better) so Hydra's optimising sweepers can use it.
"""

from __future__ import annotations

import json
import logging
import math
import os
import sys
import traceback
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from bmimic import BmimicError, launch
from bmimic.config import check_composed, check_num_envs_fit, resolve_runtime, validate, with_schema_defaults
from bmimic.console import quiet_stdout, quiet_warp, summary_block
from bmimic.runs import (
    LOCK_NAME,
    ResumeRefusedError,
    RunLockedError,
    RunPlan,
    atomic_write_json,
    atomic_write_text,
    check_resume_changes,
    discard_launch_dir,
    intact_checkpoints,
    lock_run,
    move_file_logs,
    plan_run,
    provenance,
    read_status,
    record_resume,
    resolve_device,
    resume_request,
    seed_everything,
    write_provenance,
    write_status,
)

log = logging.getLogger("bmimic.train")


def _user_errors() -> tuple[type[BaseException], ...]:
    from bmimic.motion.motion import MotionDataError

    return (BmimicError, MotionDataError)


def build_task(cfg: DictConfig, device: str):
    """Robot model, robot info, motion and bins of a composed config (validated against the motion)."""
    from bmimic.motion.config import load_motion
    from bmimic.robot import load_mjmodel, resolve_robot
    from bmimic.sampling.config import layout_for, min_motion_bin_s

    mjm = load_mjmodel(cfg=cfg.robot)
    robot = resolve_robot(cfg.robot, mjm)
    motion = load_motion(cfg.motion, mjm, bin_size_s=min_motion_bin_s(cfg.sampler), lafan_dir=cfg.data.lafan_dir,
                         control_fps=1.0 / (cfg.sim.timestep_s * cfg.sim.decimation))
    validate(cfg, motion.duration_s)
    layout = layout_for(cfg.sampler, motion.num_frames, motion.fps, device=device)
    return mjm, robot, motion, layout


def build(cfg: DictConfig, device: str, task: tuple | None = None):
    """Robot, motion, bins, sampler, environments: everything a run or a tool needs (`task`: what
    `build_task` returned, when the caller already has it)."""
    from bmimic.envs.tracking_env import TrackingEnv, episode_length_steps
    from bmimic.motion.reference import ReferenceMotion
    from bmimic.sampling.accounting import EpisodeAccounting
    from bmimic.sampling.config import make_sampler

    mjm, robot, motion, layout = task if task is not None else build_task(cfg, device)
    check_num_envs_fit(cfg, mjm, device, cfg.num_envs, cfg.ppo.num_steps_per_env)
    sampler = make_sampler(cfg.sampler, layout.num_bins, device)
    accounting = EpisodeAccounting.from_config(cfg.sampler.accounting, sampler, layout, cfg.num_envs,
                                               episode_length_steps(cfg.env, cfg.sim), device=device)
    env = TrackingEnv(cfg.env, cfg.sim, mjm, robot, ReferenceMotion.for_robot(motion, robot, device), cfg.num_envs,
                      device, accounting=accounting)
    return mjm, robot, motion, layout, sampler, env


def build_evaluator(cfg: DictConfig, device: str, robot, motion, layout, robust: bool = False):
    """The sampler-independent evaluator (robust: with domain randomisation, observation noise, pushes)."""
    from bmimic.envs.tracking_env import TrackingEnv
    from bmimic.motion.reference import ReferenceMotion
    from bmimic.robot import load_mjmodel
    from bmimic.training.evaluation import Evaluator

    total = layout.num_bins * cfg.eval.episodes_per_bin
    n = max(1, min(total, cfg.eval.max_envs))
    mjm = load_mjmodel(cfg=cfg.robot)
    check_num_envs_fit(cfg, mjm, device, n, 0)
    env = TrackingEnv(cfg.env, cfg.sim, mjm, robot, ReferenceMotion.for_robot(motion, robot, device), n, device,
                      mode="eval", robust=robust, layout=layout)
    return Evaluator(env, layout, motion.segments, cfg.eval.episodes_per_bin, cfg.eval.horizon_s,
                     max_mpkpe_rel_mm=cfg.eval.max_mpkpe_rel_mm)


def robust_evaluation(cfg: DictConfig, device: str, robot, motion, layout, trainer, run_dir: Path) -> dict:
    """`eval.robust`: the final evaluation again with DR, noise and pushes on -> eval_robust.parquet;
    returns its summary (metrics.json keys `final_robust_eval_*`)."""
    from bmimic.runs import atomic_write_parquet
    from bmimic.training.evaluation import summarize

    evaluator = build_evaluator(cfg, device, robot, motion, layout, robust=True)
    policy = trainer.alg.get_policy()
    policy.eval()
    p = trainer.progress
    per_bin = evaluator.evaluate(policy, p.iteration, p.env_steps, p.wall_time_s)
    atomic_write_parquet(run_dir / "eval_robust.parquet", per_bin)
    evaluator.env.close()
    summary = summarize(per_bin, prefix="robust_eval")
    log.info("robust eval at iteration %d: failure rate %.3f (clean: see eval.parquet)", p.iteration,
             summary["robust_eval_failure_rate"])
    return {f"final_{k}": v for k, v in summary.items()}


def _init_distributed() -> tuple[int, int]:
    """(rank, world size); under torchrun, join the process group (NCCL on GPUs, gloo on a CPU-only
    machine) before any env is built."""
    import torch

    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return 0, 1
    if not torch.distributed.is_initialized():
        if torch.cuda.is_available():
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
            torch.distributed.init_process_group("nccl")
        else:  # CPU ranks (gloo): the same code path, for smoke tests without a GPU
            torch.distributed.init_process_group("gloo")
    return torch.distributed.get_rank(), world


def train(cfg: DictConfig, launch_dir: Path, sweep_job: bool = False, ctx: RunContext | None = None) -> float:
    """Train in a fresh run folder (`launch_dir`) or continue the run `cfg.resume` names; returns the
    final evaluated failure rate.

    Nothing is written into any run folder until every check has passed, the checkpoint (if any) is
    loaded into the built trainer and the config is compared with the one it was trained with: a
    refused resume leaves the run it names byte-identical.
    """
    import torch

    from bmimic.sampling.config import describe as describe_sampler
    from bmimic.training.runner import Trainer

    ctx = ctx if ctx is not None else RunContext(launch_dir)
    requested = cfg.device
    smoke_defaults = cfg.num_envs is None and cfg.max_iterations is None
    quiet_warp(cfg.verbose)
    device = resolve_device(requested)
    rank, world = _init_distributed()
    if world > 1:
        if torch.distributed.get_backend() == "nccl":
            device = f"cuda:{int(os.environ.get('LOCAL_RANK', '0'))}"
        cfg.seed = cfg.seed + rank  # distinct worlds per rank; rsl-rl broadcasts the policy
    resolve_runtime(cfg, device)
    validate(cfg)
    smoke = not device.startswith("cuda") and smoke_defaults
    main_rank = rank == 0  # under torchrun only rank 0 writes the run folder
    plan = plan_run(cfg.resume, launch_dir, sweep_job, trust=bool(cfg.trust_checkpoint))
    if plan.note:
        log.warning(plan.note)
    resolved = OmegaConf.to_container(cfg, resolve=True)
    allowed = list(cfg.resume_allow_changes or [])
    changes = check_resume_changes(plan, resolved, allowed, fill_defaults=with_schema_defaults)
    if plan.continues:
        _refuse_finished(plan, cfg.max_iterations)
    if main_rank and not ctx.holds(plan.run_dir):
        ctx.lock(plan.run_dir)
    seed_everything(cfg.seed)

    task = build_task(cfg, device)
    if main_rank:  # before the environment is built: its first start compiles Warp kernels (minutes)
        log.info(start_summary(cfg, requested, world, smoke, task[2], task[3], plan.run_dir))
    mjm, robot, motion, layout, sampler, env = build(cfg, device, task)
    for line in describe_sampler(cfg.sampler, layout, sampler):
        log.info("%s", line)
    evaluator = build_evaluator(cfg, device, robot, motion, layout) if main_rank else None  # rank 0 evaluates
    run_dir = plan.run_dir
    with quiet_stdout(cfg.verbose):  # rsl-rl prints its observation sets and models while building
        trainer = Trainer(env, evaluator, sampler, cfg.ppo, run_dir, device, cfg.run_name,
                          eval_every_iters=cfg.eval.every_iters, logger=cfg.logger,
                          wandb_project=cfg.wandb_project, sampler_log_every=cfg.sampler.log_every,
                          progress_bar=cfg.progress_bar and main_rank, is_main_rank=main_rank,
                          run_config=resolved)
    if plan.state is not None:
        trainer.restore(plan.state, plan.checkpoint, allowed)
    if main_rank:
        _commit(ctx, plan, resolved, device, changes, motion)
    try:
        trainer.learn(cfg.max_iterations, cfg.ppo.init_at_random_ep_len, cfg.time_limit_s)
        final = trainer.progress.last_eval
        # Rank 0 alone evaluates (the evaluation env holds no collective): the other ranks release
        # their graphs and leave the process group meanwhile, and return NaN.
        if not main_rank:
            final = dict.fromkeys(("eval_failure_rate", "eval_success_rate", "eval_mpkpe_mm",
                                   "eval_bins_mastered_frac"), math.nan)
        elif not trainer.eval_rows or int(trainer.eval_rows[-1]["iteration"].iloc[0]) != trainer.progress.iteration:
            final = trainer.evaluate()
        robust = robust_evaluation(cfg, device, robot, motion, layout, trainer, run_dir) if (
            cfg.eval.robust and main_rank) else {}
        if main_rank:
            trainer.save_checkpoint()
    finally:
        trainer.close()
        env.close()
        if world > 1:
            torch.distributed.destroy_process_group()
    metrics = {
        "final_eval_failure_rate": final["eval_failure_rate"],
        "final_eval_success_rate": final["eval_success_rate"],
        "final_eval_mpkpe_mm": final["eval_mpkpe_mm"],
        "final_eval_bins_mastered_frac": final["eval_bins_mastered_frac"],
        **robust,
        "iterations": trainer.progress.iteration,
        "env_steps": trainer.progress.env_steps,
        "wall_time_s": trainer.progress.wall_time_s,
        "mean_episode_length": trainer.train_rows[-1]["mean_episode_length"] if trainer.train_rows else math.nan,
        "max_episode_length": env.max_episode_length,
        "num_bins": layout.num_bins,
        "num_envs": cfg.num_envs,
        "device": device,
        **trainer.total_resets,
    }
    if not main_rank:
        log.info("rank %d done: %d iterations, %d env steps, learning rate %.6e (rank 0 evaluates and writes %s)",
                 rank, trainer.progress.iteration, trainer.progress.env_steps, trainer.alg.learning_rate, run_dir)
        return float(metrics["final_eval_failure_rate"])
    atomic_write_json(run_dir / "metrics.json", metrics)
    write_status(run_dir, "done", trainer.progress.iteration)
    broken = sum(trainer.total_resets.values())
    log.info("done: %d iterations, %.0f s, eval failure rate %.3f%s -> %s", metrics["iterations"],
             metrics["wall_time_s"], metrics["final_eval_failure_rate"],
             f"; {broken} broken world-steps were reset" if broken else "", run_dir)
    return float(metrics["final_eval_failure_rate"])


def start_summary(cfg: DictConfig, requested_device: str, world: int, smoke: bool, motion, layout,
                  run_dir: Path) -> str:
    """The start-up block: device, envs, motion, bins, sampler variant and run folder."""
    choices = HydraConfig.get().runtime.choices if HydraConfig.initialized() else {}
    m = cfg.motion
    source = {"builtin": f"built-in {m.builtin}", "lafan": f"LAFAN1 {m.clip}"}.get(m.source, str(m.path))
    if m.start_s is not None or m.end_s is not None:
        source += f", {m.start_s or 0:g}-{'end' if m.end_s is None else format(m.end_s, 'g')} s"
    variant = choices.get("sampler") or cfg.sampler.name
    ranks = f" per rank, {world} ranks" if world > 1 else ""
    title = ("no GPU: this is a smoke-scale run through the whole pipeline; on a GPU the same command "
             "trains for real" if smoke else "training")
    return summary_block(title, [
        ("device", f"{cfg.device} (requested {requested_device})"),
        ("envs", f"{cfg.num_envs}{ranks}"),
        ("iterations", f"{cfg.max_iterations} of {cfg.ppo.num_steps_per_env} steps per env"),
        ("motion", f"{choices.get('motion') or m.name}: {source}; {motion.duration_s:.1f} s at {motion.fps:g} Hz"),
        ("bins", layout.describe()),
        ("sampler", variant if variant == cfg.sampler.name else f"{variant} ({cfg.sampler.name})"),
        ("run folder", str(run_dir)),
    ])


class RunContext:
    """What a launch may write (nothing until `_commit`, then its run folder) and the run locks it
    holds (released by `release` or when the process ends)."""

    def __init__(self, launch_dir: Path) -> None:
        self.launch_dir = Path(launch_dir)
        """The folder Hydra made for this launch."""
        self.run_dir: Path | None = None
        """The run folder this launch writes; None until committed."""
        self.hydra_record: dict[str, str] | None = None
        """This launch's .hydra files (written at commit into a new run)."""
        self._locks: dict[Path, object] = {}

    def holds(self, run_dir: Path) -> bool:
        return Path(run_dir).resolve() in self._locks

    def lock(self, run_dir: Path) -> None:
        f = lock_run(run_dir)
        if f is None:
            raise RunLockedError(f"{run_dir}: is being trained by another process (its {LOCK_NAME} is held); "
                                 "wait for it or stop it first")
        self._locks[Path(run_dir).resolve()] = f

    def release(self, run_dir: Path | None = None) -> None:
        for key in [k for k in self._locks if run_dir is None or k == Path(run_dir).resolve()]:
            self._locks.pop(key).close()


def _refuse_finished(plan: RunPlan, max_iterations: int) -> None:
    """Continuing a run that already reached max_iterations would only rewrite its files."""
    iteration = int(plan.state.get("iter", -1)) if plan.state else -1
    if read_status(plan.run_dir).get("status") == "done" and iteration >= max_iterations:
        raise ResumeRefusedError(
            f"resume: {plan.run_dir} is done at iteration {iteration} (max_iterations={max_iterations}); "
            "raise max_iterations to train it further")


def _commit(ctx: RunContext, plan: RunPlan, resolved: dict, device: str, changes: dict, motion) -> None:
    """The first writes of a launch, once every check has passed."""
    run_dir = plan.run_dir
    if run_dir.resolve() != ctx.launch_dir.resolve():
        move_file_logs(ctx.launch_dir, run_dir)  # a resumed run logs into its own folder
        ctx.release(ctx.launch_dir)
        discard_launch_dir(ctx.launch_dir)  # no empty timestamped folder is left behind
    ctx.run_dir = run_dir
    entry = {"checkpoint": str(plan.checkpoint), "iteration": int((plan.state or {}).get("iter", 0)),
             "changes": {k: list(v) for k, v in changes.items()}, "note": plan.note or None}
    launch.note_previous_attempt(run_dir, read_status(run_dir))  # a sweep job's killed or failed attempt
    if plan.continues:
        record_resume(run_dir, {**entry, "provenance": provenance(device)})
        if changes or not (run_dir / "resolved_config.json").exists():
            atomic_write_json(run_dir / "resolved_config.json", resolved)
        if not (run_dir / ".hydra" / "config.yaml").exists():
            write_hydra_record(run_dir, ctx.hydra_record)
        if changes:
            log.info("resume: accepted config changes %s (recorded in resumes.json)",
                     ", ".join(f"{k}: {json.dumps(a, default=str)} -> {json.dumps(b, default=str)}"
                               for k, (a, b) in changes.items()))
    else:
        write_hydra_record(run_dir, ctx.hydra_record)
        write_provenance(run_dir, device)
        atomic_write_json(run_dir / "resolved_config.json", resolved)
        if plan.state is not None:  # a new run that starts from another run's checkpoint
            record_resume(run_dir, entry)
    write_status(run_dir, "running", entry["iteration"])
    atomic_write_json(run_dir / "motion_segments.json", [s._asdict() for s in motion.segments])


def write_hydra_record(run_dir: Path, record: dict[str, str] | None) -> None:
    """.hydra/{config,hydra,overrides}.yaml as Hydra writes them; conf/train.yaml sets
    hydra.output_subdir=null so that Hydra itself never rewrites a finished run's record."""
    for name, text in (record or {}).items():
        atomic_write_text(run_dir / ".hydra" / name, text)


def hydra_record(cfg: DictConfig) -> dict[str, str] | None:
    """The .hydra files of this launch, from the config as composed (before runtime resolution)."""
    if not HydraConfig.initialized():
        return None
    hc = HydraConfig.instance().cfg
    return {"config.yaml": OmegaConf.to_yaml(cfg), "hydra.yaml": OmegaConf.to_yaml(hc),
            "overrides.yaml": OmegaConf.to_yaml(hc.hydra.overrides.task)}


def check_config(cfg: DictConfig) -> None:
    """bmimic.config.check_composed with Hydra's group choices (no device, no motion needed)."""
    check_composed(cfg, HydraConfig.get().runtime.choices if HydraConfig.initialized() else None)


@hydra.main(version_base="1.3", config_path="conf", config_name="train")
def main(cfg: DictConfig) -> float:
    hc = HydraConfig.get()
    launch_dir = Path(hc.runtime.output_dir)
    multirun = hc.mode == RunMode.MULTIRUN
    ctx = RunContext(launch_dir)
    ctx.hydra_record = hydra_record(cfg)
    outcome, message = "failed", None
    try:
        check_config(cfg)
        if multirun:
            previous = read_status(launch_dir)
            if previous.get("status") == "done" and resume_request(cfg.get("resume")) is None:
                log.info("skipping %s: already done", launch_dir)
                outcome = "done before"
                return float(_read_metrics(launch_dir).get("final_eval_failure_rate", math.nan))
            try:
                ctx.lock(launch_dir)
            except RunLockedError as e:
                outcome, message = "locked", str(e)
                print(f"skipping {launch_dir}: being trained by another process", file=sys.stderr)
                return math.nan
            if resume_request(cfg.resume) is None:
                cfg.resume = "true"  # an interrupted job continues from its own last checkpoint
            launch.pin_job_to_gpu()  # joblib workers: one GPU per slot, before anything initialises CUDA
        result = train(cfg, launch_dir, sweep_job=multirun, ctx=ctx)
        outcome = "done"
        return result
    except _user_errors() as e:
        message = str(e).splitlines()[0] if str(e) else type(e).__name__
        _record_failure(ctx, multirun, message)
        print(f"error: {message}", file=sys.stderr)
        if multirun:
            return math.nan
        sys.exit(2)
    except Exception as e:
        message = f"{type(e).__name__}: {e}"
        _record_failure(ctx, multirun, message, traceback.format_exc())
        if multirun:  # one broken job must not end the sweep; its error is kept in status.json
            log.error("job failed:\n%s", traceback.format_exc())
            return math.nan
        raise
    finally:
        ctx.release()
        if multirun:
            launch.record_job_outcome(launch_dir, outcome, message)
            _update_sweep_index(launch_dir)


def _record_failure(ctx: RunContext, multirun: bool, message: str, details: str = "") -> None:
    """Record a failed attempt where it cannot damage anything: in the run once committed; before
    that only in a sweep job folder without checkpoints that is not done; a single run's unused
    launch folder is removed."""
    if ctx.run_dir is not None:
        write_status(ctx.run_dir, "failed", read_status(ctx.run_dir).get("iteration", 0) or 0, error=message)
        launch.append_error_log(ctx.run_dir, f"attempt failed: {message}", details)
    elif multirun:
        # A sweep job that holds no checkpoint and is not done has nothing to damage: keep its history.
        previous = read_status(ctx.launch_dir)
        if previous.get("status") != "done" and not intact_checkpoints(ctx.launch_dir / "checkpoints"):
            launch.note_previous_attempt(ctx.launch_dir, previous)
            write_status(ctx.launch_dir, "failed", error=message)
            launch.append_error_log(ctx.launch_dir, f"attempt failed: {message}", details)
    elif int(os.environ.get("RANK", "0")) == 0:  # under torchrun, rank 0 owns the folder
        ctx.release()
        discard_launch_dir(ctx.launch_dir)


def _read_metrics(run_dir: Path) -> dict:
    from bmimic.runs import read_json

    return read_json(run_dir / "metrics.json", default={}) or {}


def _update_sweep_index(run_dir: Path) -> None:
    """Rebuild the sweep's index.csv from its run folders (safe when jobs finish concurrently)."""
    try:
        from analysis.index import write_index

        sweep_dir = Path(HydraConfig.get().sweep.dir)
        write_index(sweep_dir)
    except Exception as e:  # the index is rebuildable; never fail a job over it
        log.warning("could not update the sweep index: %s", e)


def inspect_sweep_argv(argv: list[str]) -> list[str]:
    """Hydra runs `-m` only; with --cfg, --help or --info it refuses. For those, print the sweep's jobs
    (as YAML comments, so --cfg's output stays YAML) and return the command line that shows its first
    job the same way, without -m."""
    from hydra._internal.utils import get_args_parser

    args = get_args_parser().parse_args(argv[1:])
    if not args.multirun or not (args.cfg or args.help or args.info):
        return argv
    try:
        jobs = launch.sweep_overrides(args.overrides)
    except Exception:  # overrides that do not compose: Hydra reports them below, in its own words
        jobs = [args.overrides]
    if args.cfg:
        print(f"# -m: {len(jobs)} jobs (python -m bmimic.launch list {' '.join(args.overrides)} lists their "
              "folders and status); the config of job 0 follows")
        for i, job in enumerate(jobs):
            print(f"#   job {i}: {' '.join(job)}")
    rest = [a for a in argv[1:] if a not in ("-m", "--multirun", *args.overrides)]
    return [argv[0], *rest, *jobs[0]]


if __name__ == "__main__":
    sys.argv = inspect_sweep_argv(sys.argv)
    main()
