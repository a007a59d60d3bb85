"""The report's tables over time and bins, computed from the tidy frames of ``analysis.load``: time to
the success threshold and bin mastery per arm (Kaplan-Meier medians over seeds), speedups against the
baseline, failure per bin and per motion segment, and the sampling distribution.

Same conventions as ``analysis.tables`` (its ``ReportOptions``; fixed RNG seeds).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pandas as pd

from analysis.metrics import (
    MEASURES,
    arm_time,
    at_budget,
    event_times,
    mastery_per_seed,
    speedup,
    start_failure,
    time_to_threshold,
)
from analysis.stats import MIN_SEEDS_IQM, curve_intervals, seed_interval
from analysis.tables import SPEEDUP_COLUMNS, ReportOptions, per_seed_text, use_bootstrap
from bmimic.runs.schema import BIN, FAILURE_RATE, HORIZON_TRUNCATED, ITERATION


def run_times(overall: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """Time to the success threshold per run (metrics.time_to_threshold, with persistence)."""
    return time_to_threshold(overall, opts.success_threshold, persist=opts.mastery_persist,
                             by=["run_dir", "arm", "seed"])


def time_summary(times: pd.DataFrame) -> pd.DataFrame:
    """Per arm and measure: ``n_seeds, n_reached, median, follow_up, per_seed`` (Kaplan-Meier median over
    seeds; NaN = not reached; per_seed lists event times, censored ones as ``>t``)."""
    rows = []
    for arm, g in times.groupby("arm", sort=True):
        g = g.sort_values("seed")
        for m in MEASURES:
            t, e = event_times(g, m)
            s = arm_time(t, e)
            per_seed = ";".join(f"{x:.6g}" if ev else f">{x:.6g}" for x, ev in zip(t, e, strict=True))
            rows.append((arm, m, s.n, s.n_reached, s.median, s.follow_up, per_seed))
    return pd.DataFrame(rows, columns=["arm", "measure", "n_seeds", "n_reached", "median", "follow_up", "per_seed"])


def bin_layouts(eval_df: pd.DataFrame, reference: str | None = None,
                columns: tuple[str, ...] = ("bin_start_s", "bin_end_s")) -> tuple[list[str], list[str]]:
    """``(same, other)``: the arms whose evaluation cuts the motion into the same bins as ``reference``
    (default: the layout most arms share) and those cut into other bins (a bin-size knob, BeyondMimic's
    released layout). Per-bin tables match bins by number, so only ``same`` can share them; ``other`` is
    empty in a report of one layout. A layout is what an arm's evaluations report for each bin in
    ``columns``: its clip times, or with ``("clip",)`` only its clip (per-clip tables need no more)."""
    if not len(eval_df):
        return [], []
    cells = eval_df[["arm", BIN, *columns]].drop_duplicates(subset=["arm", BIN]).sort_values(BIN)
    layout = {arm: tuple(tuple(round(v, 6) if isinstance(v, float) else v for v in r)
                         for r in g[[BIN, *columns]].itertuples(index=False, name=None))
              for arm, g in cells.groupby("arm", sort=True)}
    if reference not in layout:
        counts: dict[tuple, int] = {}
        for lay in layout.values():
            counts[lay] = counts.get(lay, 0) + 1
        reference = next(arm for arm, lay in layout.items() if counts[lay] == max(counts.values()))
    same = [arm for arm, lay in layout.items() if lay == layout[reference]]
    return same, [arm for arm in layout if arm not in same]


def mastery_seeds(eval_df: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """metrics.mastery_per_seed with the report's threshold and persistence."""
    return mastery_per_seed(eval_df, opts.mastery_threshold, opts.mastery_persist)


def mastery(mastery_seed_df: pd.DataFrame, bins: pd.DataFrame) -> pd.DataFrame:
    """Per ``arm, bin``: ``segment, horizon_truncated, n_seeds, n_mastered, mastery_iteration`` (the
    Kaplan-Meier median over seeds, NaN = not reached), ``follow_up`` and ``per_seed`` (iterations,
    ``>t`` for seeds censored at t)."""
    rows = []
    for (arm, b), g in mastery_seed_df.groupby(["arm", BIN], sort=True):
        g = g.sort_values("seed")
        t, e = event_times(g, "iteration")
        s = arm_time(t, e)
        per_seed = ";".join(f"{x:.6g}" if ev else f">{x:.6g}" for x, ev in zip(t, e, strict=True))
        rows.append((arm, b, s.n, s.n_reached, s.median, s.follow_up, per_seed))
    out = pd.DataFrame(rows, columns=["arm", BIN, "n_seeds", "n_mastered", "mastery_iteration", "follow_up",
                                      "per_seed"])
    return out.merge(bins[[BIN, "segment", HORIZON_TRUNCATED]], on=BIN, how="left")


