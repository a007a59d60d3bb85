"""One knob at a time around a reference arm: which of a sampler's knobs matter, and how much.

A *knob study* (e.g. sweeps/sensitivity_dance1.yaml) runs a reference arm (the design:
``sampler=adaptive`` with its own defaults) and arms that change exactly one numeric sampler key of it
(``sampler=adaptive,sampler.gamma=0.5``), usually beside uniform sampling. ``knob_arms`` finds that
structure in any set of runs; the report adds its Knobs section only where it exists.

Per level (``knob_levels``), against the reference and against uniform:

- final failure: per-seed mean, the seeds' range, the difference of means from the reference, its
  two-sided exact permutation p (uncorrected; 3 v 5 seeds: smallest attainable p 2/56 = 0.036) and the
  1 - alpha confidence interval of that difference from the same test inverted (analysis.shift_interval;
  unbounded where the seeds cannot bound it, e.g. a single seed);
- iterations to ``THRESHOLDS`` overall success (sustained as the report's time to threshold;
  Kaplan-Meier median over seeds, censored at the run's last evaluation);
- speedup = reference median / level median (> 1: the level reaches the threshold sooner), its status
  (metrics.speedup: estimate, or a bound under censoring), its 1 - alpha interval (the Gehan test
  inverted, shift_interval.ratio_interval), the range of the per-seed ratios
  (reference median / each seed's time; a seed that never got there gives a bound), and the Gehan
  permutation p of the censored times; the same against uniform, the speedup a user of the level
  gets over not adapting at all.

Per knob (``knob_trends``): whether final failure moves monotonically with the knob's value over all of the
knob's runs, the reference's included: Spearman's rank correlation of value and final failure (average ranks
for ties: the seeds of a level share its value) and its two-sided permutation p (final failures shuffled over
the runs, exchangeable when the knob changes nothing). It asks a different question from the per-level tests
(a dose-response over the whole range rather than one level against the reference), is post hoc in studies
that did not plan it, and stays outside the verdict's Holm family.

Per knob (``knob_summary``): the levels' speedups over the reference at the first threshold, lowest and
highest, with their seed ranges; the final-failure differences, lowest and highest, with their
intervals; and which levels
differ from the reference at p < alpha in either measure, uncorrected and after Holm's step-down
adjustment over the row's tests (two per level). The verdict is the adjusted one: "differs" where some
adjusted p < alpha, else "within noise" (the uncorrected levels are still listed, since with several
levels a few differ by chance). With 3 seeds against 5 the smallest p is 2/56 = 0.036, so once a row
holds two tests no adjusted p falls below 0.05: such a study estimates effect sizes, it does not decide.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from analysis.load import arm_items
from analysis.metrics import arm_time, event_times, speedup, time_to_threshold
from analysis.shift_interval import ratio_interval, shift_interval
from analysis.stats import holm, permutation_pvalue, smallest_pvalue
from analysis.tables import ReportOptions

THRESHOLDS = (0.9, 0.95)
"""Overall success levels at which each level's speedup is reported (the first one ranks the knobs)."""

KNOB_ARM_COLUMNS = ["arm", "knob", "value", "reference"]
"""Columns of knob_arms: the arm, the sampler key it changes, its value there, and the reference arm
(the arm of the same sampler that changes nothing). The reference itself has a row per knob too, with
its own value of the key."""

LEVEL_COLUMNS = [
    "knob", "value", "arm", "is_reference", "n_seeds", "final_failure", "final_failure_min", "final_failure_max",
    "failure_difference", "failure_difference_low", "failure_difference_high", "failure_p", "failure_smallest_p",
    *(f"{c}_{int(round(t * 100))}" for t in THRESHOLDS for c in (
        "iterations", "reached", "speedup", "speedup_status", "speedup_low", "speedup_high", "speedup_seed_min",
        "speedup_seed_max", "speedup_p", "vs_uniform", "vs_uniform_status")),
]
"""Columns of knob_levels.csv (one row per knob and level, the reference's value included):
``final_failure`` is the mean over seeds of the final overall failure, ``failure_difference`` the
level's mean minus the reference's, ``failure_difference_low``/``_high`` its 1 - alpha interval (the
permutation test inverted; +-inf: unbounded), ``iterations_<t>`` the Kaplan-Meier median iterations to success
>= t/100 (NaN: not reached by half the seeds), ``reached_<t>`` the seeds that reached it,
``speedup_<t>`` the reference's median / the level's (``speedup_status`` as metrics.speedup),
``speedup_low``/``_high`` its 1 - alpha interval (the Gehan test inverted under a scale model,
shift_interval.ratio_interval; 0 / inf: unbounded),
``speedup_seed_min``/``_max`` the range of reference median / each seed's time, ``speedup_p`` the Gehan
permutation p, ``vs_uniform_<t>`` the speedup over uniform (NaN without a uniform arm)."""

