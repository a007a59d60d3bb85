"""`python -m bmimic.eval RUN_DIR_OR_CHECKPOINT [options] [key=value ...]`: evaluate a trained policy.

    python -m bmimic.eval outputs/runs/default/2026-01-01_12-00-00            # the run's latest.pt
    python -m bmimic.eval outputs/runs/default/<stamp>/checkpoints/model_500.pt --episodes-per-bin 8
    python -m bmimic.eval RUN --horizon-s 4 --device cuda:1 eval.max_envs=1024
    python -m bmimic.eval RUN --whole-clip 128 --conditions nominal,robust
    python -m bmimic.eval RUN motion=lafan_folder data.lafan_dir=/data/unseen     # clips it never saw
    python -m bmimic.eval RUN motion=/data/unseen/fight2_subject2.csv              # a file or folder of clips

The run's composed config (RUN_DIR/.hydra/config.yaml) is reloaded and its `auto`/null values are
resolved for this machine exactly as training does; dotted `key=value` overrides are merged on top.
Robot, motion, time bins and the evaluation environment are rebuilt like training's
(`bmimic.task.build_evaluator`), the actor is rebuilt from the checkpoint, and the
sampler-independent evaluation runs with the deterministic policy: `episodes_per_bin` episodes
start at stratified frames of every bin and run for `horizon_s`; an episode that terminates before
then (or, with eval.max_mpkpe_rel_mm, tracks worse than that on average) is a failure, charged to the
bin where it happened (bmimic.training.evaluator). Tables go to RUN_DIR/eval/<checkpoint>/
(latest.pt is named after its iteration, model_<it>, so re-evaluating after more training never
overwrites an older result; on a motion the checkpoint was not trained on, `motion=<option, file or
folder>`, RUN_DIR/eval/<checkpoint>_on_<motion>-<digest>/ with the same tables; evaluating the same
checkpoint again replaces its folder with a warning, and is refused when sim2sim compared a gap
against it, unless --force or --out says where):

    eval_episodes.parquet  one row per episode (start, end and failure frame and bin, errors)
    eval_bins.parquet      one row per time bin: visits, failures, failure_rate, start counts, errors
    eval_segments.csv      one row per motion segment, counted like the bins (visits, failures there)
    eval_summary.json      overall numbers (keys as in metrics.json: eval_success_rate, eval_mpkpe_mm, ...)

`--whole-clip [R]` evaluates whole clips instead (bmimic.training.whole_clip; sim2sim's flag does the
same in native MuJoCo): per clip, rollouts from its first frame to its last under each of `--conditions`
(nominal: as above, deterministic, one rollout; robust: training's domain randomisation, observation
noise and pushes, R of them, each its own draw; R defaults to eval.whole_clip.rollouts), into
RUN_DIR/eval/<checkpoint>/whole_clip/ (or --out):

    whole_clip.csv            per condition and clip: rollouts, completed, success, start transients
                              (failures in the first second) and later failures, errors over completed ones
    whole_clip_survival.csv   per condition, clip and second: rollouts still tracking (a view of the
                              other two; the analysis derives it again)
    whole_clip_failures.csv   one row per failed rollout: frame, time into the clip, bin, kind
    whole_clip_summary.json   overall numbers (whole_clip_<condition>_success_rate, ...)

Bad input (missing folder, no checkpoint, a checkpoint that does not match the run's config,
--whole-clip R below 1, an unknown condition, a clip longer than eval.whole_clip.max_clip_s) prints one
`error: ...` line and exits with status 2, writing nothing.
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import logging
import sys
import time
from pathlib import Path
from typing import Sequence

from bmimic import BmimicError
from bmimic.cli.common import add_trust_flag, first_line, path_arg, user_errors
from bmimic.cli.console import quiet_warp
from bmimic.evaluation.report import format_report
from bmimic.evaluation.saved_run import (
    LoadedRun,
    evaluation_label,
    evaluation_record,
    load_run,
    load_run_checkpoint,
)
from bmimic.evaluation.tables import EvalResult, bin_table, episode_table, segment_table, write_tables
from bmimic.evaluation.whole_clip import evaluate_whole_clip, format_whole_clip, write_whole_clip_tables
from bmimic.runs import safe_read
from bmimic.runs.folder import EVAL_DIR, EVAL_SUMMARY, EVAL_TABLES, SIM2SIM_DIR, WHOLE_CLIP_DIR
from bmimic.runs.schema import HORIZON_TRUNCATED, WHOLE_CLIP_CONDITIONS, summary_key

log = logging.getLogger("bmimic.eval")


def evaluate(run: LoadedRun, overrides: Sequence[str] = ()) -> EvalResult:
    """Run the sampler-independent evaluation of `run.checkpoint` and build the tables."""
    from bmimic.runtime import seed_everything
    from bmimic.task import build_evaluator
    from bmimic.training.evaluator import summarize
    from bmimic.training.policy import build_policy

    task = run.task
    cfg, device, motion, layout = task.cfg, task.device, task.motion, task.layout
    state = load_run_checkpoint(run)
    seed_everything(cfg.seed)
    evaluator = build_evaluator(task)
    env = evaluator.env
    policy = build_policy(state, env, cfg.ppo, device, run.checkpoint)
    iteration = int(state.get("iter", -1))
    log.info("evaluating %s (iteration %d) on %s: %d bins x %d episodes, horizon %g s, %d worlds",
             run.checkpoint, iteration, device, layout.num_bins, cfg.eval.episodes_per_bin,
             cfg.eval.horizon_s, env.num_envs)
    t0 = time.perf_counter()
    rollouts = evaluator.run_episodes(policy)
    wall = time.perf_counter() - t0
    episodes = episode_table(rollouts.episodes, layout, motion, env.step_dt, iteration)
    bins = bin_table(rollouts, episodes, layout, motion.segments)
    segments = segment_table(rollouts, episodes, motion)
    summary = {
        **summarize(bins),
        "episodes": int(len(episodes)),
        "failures": int(episodes["failed"].sum()),
        "num_bins": int(layout.num_bins),
        "episodes_per_bin": int(cfg.eval.episodes_per_bin),
        "horizon_s": float(cfg.eval.horizon_s),
        "max_mpkpe_rel_mm": cfg.eval.max_mpkpe_rel_mm,
        "horizon_truncated_bins": int(bins[HORIZON_TRUNCATED].sum()),
        "eval_worlds": int(env.num_envs),
        "eval_wall_time_s": wall,
        "motion_duration_s": float(motion.duration_s),
        **evaluation_record(run, state, overrides),
    }
    return EvalResult(episodes, bins, segments, summary)


class EarlierEvaluationError(BmimicError):
    """An evaluation would replace one that sim2sim compared against."""


def keep_earlier(out_dir: Path, run_dir: Path, force: bool) -> None:
    """An earlier evaluation in `out_dir` is replaced with a warning; one that a sim2sim result of the
    same checkpoint compared its gap against only with `force` (EarlierEvaluationError otherwise)."""
    summary = out_dir / EVAL_SUMMARY
    if not summary.exists():
        there = [n for n in EVAL_TABLES if (out_dir / n).exists() or (out_dir / n).is_symlink()]
        if there:  # a folder of someone else's files that share a name with ours: never replaced
            raise EarlierEvaluationError(f"{out_dir / there[0]}: exists, and no evaluation's summary beside it says "
                                         "bmimic wrote it; choose another --out")
        return
    try:
        earlier = safe_read.read_json(summary)
    except (OSError, ValueError):
        earlier = None
    if not isinstance(earlier, dict) or "checkpoint" not in earlier or summary_key("success_rate") not in earlier:
        raise EarlierEvaluationError(f"{summary}: exists and is not a bmimic evaluation's summary; choose another --out")
    compared = sorted(p.parent for p in (run_dir / SIM2SIM_DIR).glob(f"*/{out_dir.name}/{EVAL_SUMMARY}"))
    if compared and not force:
        raise EarlierEvaluationError(
            f"{out_dir}: holds an earlier evaluation that sim2sim's gap in {compared[0]} was computed against; "
            "write this one elsewhere with --out DIR, or replace it with --force")
    log.warning("replacing the earlier evaluation in %s%s", out_dir,
                f" (the sim2sim gap in {', '.join(map(str, compared))} was computed against it)" if compared else "")


def flag_overrides(args: argparse.Namespace) -> list[str]:
    """The convenience flags as dotted overrides (applied after the positional ones, so they win)."""
    out = []
    if args.episodes_per_bin is not None:
        out.append(f"eval.episodes_per_bin={args.episodes_per_bin}")
    if args.horizon_s is not None:
        out.append(f"eval.horizon_s={args.horizon_s}")
    if args.max_envs is not None:
        out.append(f"eval.max_envs={args.max_envs}")
    if args.device is not None:
        out.append(f"device={args.device}")
    if isinstance(args.whole_clip, int):
        out.append(f"eval.whole_clip.rollouts={args.whole_clip}")
    if args.conditions is not None:
        out.append(f"eval.whole_clip.conditions=[{','.join(args.conditions)}]")
    return out


def check_flags(args: argparse.Namespace) -> None:
    """The whole-clip flags' values and --out (UsageError, one line), before anything is read."""
    if args.conditions is not None and args.whole_clip is None:
        raise UsageError("--conditions: only with --whole-clip")
    if isinstance(args.whole_clip, int) and args.whole_clip < 1:
        raise UsageError(f"--whole-clip {args.whole_clip}: the rollouts per clip must be >= 1")
    if args.out is not None and args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out}: is a file, not a folder")  # before the evaluation's minutes
    if args.conditions is not None:
        unknown = [c for c in args.conditions if c not in WHOLE_CLIP_CONDITIONS]
        if unknown or not args.conditions or len(set(args.conditions)) != len(args.conditions):
            problem = f"unknown condition {unknown[0]!r}" if unknown else "name each condition once"
            raise UsageError(f"--conditions: {problem} (known: {', '.join(WHOLE_CLIP_CONDITIONS)})")