def speedups(times: pd.DataFrame, mastery_seed_df: pd.DataFrame, baseline: str, runs: pd.DataFrame,
             opts: ReportOptions) -> tuple[pd.DataFrame, pd.DataFrame]:
    """``(speedup, per_bin)``: speedup.csv (SPEEDUP_COLUMNS; measures: time to the success threshold in
    iterations, env steps and wall time) and the per-bin mastery speedups (``arm, baseline, bin`` then
    the same columns), each arm against ``baseline`` (metrics.speedup)."""
    boot = use_bootstrap(runs)
    kw: dict[str, Any] = dict(bootstrap=boot, n_resamples=opts.n_resamples, confidence=opts.confidence, seed=opts.bootstrap_seed,
              n_permutations=opts.n_permutations)
    rows, bin_rows = [], []
    base_t = times[times["arm"] == baseline].sort_values("seed")
    for arm in sorted(set(times["arm"]) - {baseline}):
        t = times[times["arm"] == arm].sort_values("seed")
        for m in MEASURES:
            s = speedup(*event_times(base_t, m), *event_times(t, m), **kw)
            rows.append((arm, baseline, m, s.ratio, s.ci_low, s.ci_high, s.status, s.p_value))
    base_m = mastery_seed_df[mastery_seed_df["arm"] == baseline]
    for (arm, b), g in mastery_seed_df[mastery_seed_df["arm"] != baseline].groupby(["arm", BIN], sort=True):
        bm = base_m[base_m[BIN] == b]
        if not len(bm):
            continue
        s = speedup(*event_times(bm.sort_values("seed"), "iteration"), *event_times(g.sort_values("seed"), "iteration"),
                    **kw)
        bin_rows.append((arm, baseline, b, s.ratio, s.ci_low, s.ci_high, s.status, s.p_value))
    cols = ["arm", "baseline", BIN, *SPEEDUP_COLUMNS[3:]]
    return pd.DataFrame(rows, columns=SPEEDUP_COLUMNS), pd.DataFrame(bin_rows, columns=cols)


def speedup_per_seed(times: pd.DataFrame, baseline: str) -> pd.DataFrame:
    """``arm, seed, measure, value``: the baseline's median time over each arm seed's time (seeds that
    reached the threshold, while the baseline's median is defined): the dots of the speedup figure."""
    rows = []
    base = times[times["arm"] == baseline]
    for m in MEASURES:
        median = arm_time(*event_times(base, m)).median
        if math.isnan(median):
            continue
        for r in times[(times["arm"] != baseline) & times["reached"]].itertuples(index=False):
            value = getattr(r, m)
            rows.append((r.arm, r.seed, m, median / value if value else math.inf))
    return pd.DataFrame(rows, columns=["arm", "seed", "measure", "value"])


def bin_failure(eval_df: pd.DataFrame) -> pd.DataFrame:
    """Seed-mean failure per ``arm, iteration, bin`` (``failure_rate``, ``n_seeds``)."""
    return (
        eval_df.groupby(["arm", ITERATION, BIN], sort=True)
        .agg(failure_rate=(FAILURE_RATE, "mean"), n_seeds=("seed", "nunique"))
        .reset_index()
    )