SUMMARY_COLUMNS = ["knob", "reference_value", "levels",
                   *(f"{end}_{c}" for end in ("slowest", "fastest")
                     for c in ("value", "speedup", "speedup_low", "speedup_high", "speedup_seed_min",
                               "speedup_seed_max")),
                   "lowest_failure_value", "lowest_failure_difference", "lowest_failure_low", "lowest_failure_high",
                   "highest_failure_value", "highest_failure_difference", "highest_failure_low",
                   "highest_failure_high",
                   "tests", "differing_levels_uncorrected", "differing_levels", "verdict",
                   "trend_runs", "trend_rho", "trend_p"]
"""Columns of knob_summary.csv, one row per knob (module docstring; speedups at THRESHOLDS[0]):
``differing_levels_uncorrected`` the levels with some p < alpha, ``differing_levels`` those with some
Holm-adjusted p < alpha over the row's ``tests``, which the ``verdict`` follows; ``trend_rho``/``trend_p``
knob_trends' rank correlation of value and final failure over the knob's ``trend_runs`` runs (NaN without it)."""

TREND_COLUMNS = ["knob", "trend_runs", "trend_rho", "trend_p"]
"""Columns of knob_trends (module docstring)."""


def _numeric(value) -> bool:
    return isinstance(value, int | float | np.number) and not isinstance(value, bool) and math.isfinite(value)


def knob_arms(runs: pd.DataFrame) -> pd.DataFrame:
    """KNOB_ARM_COLUMNS for the included arms of ``runs`` (load.load_runs, labelled) that change exactly
    one numeric ``sampler.*`` key of a reference arm of the same sampler; empty when there is none."""
    arms = runs[runs["included"]].drop_duplicates("arm").set_index("arm")
    if arms.empty:
        return pd.DataFrame(columns=KNOB_ARM_COLUMNS)
    items = {a: arm_items(arms.loc[a, "overrides"]) for a in arms.index}
    shared = set.intersection(*(set(i.items()) for i in items.values())) if len(items) > 1 else set()
    own = {a: {k: v for k, v in i.items() if (k, v) not in shared and k != "sampler"} for a, i in items.items()}
    references = {arms.loc[a, "sampler"]: a for a in sorted(arms.index) if not own[a]}
    rows = []
    for arm in sorted(arms.index):
        keys = list(own[arm])
        ref = references.get(arms.loc[arm, "sampler"])
        if ref is None or ref == arm or len(keys) != 1 or not keys[0].startswith("sampler."):
            continue
        value = arms.loc[arm].get(f"param.{keys[0]}")
        if _numeric(value):
            rows.append((arm, keys[0], float(value), ref))
    out = pd.DataFrame(rows, columns=KNOB_ARM_COLUMNS)
    for (knob, ref), _ in out.groupby(["knob", "reference"], sort=True):
        value = arms.loc[ref].get(f"param.{knob}")
        if _numeric(value):
            out.loc[len(out)] = (ref, knob, float(value), ref)
    return out.sort_values(["knob", "value"], kind="stable").reset_index(drop=True)


def _seed_ratios(ref_median: float, time: np.ndarray, event: np.ndarray) -> tuple[float, float]:
    """(min, max) of reference median / each seed's time; a censored seed counts at its last time, a
    bound in the direction of slower."""
    if not len(time) or not math.isfinite(ref_median):
        return math.nan, math.nan
    ratios = ref_median / np.where(time > 0, time, np.nan)
    return float(np.nanmin(ratios)), float(np.nanmax(ratios))


