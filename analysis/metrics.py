"""Task metrics over tidy tables: overall failure, bin mastery, time to a success threshold, speedup.

Definitions (used by the report and its text):

- *overall failure* of an evaluation = the unweighted mean of ``failure_rate`` over bins (every part
  of the motion counts the same, however many episodes a bin got); *overall success* = 1 - that.
- a bin's *mastery iteration* = the first evaluation iteration at which its failure rate is below
  the threshold. It need not stay below afterwards (a bin that is mastered and later forgotten keeps
  its first mastery iteration). Never below -> NaN ("never").
- *time to threshold* = the first evaluation at which overall success >= the threshold, read as
  iteration, env steps and wall time of that evaluation. Never -> NaN.
- *speedup* = baseline / arm, so > 1 means the arm is faster.

All functions are pure: they take frames and return new frames or numbers.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from analysis.stats import DEFAULT_RESAMPLES, bootstrap_ci, iqm

MEASURES = ("iteration", "env_steps", "wall_time_s")
"""How time to threshold is measured: training iterations, environment steps, seconds."""


def overall_failure(eval_df: pd.DataFrame, by=("run_dir", "arm", "seed")) -> pd.DataFrame:
    """Overall evaluated failure and success per run and evaluation iteration.

    Returns ``by + [iteration, env_steps, wall_time_s, failure_rate, success_rate, num_bins]`` where
    ``failure_rate`` is the mean over the bins evaluated at that iteration.
    """
    by = list(by)
    out = (
        eval_df.groupby([*by, "iteration"], sort=True)
        .agg(
            env_steps=("env_steps", "max"),
            wall_time_s=("wall_time_s", "max"),
            failure_rate=("failure_rate", "mean"),
            num_bins=("bin", "nunique"),
        )
        .reset_index()
    )
    out["success_rate"] = 1.0 - out["failure_rate"]
    return out[[*by, "iteration", "env_steps", "wall_time_s", "failure_rate", "success_rate", "num_bins"]]


def mastery_iterations(bin_failure: pd.DataFrame, threshold: float = 0.1, by=()) -> pd.DataFrame:
    """Each bin's mastery iteration: the first evaluation with ``failure_rate < threshold``.

    ``bin_failure`` has ``iteration, bin, failure_rate`` (plus the ``by`` columns), one row per
    (group, iteration, bin); pass an arm's seed-mean curve or one run's curve. Returns
    ``by + [bin, mastery_iteration, mastered, last_iteration]``: ``mastery_iteration`` is NaN where
    the bin never dropped below the threshold, ``last_iteration`` the last evaluation seen (the
    censoring point for bins never mastered).
    """
    by = list(by)
    rows = []
    for key, group in bin_failure.groupby([*by, "bin"], sort=True):
        group = group.sort_values("iteration")
        below = group.loc[group["failure_rate"] < threshold, "iteration"]
        first = float(below.iloc[0]) if len(below) else np.nan
        rows.append((*key, first, bool(len(below)), float(group["iteration"].max())))
    return pd.DataFrame(rows, columns=[*by, "bin", "mastery_iteration", "mastered", "last_iteration"])


def time_to_threshold(
    curve: pd.DataFrame, threshold: float = 0.9, value: str = "success_rate", by=("run_dir", "arm", "seed")
) -> pd.DataFrame:
    """When each group's ``value`` first reaches ``threshold`` (``>=``), in each of MEASURES.

    ``curve`` has ``iteration, env_steps, wall_time_s`` and ``value`` per evaluation (e.g. the output
    of overall_failure). Returns ``by + [reached, iteration, env_steps, wall_time_s,
    last_iteration, last_env_steps, last_wall_time_s]``: the measures at the first evaluation that
    reached it (NaN if none did) and at the last evaluation (the censoring point).
    """
    by = list(by)
    rows = []
    for key, group in curve.groupby(by, sort=True, dropna=False):
        key = key if isinstance(key, tuple) else (key,)
        group = group.sort_values("iteration")
        hit = group[group[value] >= threshold]
        first = [float(hit[m].iloc[0]) if len(hit) else np.nan for m in MEASURES]
        last = [float(group[m].iloc[-1]) for m in MEASURES]
        rows.append((*key, bool(len(hit)), *first, *last))
    return pd.DataFrame(rows, columns=[*by, "reached", *MEASURES, *(f"last_{m}" for m in MEASURES)])


def censored(times: pd.DataFrame, measure: str) -> np.ndarray:
    """Time to threshold in ``measure`` with runs that never reached it counted at their last
    evaluation: a lower bound on their true time, so an arm that rarely reaches the threshold is
    never made to look slower than the data shows."""
    return np.where(times["reached"], times[measure], times[f"last_{measure}"]).astype(float)


def speedup(
    baseline, arm, n_resamples: int = DEFAULT_RESAMPLES, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float, float]:
    """Speedup ``IQM(baseline) / IQM(arm)`` of per-seed times, with a stratified bootstrap interval.

    ``baseline`` and ``arm`` are per-seed times (e.g. iterations to threshold); seeds are resampled
    within each arm. > 1 means the arm needs less time. Returns ``(ratio, low, high)``; an arm whose
    IQM is 0 gives an infinite ratio.
    """
    def ratio(b, a):
        with np.errstate(divide="ignore", invalid="ignore"):
            return iqm(b, axis=0) / iqm(a, axis=0)

    return bootstrap_ci(
        np.asarray(baseline, float), np.asarray(arm, float),
        statistic=ratio, n_resamples=n_resamples, confidence=confidence, seed=seed,
    )


def mastery_speedup(mastery: pd.DataFrame, baseline: str) -> pd.DataFrame:
    """Per-bin mastery speedup of every arm against ``baseline``: baseline / arm mastery iteration.

    ``mastery`` is mastery_iterations(..., by=["arm"]). Censoring: a bin never mastered by either
    arm is excluded (ratio NaN, ``censored="both never"``); a bin mastered by one arm only counts
    the other as mastered at its last evaluation (``censored="baseline never"``: the ratio is a
    lower bound; ``"arm never"``: an upper bound). Equal zero iterations give 1, an arm at 0 against
    a positive baseline gives inf. Returns ``arm, bin, baseline_iteration, arm_iteration, ratio,
    censored`` for every arm but the baseline.
    """
    if baseline not in set(mastery["arm"]):
        raise ValueError(f"baseline arm {baseline!r} not among arms {sorted(set(mastery['arm']))}")
    base = mastery[mastery["arm"] == baseline].set_index("bin")
    rows = []
    for arm, group in mastery[mastery["arm"] != baseline].groupby("arm", sort=True):
        for r in group.itertuples(index=False):
            if r.bin not in base.index:
                continue
            b = base.loc[r.bin]
            b_it = b["mastery_iteration"] if b["mastered"] else b["last_iteration"]
            a_it = r.mastery_iteration if r.mastered else r.last_iteration
            note = {(True, True): "", (False, True): "baseline never", (True, False): "arm never"}.get(
                (bool(b["mastered"]), bool(r.mastered)), "both never"
            )
            if note == "both never":
                ratio = np.nan
            elif a_it == 0:
                ratio = 1.0 if b_it == 0 else np.inf
            else:
                ratio = b_it / a_it
            rows.append((arm, r.bin, float(b_it), float(a_it), float(ratio), note))
    return pd.DataFrame(rows, columns=["arm", "bin", "baseline_iteration", "arm_iteration", "ratio", "censored"])


def final_rows(df: pd.DataFrame, by=("run_dir",)) -> pd.DataFrame:
    """The rows of each group's last iteration (e.g. each run's final evaluation)."""
    by = list(by)
    last = df.groupby(by)["iteration"].transform("max")
    return df[df["iteration"] == last].reset_index(drop=True)


def bin_table(eval_df: pd.DataFrame, segments: pd.DataFrame | None = None) -> pd.DataFrame:
    """One row per bin: ``bin, bin_start_s, bin_end_s, segment, label``.

    A bin's segment is the motion segment (from motion_segments.json) containing the bin's midpoint,
    else the eval table's ``segment`` column, else empty; ``label`` reads ``"<bin> <segment>"``.
    """
    bins = eval_df.groupby("bin", sort=True).agg(bin_start_s=("bin_start_s", "min"), bin_end_s=("bin_end_s", "max"))
    bins = bins.reset_index()
    if "segment" in eval_df.columns:
        bins["segment"] = eval_df.groupby("bin", sort=True)["segment"].first().astype(str).to_numpy()
    else:
        bins["segment"] = ""
    if segments is not None and len(segments):
        mid = (bins["bin_start_s"] + bins["bin_end_s"]) / 2.0
        for seg in segments.itertuples(index=False):
            inside = (mid >= seg.start_s) & (mid < seg.end_s)
            bins.loc[inside, "segment"] = str(seg.name)
    bins["label"] = [f"{b} {s}".strip() for b, s in zip(bins["bin"], bins["segment"], strict=True)]
    return bins
