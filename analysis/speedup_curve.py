"""Speedup as a curve: the ratio of times to a success threshold over many thresholds, and the
iso-failure ratio over training.

One speedup number hides its threshold: an arm can be as fast as the baseline to 70% success and
1.5 times faster to 90%. So:

- ``speedup_curve``: for every arm against the baseline and every success threshold of
  ``THRESHOLDS`` (50% to 99%), metrics.speedup of the times to that threshold (Kaplan-Meier medians
  over seeds, the same persistence as the report's time to threshold), in iterations and env steps,
  with its bootstrap interval over seeds (when every arm has enough seeds), its censoring status
  (``estimate``, ``lower_bound``, ``upper_bound``, ``not_estimable``) and its permutation p-value
  (uncorrected, one test per threshold). Wall time is left out: it depends on the machine and on
  what shared it (analysis.machines).
- ``iso_failure``: for each evaluation t of the baseline, the baseline's failure level L there
  (point estimate over seeds), the time t' at which the arm's curve (point estimate over seeds) first
  got to L or below, linearly interpolated between the two evaluations around the crossing, and the
  ratio t / t' (> 1: the arm got there sooner). ``upper_bound`` when the arm never got to L (ratio
  at most t over its last evaluation), ``lower_bound`` when it was already there at its first
  evaluation (ratio at least t over that evaluation), ``not_estimable`` when that first evaluation
  is at 0. Computed on the point curves, so it has no interval.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from analysis.metrics import event_times, speedup, time_to_threshold
from analysis.stats import point, smallest_pvalue
from analysis.tables import ReportOptions, use_bootstrap
from bmimic.runs.schema import ENV_STEPS, FAILURE_RATE, ITERATION

THRESHOLDS = tuple(p / 100 for p in (*range(50, 80, 5), *range(80, 100)))
"""Success thresholds of the speedup curve: 0.50 to 0.80 in steps of 0.05, then to 0.99 in steps of 0.01."""

CURVE_MEASURES = ("iteration", ENV_STEPS)
"""Measures of the speedup curve (wall time is not comparable across machines and loads)."""

CURVE_COLUMNS = ["arm", "baseline", "measure", "threshold", "ratio", "ci_low", "ci_high", "ci_method", "status",
                 "p_value", "smallest_p", "arm_reached", "baseline_reached", "arm_seeds", "baseline_seeds"]
"""Columns of speedup_curve.csv: one row per arm, measure and threshold; ``*_reached`` are the seeds
that got to the threshold."""

ISO_COLUMNS = ["arm", "baseline", "measure", "baseline_time", "failure_level", "arm_time", "ratio", "status"]
"""Columns of iso_failure.csv: one row per arm, measure and baseline evaluation."""


def speedup_curve(overall: pd.DataFrame, baseline: str, runs: pd.DataFrame, opts: ReportOptions,
                  thresholds=THRESHOLDS, measures=CURVE_MEASURES) -> pd.DataFrame:
    """CURVE_COLUMNS for every arm against ``baseline`` (module docstring); ``overall`` is
    metrics.overall_failure of every run."""
    boot = use_bootstrap(runs)
    kw: dict[str, Any] = dict(bootstrap=boot, n_resamples=opts.n_resamples, confidence=opts.confidence, seed=opts.bootstrap_seed,
              n_permutations=opts.n_permutations)
    rows = []
    for threshold in thresholds:
        times = time_to_threshold(overall, threshold, persist=opts.mastery_persist, by=["run_dir", "arm", "seed"])
        base = times[times["arm"] == baseline].sort_values("seed")
        for arm in sorted(set(times["arm"]) - {baseline}):
            t = times[times["arm"] == arm].sort_values("seed")
            for m in measures:
                s = speedup(*event_times(base, m), *event_times(t, m), **kw)
                rows.append((arm, baseline, m, threshold, s.ratio, s.ci_low, s.ci_high, s.ci_method, s.status,
                             s.p_value, smallest_pvalue(len(t), len(base), opts.n_permutations),
                             int(t["reached"].sum()), int(base["reached"].sum()), len(t), len(base)))
    return pd.DataFrame(rows, columns=CURVE_COLUMNS)


def _point_curve(overall: pd.DataFrame, measure: str) -> pd.DataFrame:
    """Per arm and evaluation iteration: the point estimate over seeds of the failure and the measure."""
    g = overall.groupby(["arm", ITERATION], sort=True)
    out = g.agg(time=(measure, "mean")).reset_index()
    out["failure"] = g[FAILURE_RATE].apply(lambda v: float(point(v.to_numpy(dtype=float)))).to_numpy()
    return out


def first_crossing(time: np.ndarray, value: np.ndarray, level: float) -> tuple[float, str]:
    """When ``value`` (sorted by ``time``) first gets to ``level`` or below: ``(time, status)`` with
    linear interpolation between the evaluation before and the one at or below (``estimate``); the
    first time and ``lower_bound`` (on the ratio) when the first value is already there; NaN and
    ``upper_bound`` when it never gets there; ``not_estimable`` when already there at time 0."""
    below = np.flatnonzero(value <= level)
    if not len(below):
        return math.nan, "upper_bound"
    i = int(below[0])
    if i == 0:
        return (float(time[0]), "lower_bound") if time[0] > 0 else (math.nan, "not_estimable")
    t0, t1, v0, v1 = float(time[i - 1]), float(time[i]), float(value[i - 1]), float(value[i])
    return t0 + (v0 - level) / (v0 - v1) * (t1 - t0), "estimate"


def iso_failure(overall: pd.DataFrame, baseline: str, measures=CURVE_MEASURES) -> pd.DataFrame:
    """ISO_COLUMNS: for every arm and every baseline evaluation after time 0 (module docstring)."""
    rows = []
    for m in measures:
        curve = _point_curve(overall, m)
        base = curve[curve["arm"] == baseline].sort_values("time")
        for arm in sorted(set(curve["arm"]) - {baseline}):
            a = curve[curve["arm"] == arm].sort_values("time")
            ta, fa = a["time"].to_numpy(dtype=float), a["failure"].to_numpy(dtype=float)
            keep = ~np.isnan(fa)
            ta, fa = ta[keep], fa[keep]
            if not len(ta):
                continue
            for tb, level in zip(base["time"], base["failure"], strict=True):
                if tb <= 0 or math.isnan(level):
                    continue
                t_arm, status = first_crossing(ta, fa, level)
                if status == "upper_bound":
                    ratio = tb / ta[-1] if ta[-1] > 0 else math.nan
                elif status == "not_estimable":
                    ratio = math.nan
                else:
                    ratio = tb / t_arm if t_arm > 0 else math.inf
                rows.append((arm, baseline, m, float(tb), float(level), t_arm, ratio, status))
    return pd.DataFrame(rows, columns=ISO_COLUMNS)