def knob_levels(knobs: pd.DataFrame, final_failure: pd.DataFrame, overall: pd.DataFrame, opts: ReportOptions,
                uniform: str | None = None) -> pd.DataFrame:
    """LEVEL_COLUMNS for every row of ``knobs`` (knob_arms). ``final_failure`` has ``arm, seed, value``
    per run (tables.per_run_metrics' ``final_failure``); ``overall`` is metrics.overall_failure of every
    run; ``uniform`` names the uniform arm, if any."""
    if knobs.empty:
        return pd.DataFrame(columns=LEVEL_COLUMNS)
    fails = {a: g.sort_values("seed")["value"].to_numpy(dtype=float) for a, g in final_failure.groupby("arm")}
    times = {t: time_to_threshold(overall, t, persist=opts.mastery_persist, by=["run_dir", "arm", "seed"])
             for t in THRESHOLDS}

    def arm_times(t: float, arm: str) -> tuple[np.ndarray, np.ndarray]:
        return event_times(times[t][times[t]["arm"] == arm].sort_values("seed"), "iteration")

    rows = []
    for k in knobs.itertuples(index=False):
        f, f_ref = fails.get(k.arm, np.array([])), fails.get(k.reference, np.array([]))
        row = {"knob": k.knob, "value": k.value, "arm": k.arm, "is_reference": k.arm == k.reference,
               "n_seeds": len(f), "final_failure": float(np.mean(f)) if len(f) else math.nan,
               "final_failure_min": float(np.min(f)) if len(f) else math.nan,
               "final_failure_max": float(np.max(f)) if len(f) else math.nan}
        same = k.arm == k.reference
        row["failure_difference"] = 0.0 if same else row["final_failure"] - float(np.mean(f_ref))
        low, high = (math.nan, math.nan) if same else shift_interval(f, f_ref, 1.0 - opts.alpha)
        row["failure_difference_low"], row["failure_difference_high"] = low, high
        row["failure_p"] = math.nan if same else permutation_pvalue(f, f_ref, n_resamples=opts.n_permutations,
                                                                    seed=opts.bootstrap_seed)
        row["failure_smallest_p"] = math.nan if same else smallest_pvalue(len(f), len(f_ref), opts.n_permutations)
        for t in THRESHOLDS:
            tag = int(round(t * 100))
            at, ae = arm_times(t, k.arm)
            bt, be = arm_times(t, k.reference)
            s = speedup(bt, be, at, ae, bootstrap=False, n_permutations=opts.n_permutations, seed=opts.bootstrap_seed)
            row[f"iterations_{tag}"] = arm_time(at, ae).median
            row[f"reached_{tag}"] = int(ae.sum())
            row[f"speedup_{tag}"], row[f"speedup_status_{tag}"] = s.ratio, s.status
            low, high = (math.nan, math.nan) if same else ratio_interval(
                bt, be, at, ae, 1.0 - opts.alpha, opts.n_permutations, opts.bootstrap_seed)
            row[f"speedup_low_{tag}"], row[f"speedup_high_{tag}"] = low, high
            lo, hi = _seed_ratios(arm_time(bt, be).median, at, ae)
            row[f"speedup_seed_min_{tag}"], row[f"speedup_seed_max_{tag}"] = lo, hi
            row[f"speedup_p_{tag}"] = math.nan if same else s.p_value
            if uniform is not None and uniform in set(times[t]["arm"]):
                u = speedup(*arm_times(t, uniform), at, ae, bootstrap=False, n_permutations=opts.n_permutations,
                            seed=opts.bootstrap_seed)
                row[f"vs_uniform_{tag}"], row[f"vs_uniform_status_{tag}"] = u.ratio, u.status
            else:
                row[f"vs_uniform_{tag}"], row[f"vs_uniform_status_{tag}"] = math.nan, "not_estimable"
        rows.append(row)
    return pd.DataFrame(rows, columns=LEVEL_COLUMNS)


def rank_trend(values, outcomes, n_resamples: int = 9999, seed: int = 0) -> tuple[float, float]:
    """(rho, p): Spearman's rank correlation of ``values`` and ``outcomes`` (average ranks for ties) and its
    two-sided permutation p (outcomes shuffled over the pairs: exact up to EXACT_PERMUTATIONS orders, else
    ``n_resamples`` seeded ones). (NaN, NaN) with fewer than 3 pairs or a constant side. NaN pairs dropped."""
    from scipy import stats

    x, y = np.asarray(values, dtype=float), np.asarray(outcomes, dtype=float)
    keep = ~(np.isnan(x) | np.isnan(y))
    x, y = pd.Series(x[keep]).rank().to_numpy(), pd.Series(y[keep]).rank().to_numpy()
    if len(x) < 3 or np.all(x == x[0]) or np.all(y == y[0]):
        return math.nan, math.nan

    def rho(a, axis=-1):  # Pearson's r of the ranks: x fixed, a permuted
        a_c = a - a.mean(axis=axis, keepdims=True)
        x_c = x - x.mean()
        return (a_c * x_c).sum(axis=axis) / np.sqrt((a_c ** 2).sum(axis=axis) * (x_c ** 2).sum())

    res = stats.permutation_test((y,), rho, permutation_type="pairings", alternative="two-sided", vectorized=True,
                                 n_resamples=n_resamples, rng=np.random.default_rng(seed))
    return float(res.statistic), float(min(1.0, res.pvalue))


