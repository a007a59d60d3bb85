"""Task metrics over tidy tables: overall failure, bin mastery per seed, time to a success threshold,
censored per-arm medians and speedups.

Definitions (used by the report and its text):

- *overall failure* of an evaluation = failed evaluation episodes / started evaluation episodes
  (starts are stratified, the same number in every bin, so every part of the motion counts the
  same); *overall success* = 1 - that; the same number as the run's ``eval_failure_rate``. It is
  not the mean of the per-bin rates: an episode spans several bins.
- the failure of a clip or a segment (``start_failure``) is counted in the same unit: failed
  episodes / episodes started in it, each episode charged to the clip (segment) it started in, so
  the overall failure is the start-weighted mean of the clips' failures.
- a bin's ``failure_rate`` is failures per *visit*, charged to the bin where the failure happened
  (bmimic.training.evaluator): a different unit, used for bin mastery and the per-bin figures,
  always labelled "per visit".
- an evaluation *counts a bin as mastered* when its failure rate is below the threshold and, if the
  bin is ``horizon_truncated`` (its episodes run out of clip before the horizon), at least one
  episode tracked all of its frames after entering it from an earlier bin (``tracked_through``).
- a bin's *mastery iteration* in one run (seed) = the first evaluation from which the bin counts as
  mastered at every evaluation for the rest of the run, or for at least ``persist`` consecutive
  evaluations. Never -> censored at the run's last evaluation.
- *time to threshold* = the first evaluation from which overall success >= the threshold, with the
  same persistence, in iterations, env steps and wall time. Never -> censored.
- per arm, times are summarised by their Kaplan-Meier median over seeds (stats.km_median): defined
  only when more than half of the seeds got there, else "not reached".
- *speedup* = baseline median / arm median, so > 1 means the arm is faster; its ``status`` is
  ``estimate`` (both medians defined), ``lower_bound`` (the baseline's median was not reached but the
  arm's was: the ratio is at least the baseline's last follow-up over the arm's median),
  ``upper_bound`` (the reverse) or ``not_estimable`` (neither reached).

All functions are pure: they take frames and return new frames or numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis.stats import (
    DEFAULT_RESAMPLES,
    bootstrap_interval,
    censored_pvalue,
    km_median,
    restricted_km_median,
)
from bmimic.runs.schema import (  # training's rule too
    BIN,
    ENV_STEPS,
    FAILURE_RATE,
    HORIZON_TRUNCATED,
    ITERATION,
    LABELS,
    REPORTED_ERRORS,
    SMOOTHNESS_COLUMNS,
    WALL_TIME_S,
    counts_as_mastered,
)

MEASURES = ("iteration", ENV_STEPS, WALL_TIME_S)
"""How time is measured: training iterations, environment steps, seconds of training."""

SPEEDUP_STATUSES = ("estimate", "lower_bound", "upper_bound", "not_estimable")
"""Values of the speedup ``status`` column."""


def overall_failure(eval_df: pd.DataFrame, by=("run_dir", "arm", "seed")) -> pd.DataFrame:
    """Overall evaluated failure and success per run and evaluation iteration.

    Returns ``by + [iteration, env_steps, wall_time_s, failure_rate, success_rate, num_bins]`` where
    ``failure_rate`` is the fraction of evaluation episodes that failed: every failed episode is charged
    to exactly one bin, so it is the sum of ``failures`` over the sum of ``start_episodes`` (``episodes``
    in tables written before per-visit accounting). Starts are stratified, the same number per bin, so
    every part of the motion counts the same. This is the run's own ``eval_failure_rate``
    (bmimic.training.evaluator.summarize), so report, metrics.json and console agree.
    """
    by = list(by)
    starts = "start_episodes" if "start_episodes" in eval_df.columns else "episodes"
    out = (
        eval_df.groupby([*by, ITERATION], sort=True)
        .agg(
            env_steps=(ENV_STEPS, "max"),
            wall_time_s=(WALL_TIME_S, "max"),
            failures=("failures", "sum"),
            starts=(starts, "sum"),
            num_bins=("bin", "nunique"),
        )
        .reset_index()
    )
    out[FAILURE_RATE] = out["failures"] / out["starts"].where(out["starts"] > 0)
    out["success_rate"] = 1.0 - out[FAILURE_RATE]
    return out[[*by, ITERATION, ENV_STEPS, WALL_TIME_S, FAILURE_RATE, "success_rate", "num_bins"]]


def start_failure(eval_df: pd.DataFrame, groups: pd.Series, by=("run_dir", "arm", "seed")) -> pd.DataFrame:
    """Failure per started episode of each group of bins (a clip, a segment), every episode charged to
    the group it started in: ``by + [iteration, group, failures, starts, failure_rate]``.

    ``groups`` maps each bin (index) to its group. Uses ``start_failures / start_episodes``; tables
    written before per-visit accounting charged failures to the start bin already (``failures /
    episodes``). Summed over the groups it is :func:`overall_failure`'s numerator and denominator.
    """
    by = list(by)
    if "start_failures" in eval_df.columns and "start_episodes" in eval_df.columns:
        fails, starts = "start_failures", "start_episodes"
    else:
        fails, starts = "failures", "episodes"
    df = eval_df[[*by, ITERATION, BIN, fails, starts]].assign(group=eval_df[BIN].map(groups))
    out = (df.groupby([*by, ITERATION, "group"], sort=False)
           .agg(failures=(fails, "sum"), starts=(starts, "sum")).reset_index())
    out[FAILURE_RATE] = out["failures"] / out["starts"].where(out["starts"] > 0)
    return out


def first_sustained(ok, persist: int) -> int:
    """Index of the first entry from which ``ok`` holds for ``persist`` consecutive entries, or for
    every remaining entry when fewer are left; -1 if none. ``first_sustained([0, 1, 0, 1, 1], 2) == 3``,
    ``first_sustained([0, 0, 1], 2) == 2`` (true for the rest of the run)."""
    ok = np.asarray(ok, dtype=bool)
    n = len(ok)
    if persist < 1:
        raise ValueError(f"persist must be >= 1, got {persist}")
    # run[i] = length of the run of trues starting at i
    run = np.zeros(n + 1, dtype=int)
    for i in range(n - 1, -1, -1):
        run[i] = run[i + 1] + 1 if ok[i] else 0
    hits = np.flatnonzero((run[:n] >= persist) | ((run[:n] > 0) & (run[:n] == n - np.arange(n))))
    return int(hits[0]) if len(hits) else -1


def mastery_per_seed(eval_df: pd.DataFrame, threshold: float = 0.1, persist: int = 2) -> pd.DataFrame:
    """Each run's mastery iteration of each bin (module docstring).

    ``eval_df`` has ``run_dir, arm, seed, iteration, env_steps, wall_time_s, bin, failure_rate`` (and
    optionally ``horizon_truncated, tracked_through``). Returns ``run_dir, arm, seed, bin, mastered,
    iteration, env_steps, wall_time_s, last_iteration, last_env_steps, last_wall_time_s,
    horizon_truncated``: the measures at the mastery evaluation (NaN when never) and at the run's
    last evaluation (the censoring point); ``horizon_truncated`` is the bin's flag at the last one.
    """
    df = eval_df.assign(_ok=counts_as_mastered(eval_df, threshold).to_numpy())
    if HORIZON_TRUNCATED not in df:
        df[HORIZON_TRUNCATED] = False
    rows = []
    for (run_dir, arm, seed, b), g in df.sort_values(ITERATION).groupby(["run_dir", "arm", "seed", BIN],
                                                                        sort=True, dropna=False):
        i = first_sustained(g["_ok"].to_numpy(), persist)
        hit = [float(g[m].iloc[i]) if i >= 0 else math.nan for m in MEASURES]
        last = [float(g[m].iloc[-1]) for m in MEASURES]
        rows.append((run_dir, arm, seed, b, i >= 0, *hit, *last, bool(g[HORIZON_TRUNCATED].iloc[-1])))
    return pd.DataFrame(rows, columns=["run_dir", "arm", "seed", BIN, "mastered", *MEASURES,
                                       *(f"last_{m}" for m in MEASURES), HORIZON_TRUNCATED])


def time_to_threshold(
    curve: pd.DataFrame, threshold: float = 0.9, value: str = "success_rate", persist: int = 2,
    by=("run_dir", "arm", "seed"),
) -> pd.DataFrame:
    """When each group's ``value`` first reaches ``threshold`` (``>=``) and stays there (``persist``).

    ``curve`` has ``iteration, env_steps, wall_time_s`` and ``value`` per evaluation (e.g. the output
    of overall_failure). Returns ``by + [reached, iteration, env_steps, wall_time_s, last_iteration,
    last_env_steps, last_wall_time_s]``: the measures at that evaluation (NaN if none) and at the
    last evaluation (the censoring point).
    """
    by = list(by)
    rows = []
    for key, group in curve.groupby(by, sort=True, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        group = group.sort_values(ITERATION)
        i = first_sustained((group[value] >= threshold).to_numpy(), persist)
        first = [float(group[m].iloc[i]) if i >= 0 else math.nan for m in MEASURES]
        last = [float(group[m].iloc[-1]) for m in MEASURES]
        rows.append((*key, i >= 0, *first, *last))
    return pd.DataFrame(rows, columns=[*by, "reached", *MEASURES, *(f"last_{m}" for m in MEASURES)])


def event_times(times: pd.DataFrame, measure: str) -> tuple[np.ndarray, np.ndarray]:
    """``(time, event)`` of time-to-event rows (``reached``/``mastered`` plus ``<measure>`` and
    ``last_<measure>``): the event time where it happened, else the censoring time."""
    event = (times["reached"] if "reached" in times else times["mastered"]).to_numpy(dtype=bool)
    time = np.where(event, times[measure].to_numpy(dtype=float), times[f"last_{measure}"].to_numpy(dtype=float))
    return time, event


@dataclass(frozen=True)
class ArmTime:
    """The per-arm summary of censored times (e.g. iterations to mastering one bin) over seeds."""

    n: int
    """Seeds."""
    n_reached: int
    """Seeds that had the event."""
    median: float
    """Kaplan-Meier median; NaN when not reached."""
    follow_up: float
    """Largest time any seed was followed (its last evaluation or event): a lower bound on a median
    that was not reached."""


def arm_time(time, event) -> ArmTime:
    """ArmTime of one arm's ``(time, event)`` per seed."""
    time = np.asarray(time, dtype=float)
    event = np.asarray(event, dtype=bool)
    if not len(time):
        return ArmTime(0, 0, math.nan, math.nan)
    return ArmTime(len(time), int(event.sum()), float(km_median(time, event)), float(time.max()))


