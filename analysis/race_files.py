"""Reading a race JSON (``bmimic-race-1``, written by ``python -m bmimic.race``): the one reader and checker that
the race commands of analysis share (analysis.races, analysis.race_whole_clip)."""

from __future__ import annotations

from pathlib import Path

from analysis import AnalysisError
from bmimic.runs import safe_read
from bmimic.runs.schema import ENV_STEPS, ITERATION, MPKPE_REL_MM, RACE_KIND, SUCCESS_RATE

EVALUATION_KEYS = (ITERATION, ENV_STEPS, "wall_from_launch_s", SUCCESS_RATE, MPKPE_REL_MM)
"""Keys every evaluation record of a race JSON must have."""

THRESHOLD_KEYS = ("metric", "threshold", "status", ITERATION, ENV_STEPS, "wall_from_launch_s",
                  "wall_from_first_iteration_s")
"""What a race JSON records of each threshold (the times empty when censored)."""


def read_race(path: str | Path) -> dict:
    """One race JSON, checked: its kind, its config and every evaluation's keys (AnalysisError, one line
    naming the file, otherwise)."""
    path = Path(path)
    try:
        data = safe_read.read_json(path, finite=True)  # bmimic.race writes null for what it did not measure
    except FileNotFoundError:
        raise AnalysisError(f"{path}: no such file") from None
    except (OSError, ValueError) as e:
        raise AnalysisError(f"{path}: not a readable JSON file ({str(e).splitlines()[0]})") from None
    if not isinstance(data, dict) or data.get("kind") != RACE_KIND:
        kind = data.get("kind") if isinstance(data, dict) else type(data).__name__
        raise AnalysisError(f"{path}: kind is {kind!r}, expected {RACE_KIND!r} (a bmimic.race --json file)")
    if not isinstance(data.get("config"), dict):
        raise AnalysisError(f"{path}: no 'config' object")
    evals = data.get("evaluations")
    if not isinstance(evals, list):
        raise AnalysisError(f"{path}: 'evaluations' is not a list")
    for i, ev in enumerate(evals):
        missing = [k for k in EVALUATION_KEYS if not isinstance(ev, dict) or k not in ev]
        if missing:
            raise AnalysisError(f"{path}: evaluation {i} lacks {', '.join(missing)}")
        bad = [k for k in EVALUATION_KEYS if not _number_or_null(ev[k])]
        if bad or not (isinstance(ev[ITERATION], int) and not isinstance(ev[ITERATION], bool) and ev[ITERATION] >= 0):
            key = bad[0] if bad else ITERATION
            raise AnalysisError(f"{path}: evaluation {i}: {key} is {ev[key]!r}, not a number"
                                f"{'' if bad else ' of iterations (an integer >= 0)'}")
    thresholds = data.get("thresholds") or []
    if not isinstance(thresholds, list) or not all(
            isinstance(t, dict) and _number_or_null(t.get("threshold")) and t.get("threshold") is not None
            and all(_number_or_null(t.get(k)) for k in THRESHOLD_KEYS[3:]) for t in thresholds):
        raise AnalysisError(f"{path}: 'thresholds' must be a list of objects with a numeric threshold and "
                            "numeric (or null) times")
    if not isinstance(data["config"].get("overrides", []), list):
        raise AnalysisError(f"{path}: config 'overrides' is not a list")
    return data


def _number_or_null(value) -> bool:
    """A JSON number (not a boolean) or null (a value that was not a number when written)."""
    return value is None or (isinstance(value, int | float) and not isinstance(value, bool))