def final_bin_failure(eval_df: pd.DataFrame, runs: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """Per ``arm, bin`` at the common final iteration: ``n_seeds, point, point_label, ci_low, ci_high,
    ci_method, per_seed, iteration``."""
    if not len(eval_df):
        return pd.DataFrame()
    common = float(eval_df.groupby("run_dir")[ITERATION].max().min())
    last = at_budget(eval_df, "iteration", common)
    boot = use_bootstrap(runs)
    frames = []
    for arm, g in last.groupby("arm", sort=True):
        wide = g.pivot_table(index="seed", columns=BIN, values=FAILURE_RATE, aggfunc="mean").sort_index()
        m = wide.to_numpy(dtype=float)
        p, low, high, method = curve_intervals(m, boot, opts.n_resamples, opts.confidence, opts.bootstrap_seed)
        n = (~np.isnan(m)).sum(axis=0)
        frames.append(pd.DataFrame({
            "arm": arm, BIN: wide.columns, "n_seeds": n, "point": p,
            "point_label": np.where(n >= MIN_SEEDS_IQM, "iqm", "mean"), "ci_low": low, "ci_high": high,
            "ci_method": method, "per_seed": [per_seed_text(pd.Series(col[~np.isnan(col)])) for col in m.T],
            ITERATION: common,
        }))
    return pd.concat(frames, ignore_index=True)


def over_clip_time(eval_df: pd.DataFrame, sampler_df: pd.DataFrame) -> pd.DataFrame:
    """Per ``arm, bin`` of each arm's own layout: ``bin_start_s, bin_end_s``, the ``failure_rate`` at the common
    final evaluation and the training sampler's ``density`` at each run's last logged iteration (probability
    per second over uniform's: 1 = uniform), both the mean over seeds. Drawn over clip time, arms cut into
    different bins compare (a bin-size knob). Empty for a library of several clips (no single clip time)."""
    if not len(eval_df) or ("clip" in eval_df.columns and eval_df["clip"].nunique() > 1):
        return pd.DataFrame()
    common = float(eval_df.groupby("run_dir")[ITERATION].max().min())
    last = at_budget(eval_df, ITERATION, common)
    keys = ["arm", BIN, "bin_start_s", "bin_end_s"]
    out = last.groupby(keys, sort=True)[FAILURE_RATE].mean().reset_index()
    if len(sampler_df) and {"probability", "bin_start_s", "bin_end_s"} <= set(sampler_df.columns):
        s = at_budget(sampler_df, ITERATION, float(sampler_df[ITERATION].max()))
        width = s["bin_end_s"] - s["bin_start_s"]
        length = width.groupby(s["run_dir"]).transform("sum")
        s = s.assign(density=s["probability"] * length / width)
        out = out.merge(s.groupby(keys, sort=True)["density"].mean().reset_index(), on=keys, how="left")
    else:
        out["density"] = np.nan
    return out


def segment_failure(eval_df: pd.DataFrame, bins: pd.DataFrame, mastery_df: pd.DataFrame,
                    segments: pd.DataFrame | None, runs: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """Final failure per ``arm, segment`` at the common final iteration, in the unit of the overall
    failure: failed episodes / episodes started in the segment (metrics.start_failure) per run, then
    point and interval over seeds; with the segment's difficulty (when the motion names one), its
    bins, and how many of them the arm has not mastered (median not reached). Empty for a motion of
    fewer than two segments."""
    if bins["segment"].nunique() < 2:
        return pd.DataFrame()
    common = float(eval_df.groupby("run_dir")[ITERATION].max().min())
    last = at_budget(eval_df, "iteration", common)
    per_run = start_failure(last, bins.set_index(BIN)["segment"]).rename(columns={"group": "segment"})
    difficulty = {}
    if segments is not None and "difficulty" in segments.columns:
        difficulty = dict(zip(segments["name"].astype(str), segments["difficulty"].astype(str), strict=True))
    order = list(dict.fromkeys(bins.sort_values(BIN)["segment"]))
    never = mastery_df[mastery_df["mastery_iteration"].isna()].groupby(["arm", "segment"]).size()
    boot = use_bootstrap(runs)
    rows = []
    for (arm, seg), g in per_run.groupby(["arm", "segment"], sort=False):
        p, low, high, method = seed_interval(g[FAILURE_RATE], boot, opts.n_resamples, opts.confidence,
                                             opts.bootstrap_seed)
        rows.append({"arm": arm, "segment": seg, "difficulty": difficulty.get(seg, ""),
                     "num_bins": int((bins["segment"] == seg).sum()), "final_failure": p,
                     "final_failure_low": low, "final_failure_high": high, "ci_method": method,
                     "n_seeds": len(g), "bins_not_mastered": int(never.get((arm, seg), 0))})
    out = pd.DataFrame(rows)
    out["order"] = out["segment"].map({s: i for i, s in enumerate(order)})
    return out.sort_values(["order", "arm"]).drop(columns="order").reset_index(drop=True)


def sampling(sampler_df: pd.DataFrame, runs: pd.DataFrame) -> pd.DataFrame:
    """Seed-mean sampling probability per ``arm, iteration, bin`` for adaptive arms (sampler != uniform)."""
    adaptive = set(runs.loc[runs["included"] & (runs["sampler"] != "uniform"), "arm"])
    df = sampler_df[sampler_df["arm"].isin(adaptive)]
    return df.groupby(["arm", ITERATION, BIN], sort=True)["probability"].mean().reset_index()