@dataclass(frozen=True)
class Speedup:
    """Speedup of an arm against a baseline (baseline median / arm median; > 1: the arm is faster)."""

    ratio: float
    """The estimate (``estimate``) or the bound (``lower_bound``, ``upper_bound``); NaN otherwise."""
    ci_low: float
    """Bootstrap interval (only for ``estimate`` with enough seeds), else NaN."""
    ci_high: float
    """See ci_low."""
    ci_method: str
    """``bootstrap_bca``, ``bootstrap_percentile`` or '' (no interval)."""
    status: str
    """One of SPEEDUP_STATUSES."""
    p_value: float
    """Two-sided permutation test of the two arms' censored times (stats.censored_pvalue)."""


def _ratio(base: float, arm: float) -> float:
    if arm == 0:
        return 1.0 if base == 0 else math.inf
    return base / arm


def speedup(
    base_time, base_event, arm_time_, arm_event, bootstrap: bool, n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95, seed: int = 0, n_permutations: int = 9999,
) -> Speedup:
    """Speedup of censored per-seed times ``arm`` against ``baseline`` (module docstring for ``status``).

    With ``bootstrap`` (every arm has enough seeds) and both medians defined, the interval is a
    stratified bootstrap over seeds (each arm resampled on its own) of the ratio of medians; a
    resample in which a median is not reached uses that arm's last follow-up time there
    (stats.restricted_km_median).
    """
    bt, be = np.asarray(base_time, float), np.asarray(base_event, bool)
    at, ae = np.asarray(arm_time_, float), np.asarray(arm_event, bool)
    b, a = arm_time(bt, be), arm_time(at, ae)
    p = censored_pvalue(at, ae, bt, be, n_resamples=n_permutations, seed=seed) if a.n and b.n else math.nan
    b_ok, a_ok = not math.isnan(b.median), not math.isnan(a.median)
    if b_ok and a_ok:
        ratio = _ratio(b.median, a.median)
        low = high = math.nan
        method = ""
        if bootstrap and a.n >= 2 and b.n >= 2 and math.isfinite(ratio):
            def stat(ib, ia, axis=-1):
                ib, ia = ib.astype(int), ia.astype(int)
                mb = restricted_km_median(bt[ib], be[ib], axis=-1)
                ma = restricted_km_median(at[ia], ae[ia], axis=-1)
                with np.errstate(divide="ignore", invalid="ignore"):
                    return np.where(ma == 0, np.where(mb == 0, 1.0, np.inf), mb / np.where(ma == 0, 1.0, ma))

            low, high, method = bootstrap_interval((np.arange(b.n, dtype=float), np.arange(a.n, dtype=float)),
                                                   stat, n_resamples, confidence, seed)
        return Speedup(ratio, low, high, method, "estimate", p)
    if a_ok:  # the baseline never got there within its follow-up: the arm is at least this much faster
        return Speedup(_ratio(b.follow_up, a.median), math.nan, math.nan, "", "lower_bound", p)
    if b_ok:
        return Speedup(_ratio(b.median, a.follow_up), math.nan, math.nan, "", "upper_bound", p)
    return Speedup(math.nan, math.nan, math.nan, "", "not_estimable", p)


