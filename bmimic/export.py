"""`python -m bmimic.export RUN_DIR_OR_CHECKPOINT [--out DIR]`: write a checkpoint's ONNX files.

Training writes them at every checkpoint; this command (re)writes them for a run trained before the
BeyondMimic-compatible file existed, or for one checkpoint of it:

    checkpoints/policy_<it>.onnx          obs -> actions, with deployment metadata
    checkpoints/motion_policy_<it>.onnx   (obs, time_step) -> actions + reference at time_step, the
                                          motion baked in (BeyondMimic's format; bmimic.sim2sim runs it)

The run's config is reloaded as `bmimic.eval` does, and a one-world evaluation environment on the CPU
supplies the robot, motion and observation layout. Overrides as eval takes them (`motion=<option, clip
file or folder of clips>`) bake another motion into motion_policy, e.g. a library policy's for one clip
(`--out` then names the folder: the files are not the run's own). Bad input prints one `error: ...` line (status 2).
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import logging
import sys
from pathlib import Path
from typing import Sequence

from bmimic.cli.common import add_trust_flag, first_line, path_arg, user_errors
from bmimic.runs.folder import checkpoints_dir, make_folder

log = logging.getLogger("bmimic.export")


def export_run(path: str | Path, out_dir: Path | None = None, trust: bool = False, force: bool = False,
               overrides: Sequence[str] = ()) -> list[Path]:
    """Export the run's latest checkpoint (or the given one); returns the written files. `trust`
    (--trust-checkpoint): a run config whose env terms import code outside bmimic is loaded, as
    bmimic.eval does. Existing ONNX files of the same iteration are replaced only with `force`.
    `overrides` (e.g. motion=clip.csv) need `out_dir`: files of another motion never land beside the run's."""
    from bmimic import BmimicError
    from bmimic.evaluation.saved_run import load_run, load_run_checkpoint
    from bmimic.runs.folder import motion_policy_onnx_name, policy_onnx_name
    from bmimic.task import build_evaluator
    from bmimic.training.onnx_export import export_checkpoint_onnx
    from bmimic.training.policy import build_policy

    if overrides and out_dir is None:
        raise BmimicError(f"overrides {' '.join(overrides)}: give --out DIR, since the files would not be the run's own")
    run = load_run(path, [*overrides, "device=cpu", "eval.max_envs=1"], trust=trust)
    task = run.task
    state = load_run_checkpoint(run)
    target = out_dir or checkpoints_dir(run.run_dir)
    it = int(state.get("iter", -1))
    there = [n for n in (policy_onnx_name(it), motion_policy_onnx_name(it)) if (target / n).exists()]
    if there and not force:
        raise BmimicError(f"{target / there[0]}: exists; add --force to replace it")
    if out_dir is not None:
        make_folder(out_dir)
    env = build_evaluator(task).env
    policy = build_policy(state, env, task.cfg.ppo, task.device, run.checkpoint)
    iteration = int(state.get("iter", -1))
    return export_checkpoint_onnx(policy, env, out_dir or checkpoints_dir(run.run_dir), iteration)


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bmimic.export", description=__doc__.splitlines()[0].split(": ", 1)[1])
    p.add_argument("path", type=path_arg, help="a run folder (its latest checkpoint) or a checkpoint file in one")
    p.add_argument("overrides", nargs="*", help="dotted overrides as bmimic.eval takes them, e.g. motion=clip.csv "
                                                "(another motion baked in; needs --out)")
    p.add_argument("--out", type=path_arg, help="folder for the files (default RUN_DIR/checkpoints)")
    p.add_argument("--force", action="store_true", help="replace ONNX files of the same iteration that exist")
    add_trust_flag(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from bmimic.cli.console import quiet_warp

    args = parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    quiet_warp()
    try:
        paths = export_run(args.path, args.out, trust=args.trust_checkpoint, force=args.force, overrides=args.overrides)
    except user_errors() as e:
        print(f"error: {first_line(e)}", file=sys.stderr)
        return 2
    for p in paths:
        print(p)
    return 0


if __name__ == "__main__":
    sys.exit(main())
