"""Convert a LAFAN1-retargeted G1 CSV to the project's motion npz.

    python -m bmimic.motion.convert IN.csv OUT.npz --fps-in 30 --fps-out 50 [--frames A B] [--force]

The CSV has no header and one row per frame: root position xyz (m), root quaternion x, y, z, w,
then the 29 joint angles (rad) in the order of `CSV_JOINT_NAMES`. The output is resampled to
`fps_out` (times 0, 1/fps_out, ... < (N-1)/fps_in; positions and joints interpolated linearly, the
root orientation by slerp), velocities come from finite differences and body states from forward
kinematics of the project's G1 model (`bmimic.motion.kinematics.kinematic_motion`).
"""

from bmimic.cli.startup import start_command

start_command(__spec__.name)  # first: the working directory off sys.path, MUJOCO_GL (bmimic.cli.startup)

import argparse
import sys
import time
from pathlib import Path
from typing import Sequence

import mujoco
import numpy as np

from bmimic.cli.common import path_arg
from bmimic.motion.kinematics import kinematic_motion
from bmimic.motion.limits import check_motion_size, check_plausible
from bmimic.motion.math import output_times, quat_slerp
from bmimic.motion.model import find_joint_limit_violation
from bmimic.motion.motion import Motion
from bmimic.motion.segments import MotionDataError, Segment
from bmimic.robot.models.g1 import G1_JOINT_NAMES

CSV_JOINT_NAMES = G1_JOINT_NAMES
"""Column order of the 29 joint angles: the LAFAN1 G1 retargets list them in the G1's MuJoCo order."""
NUM_COLUMNS = 7 + len(CSV_JOINT_NAMES)
QUAT_NORM_TOLERANCE = 1e-3
JOINT_LIMIT_TOLERANCE_RAD = 0.1