class UsageError(BmimicError):
    """A command-line flag's value makes no sense."""


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bmimic.eval",
        description="Sampler-independent evaluation of a trained policy (deterministic actions).",
        epilog="Tables: RUN_DIR/eval/<checkpoint>/{" + ",".join(EVAL_TABLES) + "}",
    )
    p.add_argument("path", type=path_arg, help="a run folder (evaluates checkpoints/latest.pt) or a checkpoint file in one")
    p.add_argument("overrides", nargs="*", help="dotted config overrides key=value, e.g. eval.horizon_s=3")
    p.add_argument("--episodes-per-bin", type=int, help="episodes started per time bin (eval.episodes_per_bin)")
    p.add_argument("--horizon-s", type=float, help="seconds an episode must survive (eval.horizon_s)")
    p.add_argument("--max-envs", type=int, help="most simultaneous evaluation worlds (eval.max_envs)")
    p.add_argument("--device", help="cpu, cuda, cuda:N or auto (default: the run's device setting)")
    p.add_argument("--out", type=path_arg, help="folder for the tables (default RUN_DIR/eval/<checkpoint>)")
    p.add_argument("--whole-clip", nargs="?", type=int, const=..., metavar="R",  # ...: R from the config
                   help="instead of the windows: R rollouts per clip from its first frame to its last, per condition "
                        "(nominal is deterministic: one per clip); R: eval.whole_clip.rollouts (128 on a GPU, 2 on a "
                        "CPU) when left out")
    p.add_argument("--conditions", "--condition", type=lambda text: [c.strip() for c in text.split(",") if c.strip()],
                   help="with --whole-clip: nominal, robust or nominal,robust (eval.whole_clip.conditions)")
    p.add_argument("--force", action="store_true",
                   help="replace an earlier evaluation of this checkpoint even when sim2sim compared against it")
    add_trust_flag(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_intermixed_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    quiet_warp()
    overrides = [*args.overrides, *flag_overrides(args)]
    try:
        check_flags(args)
        run = load_run(args.path, overrides, trust=args.trust_checkpoint)
        if args.out is None:  # RUN/eval/<checkpoint>: checked before the evaluation's minutes
            from bmimic.training.checkpoints import load_checkpoint_file

            state = load_checkpoint_file(run.checkpoint, "cpu")
            out_dir = run.run_dir / EVAL_DIR / evaluation_label(run, state)
            out_dir = out_dir / WHOLE_CLIP_DIR if args.whole_clip is not None else out_dir
        else:
            out_dir = args.out
        if args.whole_clip is not None:
            whole = evaluate_whole_clip(run, overrides)
            write_whole_clip_tables(whole, out_dir.resolve())
        else:
            keep_earlier(out_dir.resolve(), run.run_dir, args.force)
            result = evaluate(run, overrides)
            write_tables(result, out_dir.resolve())
    except user_errors() as e:
        print(f"error: {first_line(e)}", file=sys.stderr)
        return 2
    print(format_whole_clip(whole) if args.whole_clip is not None else format_report(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