def knob_trends(knobs: pd.DataFrame, final_failure: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """TREND_COLUMNS, one row per knob of ``knobs`` (knob_arms): rank_trend of the knob's value against each
    run's final failure (``final_failure``: ``arm, seed, value`` per run) over the runs of its levels."""
    rows = []
    for knob, g in knobs.groupby("knob", sort=True):
        runs = final_failure.merge(g[["arm", "value"]].rename(columns={"value": "level"}), on="arm")
        r, p = rank_trend(runs["level"], runs["value"], opts.n_permutations, opts.bootstrap_seed)
        rows.append({"knob": knob, "trend_runs": len(runs), "trend_rho": r, "trend_p": p})
    return pd.DataFrame(rows, columns=TREND_COLUMNS)


def knob_summary(levels: pd.DataFrame, alpha: float = 0.05, trends: pd.DataFrame | None = None) -> pd.DataFrame:
    """SUMMARY_COLUMNS: one row per knob of ``levels`` (knob_levels), with ``trends`` (knob_trends) if given."""
    tag = int(round(THRESHOLDS[0] * 100))
    rows = []
    for knob, g in levels.groupby("knob", sort=True):
        ref = g[g["is_reference"]]
        other = g[~g["is_reference"]]
        if other.empty:
            continue
        ranked = other.assign(_s=other[f"speedup_{tag}"].fillna(-np.inf)).sort_values(["_s", "value"])
        slow, fast = ranked.iloc[0], ranked.iloc[-1]
        by_fail = other.sort_values(["failure_difference", "value"])
        uncorrected = other[(other["failure_p"] < alpha) | (other[f"speedup_p_{tag}"] < alpha)]
        # The row's family: each level's final-failure test and its time test (a NaN p is no test).
        family = np.concatenate([other["failure_p"].to_numpy(float), other[f"speedup_p_{tag}"].to_numpy(float)])
        adjusted = holm(family)
        n = len(other)
        differing = other[(adjusted[:n] < alpha) | (adjusted[n:] < alpha)]
        rows.append({
            "knob": knob, "reference_value": float(ref["value"].iloc[0]) if len(ref) else math.nan,
            "levels": ", ".join(f"{v:g}" for v in sorted(g["value"])),
            **{f"{name}_{c}": row[f"{c}_{tag}" if c != "value" else "value"]
               for name, row in (("slowest", slow), ("fastest", fast))
               for c in ("value", "speedup", "speedup_low", "speedup_high", "speedup_seed_min", "speedup_seed_max")},
            "lowest_failure_value": by_fail["value"].iloc[0],
            "lowest_failure_difference": by_fail["failure_difference"].iloc[0],
            "lowest_failure_low": by_fail["failure_difference_low"].iloc[0],
            "lowest_failure_high": by_fail["failure_difference_high"].iloc[0],
            "highest_failure_value": by_fail["value"].iloc[-1],
            "highest_failure_difference": by_fail["failure_difference"].iloc[-1],
            "highest_failure_low": by_fail["failure_difference_low"].iloc[-1],
            "highest_failure_high": by_fail["failure_difference_high"].iloc[-1],
            "tests": int(np.count_nonzero(~np.isnan(family))),
            "differing_levels_uncorrected": ", ".join(f"{v:g}" for v in sorted(uncorrected["value"])),
            "differing_levels": ", ".join(f"{v:g}" for v in sorted(differing["value"])),
            "verdict": "differs" if len(differing) else "within noise",
        })
    out = pd.DataFrame(rows, columns=[c for c in SUMMARY_COLUMNS if not c.startswith("trend_")])
    trend = trends if trends is not None else pd.DataFrame(columns=TREND_COLUMNS)
    return out.merge(trend, on="knob", how="left")[SUMMARY_COLUMNS]


__all__ = ["KNOB_ARM_COLUMNS", "LEVEL_COLUMNS", "SUMMARY_COLUMNS", "THRESHOLDS", "TREND_COLUMNS", "knob_arms",
           "knob_levels", "knob_summary", "knob_trends", "rank_trend"]
