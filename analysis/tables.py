"""The report's tables, computed from the tidy frames of ``analysis.load``.

Each function takes the loaded tables and returns one tidy frame that is written as a CSV and
drawn by ``analysis.plots``. Intervals are 95 % percentile bootstraps over seeds with a fixed RNG
seed (``ReportOptions.bootstrap_seed``), so the same runs always give the same report.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis import AnalysisError
from analysis.metrics import (
    MEASURES,
    censored,
    final_rows,
    mastery_iterations,
    mastery_speedup,
    overall_failure,
    speedup,
    time_to_threshold,
)
from analysis.stats import DEFAULT_RESAMPLES, aggregate_over_seeds, bootstrap_ci, iqm


@dataclass(frozen=True)
class ReportOptions:
    """Thresholds and statistics settings of a report."""

    mastery_threshold: float = 0.1
    """A bin is mastered at the first evaluation where its failure rate is below this."""

    success_threshold: float = 0.9
    """Overall evaluated success (1 - mean failure over bins) an arm must reach for time to threshold."""

    baseline: str | None = None
    """Arm the speedups are measured against; None picks the arm whose sampler.name is "uniform"."""

    n_resamples: int = DEFAULT_RESAMPLES
    """Bootstrap resamples per interval."""

    confidence: float = 0.95
    """Coverage of the bootstrap intervals."""

    bootstrap_seed: int = 0
    """RNG seed of every bootstrap, for reproducible reports."""


CURVE_METRICS = {
    "mean_episode_length": ("train_metrics", "mean episode length (steps)"),
    "mean_reward": ("train_metrics", "mean reward"),
    "eval_failure_rate": ("eval", "evaluated overall failure rate"),
}
"""Learning-curve metric -> (source table, axis label)."""


def _boot(values, opts: ReportOptions) -> tuple[float, float, float]:
    values = np.asarray(values, dtype=float)
    values = values[~np.isnan(values)]
    if not len(values):
        return np.nan, np.nan, np.nan
    return bootstrap_ci(values, n_resamples=opts.n_resamples, confidence=opts.confidence, seed=opts.bootstrap_seed)


def choose_baseline(runs: pd.DataFrame, baseline: str | None) -> tuple[str | None, str]:
    """The baseline arm and a sentence saying how it was chosen (or why there is none)."""
    arms = runs.loc[runs["included"], ["arm", "sampler"]].drop_duplicates()
    if baseline is not None:
        if baseline not in set(arms["arm"]):
            raise AnalysisError(f"--baseline {baseline!r}: not an arm with usable runs; arms: {sorted(arms['arm'])}")
        return baseline, f"baseline `{baseline}` (given)"
    uniform = sorted(arms.loc[arms["sampler"] == "uniform", "arm"])
    if not uniform:
        return None, "no arm has sampler.name == uniform and no --baseline was given: speedups are skipped"
    note = f"baseline `{uniform[0]}` (its sampler is uniform)"
    if len(uniform) > 1:
        note += f"; other uniform arms: {', '.join(f'`{a}`' for a in uniform[1:])} (pick one with --baseline)"
    return uniform[0], note


def learning_curves(train: pd.DataFrame, overall: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """``arm, metric, iteration, iqm, mean, ci_low, ci_high, n_seeds`` for every CURVE_METRICS entry."""
    frames = []
    for metric, (source, _) in CURVE_METRICS.items():
        df = train if source == "train_metrics" else overall.rename(columns={"failure_rate": metric})
        if not len(df):
            continue
        curve = aggregate_over_seeds(df, metric, by=["arm"], x="iteration", n_resamples=opts.n_resamples,
                                     confidence=opts.confidence, seed=opts.bootstrap_seed, unit="run_dir")
        curve.insert(1, "metric", metric)
        frames.append(curve)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def bin_failure(eval_df: pd.DataFrame) -> pd.DataFrame:
    """Seed-mean failure per ``arm, iteration, bin`` (``failure_rate``, ``n_seeds``)."""
    return (
        eval_df.groupby(["arm", "iteration", "bin"], sort=True)
        .agg(failure_rate=("failure_rate", "mean"), n_seeds=("seed", "nunique"))
        .reset_index()
    )


def final_bin_failure(eval_df: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """Each run's last evaluation per bin, aggregated over seeds: ``arm, bin, iqm, ci_low, ci_high,
    n_seeds, iteration_min, iteration_max`` (the iterations differ when a run is still going)."""
    last = final_rows(eval_df, by=["run_dir"])
    frames = []
    for arm, g in last.groupby("arm", sort=True):
        wide = g.pivot_table(index="run_dir", columns="bin", values="failure_rate", aggfunc="mean")
        point, low, high = bootstrap_ci(wide.to_numpy(dtype=float), n_resamples=opts.n_resamples,
                                        confidence=opts.confidence, seed=opts.bootstrap_seed)
        its = g.groupby("bin")["iteration"]
        frames.append(pd.DataFrame({
            "arm": arm, "bin": wide.columns, "iqm": point, "ci_low": low, "ci_high": high,
            "n_seeds": wide.notna().sum().to_numpy(), "iteration_min": its.min().to_numpy(),
            "iteration_max": its.max().to_numpy(),
        }))
    return pd.concat(frames, ignore_index=True)


def segment_failure(eval_df: pd.DataFrame, bins: pd.DataFrame, mastery_df: pd.DataFrame,
                    segments: pd.DataFrame | None, opts: ReportOptions) -> pd.DataFrame:
    """Final failure per ``arm, segment``: each run's last evaluation averaged over the segment's bins,
    then IQM and interval over seeds; with the segment's difficulty (when the motion names one), its
    bins, and how many of them the arm never mastered. Empty for a motion of fewer than two segments."""
    if bins["segment"].nunique() < 2:
        return pd.DataFrame()
    last = final_rows(eval_df, by=["run_dir"]).drop(columns=["segment"], errors="ignore")
    last = last.merge(bins[["bin", "segment"]], on="bin", how="left")
    per_run = last.groupby(["arm", "segment", "run_dir"], sort=False)["failure_rate"].mean().reset_index()
    difficulty = {}
    if segments is not None and "difficulty" in segments.columns:
        difficulty = dict(zip(segments["name"].astype(str), segments["difficulty"].astype(str), strict=True))
    order = list(dict.fromkeys(bins.sort_values("bin")["segment"]))
    never = mastery_df[mastery_df["mastery_iteration"].isna()].groupby(["arm", "segment"]).size()
    rows = []
    for (arm, seg), g in per_run.groupby(["arm", "segment"], sort=False):
        point, low, high = _boot(g["failure_rate"], opts)
        rows.append({"arm": arm, "segment": seg, "difficulty": difficulty.get(seg, ""),
                     "num_bins": int((bins["segment"] == seg).sum()), "final_failure": point,
                     "final_failure_low": low, "final_failure_high": high, "n_seeds": len(g),
                     "bins_never_mastered": int(never.get((arm, seg), 0))})
    out = pd.DataFrame(rows)
    out["order"] = out["segment"].map({s: i for i, s in enumerate(order)})
    return out.sort_values(["order", "arm"]).drop(columns="order").reset_index(drop=True)


def sampling(sampler_df: pd.DataFrame, runs: pd.DataFrame) -> pd.DataFrame:
    """Seed-mean sampling probability per ``arm, iteration, bin`` for adaptive arms (sampler != uniform)."""
    adaptive = set(runs.loc[runs["included"] & (runs["sampler"] != "uniform"), "arm"])
    df = sampler_df[sampler_df["arm"].isin(adaptive)]
    return df.groupby(["arm", "iteration", "bin"], sort=True)["probability"].mean().reset_index()


def mastery(bin_fail: pd.DataFrame, bins: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """Mastery iteration per ``arm, bin`` from the arm's seed-mean failure, with the bin's segment."""
    m = mastery_iterations(bin_fail, opts.mastery_threshold, by=["arm"])
    return m.merge(bins[["bin", "segment"]], on="bin", how="left")


def run_times(overall: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """Time to the success threshold per run (metrics.time_to_threshold)."""
    return time_to_threshold(overall, opts.success_threshold, by=["run_dir", "arm", "seed"])


def arm_summary(runs, overall, mastery_df, times, opts: ReportOptions) -> pd.DataFrame:
    """One row per arm with usable runs: seeds, final overall failure (IQM and interval over seeds),
    median mastery iteration over bins (never-mastered bins at their last evaluation), bins never
    mastered, and time to threshold in each measure (IQM and interval over seeds; seeds that never
    reached it counted at their last evaluation) with the number of seeds that reached it."""
    rows = []
    final = final_rows(overall, by=["run_dir"])
    for arm in sorted(set(runs.loc[runs["included"], "arm"])):
        r = runs[runs["arm"] == arm]
        row = {
            "arm": arm,
            "sampler": r["sampler"].iloc[0],
            "n_seeds": int(r["included"].sum()),
            "n_running": int((r["included"] & (r["status"] == "running")).sum()),
            "n_excluded": int((~r["included"]).sum()),
        }
        f = final[final["arm"] == arm]
        row["final_failure"], row["final_failure_low"], row["final_failure_high"] = _boot(f["failure_rate"], opts)
        m = mastery_df[mastery_df["arm"] == arm]
        at = np.where(m["mastered"], m["mastery_iteration"], m["last_iteration"])
        row["mastery_median"] = float(np.median(at)) if len(at) else np.nan
        row["bins_never_mastered"] = int((~m["mastered"]).sum())
        row["num_bins"] = len(m)
        t = times[times["arm"] == arm]
        row["n_reached"] = int(t["reached"].sum())
        for measure in MEASURES:
            values = censored(t, measure) if row["n_reached"] else np.full(len(t), np.nan)
            point, low, high = _boot(values, opts)
            row[f"time_{measure}"], row[f"time_{measure}_low"], row[f"time_{measure}_high"] = point, low, high
        rows.append(row)
    return pd.DataFrame(rows)


def speedups(mastery_df, times, baseline: str, opts: ReportOptions) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Speedup of every arm against ``baseline`` (baseline / arm; > 1 means the arm is faster).

    Returns ``(per_bin, table)``: ``per_bin`` is metrics.mastery_speedup; ``table`` has one row per
    ``arm, measure``: the three time-to-threshold measures (ratio of IQMs over seeds, stratified
    bootstrap interval, seeds that never reached counted at their last evaluation; NaN when neither
    arm ever reached it) and ``mastery_median`` (median over bins of the per-bin ratios; no interval).
    ``bound`` is "lower" when no baseline seed reached the threshold (the ratio can only be larger),
    "upper" when no arm seed did, else empty.
    """
    per_bin = mastery_speedup(mastery_df, baseline)
    rows = []
    base_t = times[times["arm"] == baseline]
    for arm in sorted(set(times["arm"]) - {baseline}):
        t = times[times["arm"] == arm]
        bound = ""
        if not t["reached"].any():
            never = "no arm seed reached it: the ratio is an upper bound (arm counted at its last evaluation)"
            bound = "upper"
        elif not base_t["reached"].any():
            never = "no baseline seed reached it: the ratio is a lower bound (baseline counted at its last evaluation)"
            bound = "lower"
        else:
            never = (f"{int((~t['reached']).sum())}/{len(t)} arm seeds, {int((~base_t['reached']).sum())}/"
                     f"{len(base_t)} baseline seeds never reached it (counted at their last evaluation)")
        for measure in MEASURES:
            if not (t["reached"].any() or base_t["reached"].any()):
                rows.append((arm, measure, np.nan, np.nan, np.nan, np.nan, np.nan, "neither arm reached it", ""))
                continue
            b, a = censored(base_t, measure), censored(t, measure)
            ratio, low, high = speedup(b, a, n_resamples=opts.n_resamples, confidence=opts.confidence,
                                       seed=opts.bootstrap_seed)
            note = "" if t["reached"].all() and base_t["reached"].all() else never
            rows.append((arm, measure, iqm(b), iqm(a), ratio, low, high, note, bound))
        bins = per_bin[per_bin["arm"] == arm]
        ratios = bins["ratio"].dropna()
        note = f"{len(ratios)} bins; {int((bins['censored'] != '').sum())} censored"
        rows.append((arm, "mastery_median", np.nan, np.nan, float(np.median(ratios)) if len(ratios) else np.nan,
                     np.nan, np.nan, note, ""))
    table = pd.DataFrame(rows, columns=["arm", "measure", "baseline_value", "arm_value", "ratio", "ci_low",
                                        "ci_high", "note", "bound"])
    return per_bin, table


