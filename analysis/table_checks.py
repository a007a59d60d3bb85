"""A run table checked on load against the run record's contract (bmimic.runs.schema) and the run's own
motion (motion_segments.json, metrics.json): a damaged or hand-edited table (a failure rate of 5.0, a
bin the motion does not have, no rows, a needed column without a single number, an iteration that is
not a count) is one AnalysisError naming the file and the column, never a report computed from it.

Torch-free; plain checks over a pandas frame, run once per table and run by analysis.load.load_table.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from analysis import AnalysisError
from bmimic.runs.folder import METRICS, MOTION_SEGMENTS, read_json, read_metrics, read_status
from bmimic.runs.schema import (
    BIN,
    BIN_COLUMNS,
    CONDITION,
    ENV_STEPS,
    FAILURE_RATE,
    HORIZON_TRUNCATED,
    ITERATION,
    WALL_TIME_S,
    table_problems,
)

RATE_COLUMNS = (FAILURE_RATE, "probability", "raw_failure_rate")
"""Columns that hold a rate or a probability: in [0, 1] (NaN where nothing was measured). (The released
sampler's `smoothed_failure_rate` is an EMA of counts, which may exceed 1.)"""
COUNT_COLUMNS = (*(c for c in BIN_COLUMNS if c not in (BIN, FAILURE_RATE, HORIZON_TRUNCATED)), "episodes",
                 "steps", "start_frame", "end_frame")
"""Columns that hold counts: >= 0 (NaN where nothing was measured)."""
TEXT_COLUMNS = ("segment", "clip", "clip_name", "difficulty", CONDITION)
"""The only columns that hold text (labels); every other column of a run table holds numbers or flags."""
MEASURED = {
    "train_metrics": (ITERATION, ENV_STEPS, WALL_TIME_S),
    "eval": (ITERATION, ENV_STEPS, WALL_TIME_S, BIN, FAILURE_RATE),
    "eval_robust": (ITERATION, ENV_STEPS, WALL_TIME_S, BIN, FAILURE_RATE),
    "sampler": (ITERATION, BIN, "probability"),
    "clip_eval": (ITERATION,),
}
"""Per table, the columns the report computes from: each must hold at least one number."""
BINNED = ("eval", "eval_robust", "sampler")
"""The tables that hold every bin of the run once per evaluation (whole_clip_failures names one bin a row)."""
TIME_TOLERANCE_S = 1e-6
"""Slack on a bin's end against the motion's duration (float rounding of the bin edges)."""
PROBABILITY_TOLERANCE = 1e-3
"""Slack on a sampling distribution's total (float32 sums over thousands of bins)."""


def motion_duration_s(run_dir: str | Path) -> float | None:
    """The motion's length in seconds from the run's motion_segments.json (the last segment's end),
    or None when the file is absent or holds no usable segment."""
    data = read_json(Path(run_dir) / MOTION_SEGMENTS)
    ends = [s.get("end_s") for s in data if isinstance(s, dict)] if isinstance(data, list) else []
    finite = [float(e) for e in ends if isinstance(e, int | float) and not isinstance(e, bool) and math.isfinite(e)]
    return max(finite) if finite else None


def recorded_bins(run_dir: str | Path) -> int | None:
    """The run's number of bins from metrics.json (None before the run finished)."""
    metrics = read_json(Path(run_dir) / METRICS)
    n = metrics.get("num_bins") if isinstance(metrics, dict) else None
    return int(n) if isinstance(n, int) and not isinstance(n, bool) and n >= 1 else None


def finished_iterations(run_dir: str | Path) -> int | None:
    """The iterations a finished run trained (metrics.json, when status.json says done; None otherwise: a
    run being trained or resumed has tables past its last metrics.json)."""
    if read_status(run_dir).get("status") != "done":
        return None
    n = read_metrics(run_dir).get("iterations")
    return int(n) if isinstance(n, int) and not isinstance(n, bool) and n >= 0 else None


def check_table(path: Path, name: str, table: pd.DataFrame, run_dir: str | Path) -> None:
    """Raise AnalysisError (one line: the file, the column, what is wrong) when `table` (the run
    table `name` read from `path`) breaks the contract; see the module doc."""
    if table.empty:
        raise AnalysisError(f"{path}: has no rows (bmimic writes a table only once it has rows): the file is "
                            "damaged; move the run aside or train it again")
    for column in table.columns:
        if column not in TEXT_COLUMNS and not _numeric(table[column]):
            raise AnalysisError(f"{path}: column {column} holds {_show(_example(table[column]))}, not numbers")
    for column in MEASURED.get(name, ()):
        if column in table.columns and not np.isfinite(table[column].to_numpy(dtype=float)).any():
            raise AnalysisError(f"{path}: column {column} has no finite value in {len(table)} rows")
    _check_key(path, table, ITERATION)
    last, done = int(table[ITERATION].max()), finished_iterations(run_dir)
    if done is not None and last > done:  # an iteration far past the run's own (issue 77: 1e18 in a 1-iteration run)
        raise AnalysisError(f"{path}: column {ITERATION} holds {last}, past the {done} iterations the finished run "
                            "trained (metrics.json): the table is damaged; move the run aside or train it again")
    if "episodes" in table.columns:  # an iteration in which episodes ended has their mean length and return
        ended = table["episodes"].to_numpy(dtype=float) > 0
        for column in ("mean_episode_length", "mean_reward"):
            if column in table.columns and not np.isfinite(table[column].to_numpy(dtype=float)[ended]).all():
                raise AnalysisError(f"{path}: column {column} is not a number in an iteration in which episodes ended")
    for column in (ENV_STEPS, WALL_TIME_S, *COUNT_COLUMNS):
        if column in table.columns:
            _check_range(path, table[column], column, 0.0, math.inf)
    for column in RATE_COLUMNS:
        if column in table.columns:
            _check_range(path, table[column], column, 0.0, 1.0)
    if BIN in table.columns and name in BINNED:
        _check_bins(path, name, table, run_dir)
    broken = table_problems(name, table)  # counts within their totals, errors >= 0, monotone iterations
    if broken:
        raise AnalysisError(f"{path}: {broken[0]}: the table is damaged; move the run aside or train it again")


def _numeric(values: pd.Series) -> bool:
    return pd.api.types.is_numeric_dtype(values) or pd.api.types.is_bool_dtype(values)


def _show(value) -> str:
    """A cell as the user would write it (`5.0`, `'1x'`), not numpy's repr."""
    value = value.item() if hasattr(value, "item") else value
    return repr(value)


def _example(values: pd.Series):
    bad = pd.to_numeric(values, errors="coerce").isna() & values.notna()
    return values[bad].iloc[0] if bad.any() else values.iloc[0]


def _check_key(path: Path, table: pd.DataFrame, column: str) -> None:
    """A key column (iteration, bin): whole numbers >= 0, every row."""
    values = table[column].to_numpy(dtype=float)
    bad = ~np.isfinite(values) | (values < 0) | (values != np.round(values))
    if bad.any():
        raise AnalysisError(f"{path}: column {column} holds {_show(table[column][bad].iloc[0])}, not a whole number >= 0")


def _check_range(path: Path, values: pd.Series, column: str, low: float, high: float) -> None:
    x = values.to_numpy(dtype=float)
    bad = np.isinf(x) | (x < low) | (x > high)  # NaN: nothing measured there (no visit, no episode)
    if bad.any():
        span = f"[{low:g}, {high:g}]" if math.isfinite(high) else f">= {low:g}"
        raise AnalysisError(f"{path}: column {column} holds {_show(values[bad].iloc[0])}, outside {span}")


def _check_bins(path: Path, name: str, table: pd.DataFrame, run_dir: str | Path) -> None:
    """Every evaluation (iteration) holds each bin of the run once: bins 0..n-1, n the run's number of
    bins (metrics.json, else the first evaluation's), and no bin ends after the motion does."""
    _check_key(path, table, BIN)
    bins = table[BIN].to_numpy(dtype=np.int64)
    iterations = table[ITERATION].to_numpy(dtype=np.int64)
    n = recorded_bins(run_dir) or int(np.sum(iterations == iterations[0]))
    if bins.max() >= n:
        raise AnalysisError(f"{path}: column {BIN} holds {int(bins.max())}, but the run has {n} bins (0..{n - 1})")
    per = pd.DataFrame({ITERATION: iterations, BIN: bins}).groupby(ITERATION)[BIN]
    if per.nunique().ne(n).any() or per.size().ne(n).any():
        it = int(per.nunique()[per.nunique().ne(n) | per.size().ne(n)].index[0])
        raise AnalysisError(f"{path}: column {BIN}: iteration {it} does not hold each of the run's {n} bins once")
    duration = motion_duration_s(run_dir)
    if duration is not None and "bin_end_s" in table.columns:
        _check_range(path, table["bin_end_s"], "bin_end_s", 0.0, duration + TIME_TOLERANCE_S)
        if "bin_start_s" in table.columns:
            _check_range(path, table["bin_start_s"], "bin_start_s", 0.0, duration + TIME_TOLERANCE_S)
    if name == "sampler":
        totals = table.groupby(ITERATION)["probability"].sum(min_count=1)
        off = totals.notna() & (totals - 1.0).abs().gt(PROBABILITY_TOLERANCE)
        if off.any():
            raise AnalysisError(f"{path}: column probability sums to {totals[off].iloc[0]:.4g} at iteration "
                                f"{int(totals[off].index[0])}, not 1 (a sampling distribution)")