def read_lafan_csv(path: str | Path, frames: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Parse and check the table; returns (data [N, 36] float64, 1-indexed file line of each row).

    `frames=(A, B)` keeps data rows A..B (1-indexed, inclusive). Errors name file, row and column.
    """
    path = Path(path)
    if not path.is_file():
        raise MotionDataError(f"{path}: file not found")
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise MotionDataError(f"{path}: cannot read as text ({err})") from None
    numbered = [(i + 1, line) for i, line in enumerate(text.splitlines()) if line.strip()]
    if not numbered:
        raise MotionDataError(f"{path}: file is empty")
    lines = [line for _, line in numbered]
    rows = np.asarray([n for n, _ in numbered], dtype=np.int64)
    try:
        data = np.loadtxt(lines, delimiter=",", dtype=np.float64, ndmin=2)
        ok = data.shape[1] == NUM_COLUMNS
    except ValueError:
        ok = False
    if not ok:
        # Slow path, only to say exactly where the table is malformed.
        _locate_parse_error(path, numbered)
        raise MotionDataError(f"{path}: cannot parse as a {NUM_COLUMNS}-column numeric CSV")

    if frames is not None:
        first, last = frames
        if not 1 <= first < last <= len(rows):
            raise MotionDataError(
                f"{path}: --frames {first} {last} is not a range within the file's 1..{len(rows)} rows"
            )
        data, rows = data[first - 1 : last], rows[first - 1 : last]

    bad = ~np.isfinite(data)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise MotionDataError(f"{path}: row {rows[r]}, column {c + 1}: value {data[r, c]} is not finite")
    norms = np.linalg.norm(data[:, 3:7], axis=1)
    off = np.abs(norms - 1.0) > QUAT_NORM_TOLERANCE
    if off.any():
        r = int(np.argmax(off))
        raise MotionDataError(
            f"{path}: row {rows[r]}, column 4: root quaternion (columns 4-7, x y z w) has norm "
            f"{norms[r]:.6f}, not 1 within {QUAT_NORM_TOLERANCE}"
        )
    return data, rows


def _locate_parse_error(path: Path, numbered: list[tuple[int, str]]) -> None:
    for lineno, line in numbered:
        cells = line.split(",")
        if len(cells) != NUM_COLUMNS:
            raise MotionDataError(
                f"{path}: row {lineno}, column {min(len(cells), NUM_COLUMNS) + 1}: found {len(cells)} "
                f"columns, expected {NUM_COLUMNS} (root xyz, root quaternion xyzw, 29 joints)"
            )
        for col, cell in enumerate(cells):
            try:
                float(cell)
            except ValueError:
                hint = " (the file must have no header row)" if lineno == numbered[0][0] else ""
                raise MotionDataError(
                    f"{path}: row {lineno}, column {col + 1}: {cell.strip()[:24]!r} is not a number{hint}"
                ) from None


def check_joint_limits(path: Path, data: np.ndarray, rows: np.ndarray, mjmodel: mujoco.MjModel) -> None:
    bad = find_joint_limit_violation(data[:, 7:], CSV_JOINT_NAMES, mjmodel, JOINT_LIMIT_TOLERANCE_RAD)
    if bad is not None:
        r, j, value, low, high = bad
        raise MotionDataError(
            f"{path}: row {rows[r]}, column {8 + j}: {CSV_JOINT_NAMES[j]} = {value:.4f} rad is outside its "
            f"range [{low:.4f}, {high:.4f}] by more than {JOINT_LIMIT_TOLERANCE_RAD} rad"
        )


def resample(data: np.ndarray, fps_in: float, fps_out: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Root position [T, 3], root quaternion [T, 4] (w, x, y, z) and joints [T, 29] at fps_out."""
    times = output_times(data.shape[0], fps_in, fps_out)
    index = times * fps_in
    i0 = np.minimum(np.floor(index).astype(np.int64), data.shape[0] - 2)
    blend = index - i0
    lerp = data[i0] + (data[i0 + 1] - data[i0]) * blend[:, None]
    quat_wxyz = data[:, [6, 3, 4, 5]]
    root_quat = quat_slerp(quat_wxyz[i0], quat_wxyz[i0 + 1], blend)
    return lerp[:, 0:3], root_quat, lerp[:, 7:]


def convert_csv(
    path: str | Path,
    mjmodel: mujoco.MjModel,
    fps_in: float = 30.0,
    fps_out: float = 50.0,
    frames: tuple[int, int] | None = None,
) -> Motion:
    """Read, check, resample and run forward kinematics; one segment named after the file."""
    path = Path(path)
    if not (np.isfinite(fps_in) and np.isfinite(fps_out) and fps_in > 0 and fps_out > 0):
        raise MotionDataError(f"{path}: fps_in and fps_out must be positive, got {fps_in} and {fps_out}")
    data, rows = read_lafan_csv(path, frames)
    check_joint_limits(path, data, rows, mjmodel)
    check_motion_size(mjmodel, (data.shape[0] - 1) / fps_in, fps_out, f"{path}: --fps-out {fps_out:g}")
    if data.shape[0] < 2 or len(output_times(data.shape[0], fps_in, fps_out)) < 2:
        raise MotionDataError(
            f"{path}: {data.shape[0]} rows at {fps_in} fps give fewer than 2 frames at {fps_out} fps"
        )
    root_pos, root_quat, joint_pos = resample(data, fps_in, fps_out)
    duration = root_pos.shape[0] / fps_out
    segments = [Segment(path.stem, 0.0, duration, "unknown")]
    try:
        return kinematic_motion(mjmodel, fps_out, root_pos, root_quat, joint_pos, CSV_JOINT_NAMES, segments)
    except MotionDataError as err:
        raise MotionDataError(f"{path}: {err}") from None


def check_output_path(src: Path, out: Path, force: bool) -> str | None:
    """Why OUT cannot be written (one line), or None: never the input itself (also through links),
    always a .npz, an existing file only with --force, never a folder."""
    if out.suffix != ".npz":
        return f"{out}: the output must end in .npz"
    try:
        same = out.exists() and src.exists() and out.resolve() == src.resolve()
    except OSError:
        same = False
    if same or (not out.exists() and out.resolve() == src.resolve()):
        return f"{out}: is the input file itself; choose another output"
    if out.is_dir():
        return f"{out}: is a folder; give the output file's name"
    if out.exists() and not force:
        return f"{out}: exists; pass --force to replace it"
    if not out.parent.is_dir():
        return f"{out}: folder {out.parent} does not exist"
    return None


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m bmimic.motion.convert", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("input", type=path_arg, help="LAFAN1 G1 CSV (no header, 36 columns)")
    parser.add_argument("output", type=path_arg, help="motion npz to write")
    parser.add_argument("--fps-in", type=float, default=30.0, help="frame rate of the CSV (default 30)")
    parser.add_argument("--fps-out", type=float, default=50.0, help="frame rate to write (default 50)")
    parser.add_argument(
        "--frames", type=int, nargs=2, metavar=("A", "B"), help="keep CSV rows A..B (1-indexed, inclusive)"
    )
    parser.add_argument("--mjcf", type=path_arg, default=None, help="robot MJCF instead of the built-in G1")
    parser.add_argument("--force", action="store_true", help="replace OUT when it exists")
    parser.add_argument("--allow-implausible", action="store_true",
                        help="write a motion that is not a plausible reference (root upside down at the first "
                             "frame, feet far from the ground) instead of refusing it")
    args = parser.parse_args(argv)
    problem = check_output_path(args.input, args.output, args.force)
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2

    # late import: the robot package is only needed past argument parsing
    from bmimic.robot import RobotModelError, load_mjmodel

    start = time.perf_counter()
    try:
        mjmodel = load_mjmodel("g1", mjcf_path=None if args.mjcf is None else str(args.mjcf))
        motion = convert_csv(
            args.input,
            mjmodel,
            args.fps_in,
            args.fps_out,
            None if args.frames is None else tuple(args.frames),
        )
        if not args.allow_implausible:
            check_plausible(motion, str(args.input), "pass --allow-implausible", mjmodel)
        motion.save(args.output)
    except (MotionDataError, RobotModelError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except OSError as err:  # OUT's folder missing, not writable, a directory, disk full
        print(f"error: {args.output}: cannot write ({err.strerror or err})", file=sys.stderr)
        return 2
    elapsed = time.perf_counter() - start
    print(
        f"wrote {args.output}: {motion.num_frames} frames at {motion.fps:g} Hz "
        f"({motion.duration_s:.2f} s) in {elapsed:.2f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