def swept_keys(runs: pd.DataFrame) -> list[str]:
    """Override keys with numeric values that take at least two values across included arms."""
    inc = runs[runs["included"]].drop_duplicates("arm")
    keys = []
    for col in (c for c in runs.columns if c.startswith("param.")):
        values = inc[col].dropna()
        numeric = values.map(lambda v: isinstance(v, int | float | np.number) and not isinstance(v, bool))
        if len(values) and numeric.all() and values.nunique() > 1:
            keys.append(col.removeprefix("param."))
    return keys


def _explicit_keys(overrides: str) -> set[str]:
    return {item.split("=", 1)[0].lstrip("+") for item in str(overrides).split(",") if "=" in item}


def sensitivity(runs: pd.DataFrame, summary: pd.DataFrame) -> pd.DataFrame:
    """Final failure, median mastery iteration and iterations to threshold against each swept key.

    For key ``k`` the arms compared are those whose sampler is one that some arm sets ``k`` for
    explicitly (a uniform arm also carries an unused ``gamma`` default, which must not become a
    point); ``series`` names the arm's other overrides, so a grid over two keys gives one line per
    value of the other. Returns ``key, value, series, arm, metric, iqm, ci_low, ci_high``.
    """
    arms = runs[runs["included"]].drop_duplicates("arm").set_index("arm")
    metrics = {
        "final_failure": ("final_failure", "final_failure_low", "final_failure_high"),
        "mastery_median": ("mastery_median", None, None),
        "time_iteration": ("time_iteration", "time_iteration_low", "time_iteration_high"),
    }
    s = summary.set_index("arm")
    rows = []
    for key in swept_keys(runs):
        setters = {a for a in arms.index if key in _explicit_keys(arms.loc[a, "overrides"])}
        samplers = set(arms.loc[sorted(setters), "sampler"])
        for arm in sorted(a for a in arms.index if arms.loc[a, "sampler"] in samplers):
            value = arms.loc[arm, f"param.{key}"]
            if pd.isna(value) or arm not in s.index:
                continue
            others = [i for i in str(arms.loc[arm, "overrides"]).split(",") if i.split("=", 1)[0] != key]
            series = ",".join(others)
            for metric, (col, lo, hi) in metrics.items():
                point = s.loc[arm, col]
                rows.append((key, float(value), series, arm, metric, point,
                             s.loc[arm, lo] if lo else point, s.loc[arm, hi] if hi else point))
    return pd.DataFrame(rows, columns=["key", "value", "series", "arm", "metric", "iqm", "ci_low", "ci_high"])


def overall(eval_df: pd.DataFrame) -> pd.DataFrame:
    """metrics.overall_failure of every run."""
    return overall_failure(eval_df, by=["run_dir", "arm", "seed"])
