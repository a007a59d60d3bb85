"""Write a synthetic G1 clip in the CSV format bmimic reads, to try "your own motion" without LAFAN1.

    python -m bmimic.motion.example OUT.csv [--seconds 4] [--fps 30] [--seed 0] [--force]

The clip is the first seconds of the built-in motion (standing, arm waves, torso twists, made by the
project's own inverse kinematics on the G1; bmimic.motion.builtin), resampled to `--fps` and written as
the LAFAN1 G1 CSV: no header, one row per frame, root position x y z (m), root quaternion x y z w, the 29
joint angles (rad) in the G1's MuJoCo order (bmimic.motion.convert.CSV_JOINT_NAMES). It holds no
motion-capture data, so it may be shared freely. Train on it with
`python -m bmimic.train motion=file motion.path=OUT.csv motion.fps_in=FPS`.
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import io
import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from bmimic.cli.common import path_arg
from bmimic.motion.segments import MotionDataError

MAX_SECONDS = 30.0
"""The built-in motion's length: the clip is a window of it."""


def example_table(seconds: float, fps: float, seed: int = 0) -> np.ndarray:
    """[N, 36] rows of the CSV: the built-in motion's first `seconds`, at `fps` frames per second."""
    from bmimic.motion.builtin import generate_builtin
    from bmimic.robot import load_mjmodel
    from bmimic.robot.models.g1 import G1_JOINT_NAMES  # the CSV's column order (bmimic.motion.convert)

    mjmodel = load_mjmodel("g1")
    motion = generate_builtin(mjmodel, "graded", seed, MAX_SECONDS).window(0.0, seconds).resample(fps)
    order = [motion.joint_names.index(name) for name in G1_JOINT_NAMES]
    root_quat_wxyz = motion.body_quat_w[:, 0]
    return np.concatenate([motion.body_pos_w[:, 0], root_quat_wxyz[:, [1, 2, 3, 0]], motion.joint_pos[:, order]], axis=1)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bmimic.motion.example", description=__doc__.split("\n\n")[0])
    p.add_argument("output", type=path_arg, help="CSV file to write")
    p.add_argument("--seconds", type=float, default=4.0, help=f"length of the clip (default 4, at most {MAX_SECONDS:g})")
    p.add_argument("--fps", type=float, default=30.0, help="frame rate of the CSV (default 30, LAFAN1's)")
    p.add_argument("--seed", type=int, default=0, help="the built-in motion's seed (default 0)")
    p.add_argument("--force", action="store_true", help="replace OUTPUT when it exists")
    args = p.parse_args(argv)
    out: Path = args.output
    problem = None
    if out.suffix.lower() != ".csv":
        problem = f"{out}: the output must end in .csv"
    elif out.is_dir():
        problem = f"{out}: is a folder; give the output file's name"
    elif out.exists() and not args.force:
        problem = f"{out}: exists; pass --force to replace it"
    elif not (0 < args.seconds <= MAX_SECONDS):
        problem = f"--seconds: must be in (0, {MAX_SECONDS:g}], got {args.seconds:g}"
    elif not (np.isfinite(args.fps) and 1 <= args.fps <= 1000):
        problem = f"--fps: must be between 1 and 1000, got {args.fps:g}"
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    try:
        table = example_table(args.seconds, args.fps, args.seed)
        buf = io.StringIO()
        np.savetxt(buf, table, delimiter=",", fmt="%.6f")
        from bmimic.runs.atomic_io import atomic_write_bytes

        atomic_write_bytes(out, buf.getvalue().encode())
    except MotionDataError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:
        print(f"error: {out}: cannot write ({err.strerror or err})", file=sys.stderr)
        return 2
    print(f"wrote {out}: {len(table)} frames at {args.fps:g} fps ({args.seconds:g} s); train on it with\n"
          f"  python -m bmimic.train motion=file motion.path={out} motion.fps_in={args.fps:g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