def final_rows(df: pd.DataFrame, by=("run_dir",)) -> pd.DataFrame:
    """The rows of each group's last iteration (e.g. each run's final evaluation)."""
    by = list(by)
    last = df.groupby(by)[ITERATION].transform("max")
    return df[df[ITERATION] == last].reset_index(drop=True)


ERROR_METRICS = {c: LABELS[c] for c in REPORTED_ERRORS}
"""eval.parquet tracking-error column -> label (lower is better), in the order the report shows them."""


SMOOTHNESS_METRICS = {c: LABELS[c] for c in SMOOTHNESS_COLUMNS}
"""eval.parquet smoothness column -> label (lower is smoother): the policy's own actions and joint motion,
not a tracking error (bmimic.training.evaluator.SMOOTHNESS_COLUMNS). Tables written before they were
recorded lack them: the report says "not recorded"."""

BROKEN = "broken"
"""eval.parquet count of episodes that ended because their world broke (non-finite or out of bounds),
charged to the bin where it happened; each is also a failure. Absent from older tables."""


def tracking_errors(eval_df: pd.DataFrame, by=("run_dir", "arm", "seed")) -> pd.DataFrame:
    """Step-weighted means per run and evaluation of every tracking error (ERROR_METRICS) and
    smoothness measure (SMOOTHNESS_METRICS) the table has: ``by + [iteration, env_steps, <column>...]``.

    Each bin's value is a mean over the steps the evaluation episodes spent at its frames
    (``eval_steps``), so the run's is the ``eval_steps``-weighted mean over bins, the run's own
    ``eval_<column>`` (bmimic.training.evaluator.summarize). Steps after an episode failed are not
    measured: an arm that fails more is measured over fewer steps. A run whose table lacks a column
    (stacked with runs that have it) gets NaN there, never 0. Empty when the table has none.
    """
    by = list(by)
    cols = [c for c in (*ERROR_METRICS, *SMOOTHNESS_METRICS) if c in eval_df.columns]
    if not cols or "eval_steps" not in eval_df.columns or not len(eval_df):
        return pd.DataFrame(columns=[*by, ITERATION, ENV_STEPS])
    w = eval_df["eval_steps"].astype(float).clip(lower=0.0)
    values = eval_df[cols].astype(float)
    weights = pd.DataFrame({c: w.where(values[c].notna() & (w > 0), 0.0) for c in cols})
    parts = values.fillna(0.0).mul(weights)  # a bin never reached has NaN values and no weight
    frame = pd.concat([eval_df[[*by, ITERATION, ENV_STEPS]], parts, weights.add_prefix("_w_")], axis=1)
    g = frame.groupby([*by, ITERATION], sort=True).agg(
        {ENV_STEPS: "max", **{c: "sum" for c in cols}, **{f"_w_{c}": "sum" for c in cols}}).reset_index()
    for c in cols:
        g[c] = g[c] / g[f"_w_{c}"].where(g[f"_w_{c}"] > 0)
    return g.drop(columns=[f"_w_{c}" for c in cols])


