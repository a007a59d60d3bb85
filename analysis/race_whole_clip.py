"""``python -m analysis.race_whole_clip RUN [--native] [--json PATH]``: a race's whole-clip finish line decided
after the race, from whole clips evaluated on its checkpoints.

A whole-clip evaluation inside the race stops training (51-79 s on an H200 for the 131.5 s dance), and the
race's 10% evaluation share left room for none in a 1250 s race (docs/benchmarks.md, 2026-11-29). Evaluating
the race's checkpoints afterwards, on another GPU or in native MuJoCo on CPU cores, measures the same policies
without touching the race's clock:

    python -m bmimic.eval RUN/checkpoints/model_N.pt --whole-clip 128 --conditions robust          # each N
    python -m bmimic.sim2sim RUN/checkpoints/motion_policy_N.onnx --whole-clip 128 --conditions robust
    python -m analysis.race_whole_clip RUN [--native] --json docs/bench/<name>.json

Each checkpoint's robust whole-clip success is placed at the race's evaluation of the same iteration (its wall
time from launch is when that policy existed), and the race's thresholds are decided again by the race's own
rule (bmimic.runs.race_record.rejudge): held over `sustain` evaluations in a row that measured them, timed at
the first. The times are the policy's, not its evaluation's, which ran outside the clock; the record names
its source. Checkpoints align with the race's evaluations when ppo.save_interval is a multiple of
eval.every_iters (500 and 100 by default; `ppo.save_interval=200` gives a finer finish line).
"""

from bmimic.cli.startup import leave_working_directory

leave_working_directory(__spec__.name)  # first: under `python -m` (bmimic.cli.startup); no MuJoCo here

import argparse
import json
import sys
from pathlib import Path

from analysis import REFUSED, AnalysisError, error_line
from analysis.files import write_text
from analysis.race_files import read_race
from bmimic.cli.common import path_arg
from bmimic.runs import safe_read
from bmimic.runs.folder import (
    EVAL_DIR,
    EVAL_SUMMARY,
    RACE,
    SIM2SIM_DIR,
    SIM2SIM_WHOLE_CLIP,
    WHOLE_CLIP_DIR,
    WHOLE_CLIP_FILES,
)
from bmimic.runs.race_judge import NATIVE_MODEL
from bmimic.runs.race_record import WHOLE_CLIP_METRIC, Threshold, rejudge
from bmimic.runs.schema import ITERATION, whole_clip_success

WARP_SUMMARY = WHOLE_CLIP_FILES[-1]
"""bmimic.eval --whole-clip's summary in RUN/eval/<checkpoint>/whole_clip/."""
NATIVE_SUMMARY = EVAL_SUMMARY
"""bmimic.sim2sim --whole-clip's summary in RUN/sim2sim/<model>/<checkpoint>/whole_clip/."""


def _read(path: Path) -> dict:
    try:
        data = safe_read.read_json(path)
    except (OSError, ValueError) as e:
        raise AnalysisError(f"{path}: not a readable JSON file ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict) or not isinstance(data.get(ITERATION), int):
        raise AnalysisError(f"{path}: no integer {ITERATION!r}")
    return data


def _robust_success(path: Path, data: dict) -> float | None:
    """The summary's robust whole-clip success (None: it evaluated the nominal condition only)."""
    try:
        return whole_clip_success(data, "robust")
    except ValueError as e:
        raise AnalysisError(f"{path}: {e}") from None


def checkpoint_success(run_dir: str | Path, native: bool = False, model: str = NATIVE_MODEL) -> dict[int, tuple[float, Path]]:
    """Iteration -> (robust whole-clip success, its summary file) of every checkpoint evaluated under RUN:
    RUN/eval/*/whole_clip (bmimic.eval) or, `native`, RUN/sim2sim/<model>/*/whole_clip (bmimic.sim2sim). Two
    summaries of one iteration that disagree are refused (one line naming both)."""
    run_dir = Path(run_dir)
    pattern = (f"{SIM2SIM_DIR}/{model}/*/{SIM2SIM_WHOLE_CLIP}/{NATIVE_SUMMARY}" if native
               else f"{EVAL_DIR}/*/{WHOLE_CLIP_DIR}/{WARP_SUMMARY}")
    found: dict[int, tuple[float, Path]] = {}
    for path in sorted(run_dir.glob(pattern)):
        data = _read(path)
        value = _robust_success(path, data)
        if value is None:
            continue
        it = data[ITERATION]
        if it in found and found[it][0] != value:
            raise AnalysisError(f"{found[it][1]} and {path}: two robust whole-clip results for iteration {it} "
                                f"({found[it][0]:g} and {value:g}); keep one")
        found.setdefault(it, (value, path))
    return found


def race_whole_clip(run_dir: str | Path, native: bool = False, model: str = NATIVE_MODEL) -> dict:
    """The run's race.json with its checkpoints' robust whole-clip success added and its thresholds decided
    again (module docstring); AnalysisError (one line) when there is nothing to add or it does not align."""
    run_dir = Path(run_dir)
    record = read_race(run_dir / RACE)
    found = checkpoint_success(run_dir, native, model)
    if not found:
        where = f"{SIM2SIM_DIR}/{model}/*/{SIM2SIM_WHOLE_CLIP}" if native else f"{EVAL_DIR}/*/{WHOLE_CLIP_DIR}"
        raise AnalysisError(f"{run_dir}: no robust whole-clip evaluation of a checkpoint under {where} "
                            "(module docstring: the commands)")
    try:
        source = ("native MuJoCo (bmimic.sim2sim --whole-clip), model " + model if native
                  else "MuJoCo-Warp (bmimic.eval --whole-clip)") + ", on the race's checkpoints after the race"
        return rejudge(record, {it: v for it, (v, _) in found.items()}, source)
    except ValueError as e:
        raise AnalysisError(f"{run_dir / RACE}: {e}") from None


def lines(record: dict) -> list[str]:
    """One line per threshold, labelled as the race labels it, then where the whole clips came from."""
    out = []
    for t in record["thresholds"]:
        name = Threshold(t["metric"], float(t["threshold"])).label
        if t["status"] == "reached":
            out.append(f"{name}: iteration {t[ITERATION]}, {t['wall_from_launch_s']:.0f} s from launch")
        else:
            out.append(f"{name}: censored")
    measured = [e for e in record["evaluations"] if WHOLE_CLIP_METRIC in e]
    out.append(f"whole clips at {len(measured)} evaluations: "
               + ", ".join(f"{e[ITERATION]}: {e[WHOLE_CLIP_METRIC]:.3g}" for e in measured))
    out.append(f"source: {record['whole_clip_source']}")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m analysis.race_whole_clip", description=__doc__.splitlines()[0])
    parser.add_argument("run", type=path_arg, help="the race's run folder (its race.json and evaluated checkpoints)")
    parser.add_argument("--native", action="store_true", help="the checkpoints' native-MuJoCo whole clips (bmimic.sim2sim)")
    parser.add_argument("--model", default=NATIVE_MODEL, help="with --native: the sim2sim model's folder (default bmimic_g1)")
    parser.add_argument("--json", type=path_arg, help="write the record here (e.g. docs/bench/<name>.json)")
    args = parser.parse_args(argv)
    try:
        record = race_whole_clip(args.run, args.native, args.model)
        if args.json is not None:
            write_text(args.json, json.dumps(record, indent=2) + "\n")
    except REFUSED as e:
        print(error_line(e), file=sys.stderr)
        return 2
    for line in lines(record):
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
