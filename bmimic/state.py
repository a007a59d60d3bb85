"""`python -m bmimic.state save|restore`: carry a job of a study from one sitting to the next in git.

    python -m bmimic.state save RUN STATE [--moments fp32|bf16]   # the newest checkpoint of RUN -> STATE
    python -m bmimic.state restore STATE RUN                      # STATE -> RUN/checkpoints (then resume=true)

A sitting ends with `save` into docs/results/<study>/state/ (a few MB: no worlds' state, no motion) and the
job's tables compacted into docs/results/<study>/runs/ (analysis.compact), both committed. The next sitting
copies the job's committed record to the run folder the study trains in, `restore`s the state into it and
continues the job with `resume=true` (bmimic.training.study_state says what a state holds and drops).
`save` replaces only an earlier state of the same job; `restore` writes only into a run folder that holds
no checkpoint and whose record trained the same job to the state's iteration. Bad input prints one
`error: ...` line (status 2) and writes nothing.
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import sys
from pathlib import Path
from typing import Sequence

from bmimic.cli.common import first_line, path_arg, user_errors


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bmimic.state",
                                description=__doc__.splitlines()[0].split(": ", 1)[1],
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                epilog="\n".join(__doc__.splitlines()[2:]))
    sub = p.add_subparsers(dest="command", required=True)
    save = sub.add_parser("save", help="write the newest intact checkpoint of RUN as a state file")
    save.add_argument("run", type=path_arg, help="a run folder with a checkpoint")
    save.add_argument("state", type=path_arg, help="the state file to write (e.g. docs/results/STUDY/state/JOB.pt)")
    save.add_argument("--moments", choices=("fp32", "bf16"), default="fp32",
                      help="the optimiser's Adam moments exactly (fp32, default) or in bfloat16 (half their bytes)")
    restore = sub.add_parser("restore", help="write a state file's checkpoint into a run folder's checkpoints/")
    restore.add_argument("state", type=path_arg, help="a state file written by `save`")
    restore.add_argument("run", type=path_arg, help="a run folder holding the job's record and no checkpoint")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    from bmimic.training.study_state import restore_state, save_state

    try:
        if args.command == "save":
            state = save_state(Path(args.run), Path(args.state), args.moments)
            size_mb = Path(args.state).stat().st_size / 1e6
            print(f"{args.state}: iteration {state['iter']}, {size_mb:.1f} MB (moments {args.moments})")
        else:
            latest = restore_state(Path(args.state), Path(args.run))
            print(f"{latest}: restored; continue the job with resume=true and hydra.run.dir={args.run}")
    except user_errors() as e:
        print(f"error: {first_line(e)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