def broken_episodes(eval_df: pd.DataFrame, by=("run_dir", "arm", "seed")) -> pd.DataFrame:
    """Episodes whose world broke, per run: ``by + [broken, evaluations]`` summed over every evaluation
    (``broken`` column); runs whose table lacks the column are left out (not recorded)."""
    by = list(by)
    if BROKEN not in eval_df.columns or not len(eval_df):
        return pd.DataFrame(columns=[*by, BROKEN, "evaluations"])
    df = eval_df.dropna(subset=[BROKEN])
    out = df.groupby(by, sort=True).agg(broken=(BROKEN, "sum"), evaluations=("iteration", "nunique")).reset_index()
    return out


def at_budget(df: pd.DataFrame, measure: str, budget: float, by=("run_dir",)) -> pd.DataFrame:
    """Each group's rows of its last evaluation with ``measure <= budget`` (groups with none are left out)."""
    by = list(by)
    df = df[df[measure] <= budget]
    if not len(df):
        return df.reset_index(drop=True)
    last = df.groupby(by)[measure].transform("max")
    return df[df[measure] == last].reset_index(drop=True)


def bin_table(eval_df: pd.DataFrame, segments: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per bin: ``bin, bin_start_s, bin_end_s, segment, label, horizon_truncated``.

    A bin's segment is the motion segment (from motion_segments.json) containing the bin's midpoint,
    else the eval table's ``segment`` column, else empty; ``label`` reads ``"<bin> <segment>"``.
    ``horizon_truncated`` is true when any evaluation flagged the bin (False for older tables).
    """
    g = eval_df.groupby(BIN, sort=True)
    bins = g.agg(bin_start_s=("bin_start_s", "min"), bin_end_s=("bin_end_s", "max")).reset_index()
    if "segment" in eval_df.columns:
        bins["segment"] = g["segment"].first().fillna("").astype(str).to_numpy()
    else:
        bins["segment"] = ""
    if segments is not None and len(segments):
        mid = (bins["bin_start_s"] + bins["bin_end_s"]) / 2.0
        for seg in segments.itertuples(index=False):
            inside = (mid >= seg.start_s) & (mid < seg.end_s)
            bins.loc[inside, "segment"] = str(seg.name)
    bins["label"] = [f"{b} {s}".strip() for b, s in zip(bins[BIN], bins["segment"], strict=True)]
    if HORIZON_TRUNCATED in eval_df.columns:
        bins[HORIZON_TRUNCATED] = g[HORIZON_TRUNCATED].any().astype(bool).to_numpy()
    else:
        bins[HORIZON_TRUNCATED] = False
    return bins
