"""Per-clip results of a motion library: final failure, bins never mastered, share of starts.

A clip's failure is counted as the overall failure is (failures where they happened over visits,
summed over the clip's bins) at the common final evaluation; bins never mastered are the clip's bins
whose median mastery over seeds was not reached; the share of starts is the clip's fraction of the
episodes the training sampler started (sampler.parquet's counts), a mean over seeds. Empty for a
single clip or for tables without a `clip` column (runs from before motion libraries)."""

from __future__ import annotations

import pandas as pd

from analysis.markdown import estimate_cell
from analysis.metrics import at_budget
from analysis.stats import seed_interval
from analysis.tables import ReportOptions, use_bootstrap


def bin_clips(eval_df: pd.DataFrame) -> pd.Series:
    """The clip of each bin (index: bin), from the evaluation table; empty without a `clip` column."""
    if "clip" not in eval_df.columns or eval_df["clip"].nunique() < 2:
        return pd.Series(dtype=object)
    return eval_df.drop_duplicates("bin").set_index("bin")["clip"].sort_index()


def clip_failure(eval_df: pd.DataFrame, sampler_df: pd.DataFrame, mastery_df: pd.DataFrame, runs: pd.DataFrame,
                 opts: ReportOptions) -> pd.DataFrame:
    """One row per ``arm, clip``: final failure (point and interval over seeds), its bins, bins never
    mastered, and the mean share of training starts (NaN without sampler tables)."""
    clips = bin_clips(eval_df)
    if clips.empty:
        return pd.DataFrame()
    common = float(eval_df.groupby("run_dir")["iteration"].max().min())
    last = at_budget(eval_df, "iteration", common).drop(columns=["clip"]).merge(
        clips.rename("clip"), left_on="bin", right_index=True)
    sums = last.groupby(["arm", "clip", "run_dir"], sort=False)[["failures", "visits"]].sum().reset_index()
    sums["failure"] = sums["failures"] / sums["visits"].where(sums["visits"] > 0)
    never = mastery_df[mastery_df["mastery_iteration"].isna()].assign(clip=lambda d: d["bin"].map(clips))
    never = never.groupby(["arm", "clip"]).size()
    share = pd.Series(dtype=float)
    if len(sampler_df) and "episodes" in sampler_df.columns:
        starts = sampler_df.assign(clip=sampler_df["bin"].map(clips)).groupby(["arm", "run_dir", "clip"])["episodes"].sum()
        share = (starts / starts.groupby(["arm", "run_dir"]).transform("sum")).groupby(["arm", "clip"]).mean()
    boot = use_bootstrap(runs)
    rows = []
    for (arm, clip), g in sums.groupby(["arm", "clip"], sort=False):
        p, low, high, method = seed_interval(g["failure"].dropna(), boot, opts.n_resamples, opts.confidence,
                                             opts.bootstrap_seed)
        rows.append({"arm": arm, "clip": clip, "num_bins": int((clips == clip).sum()), "final_failure": p,
                     "final_failure_low": low, "final_failure_high": high, "ci_method": method, "n_seeds": len(g),
                     "bins_not_mastered": int(never.get((arm, clip), 0)),
                     "start_share": float(share.get((arm, clip), float("nan")))})
    order = {c: i for i, c in enumerate(dict.fromkeys(clips))}
    out = pd.DataFrame(rows)
    return out.sort_values(["clip", "arm"], key=lambda s: s.map(order) if s.name == "clip" else s).reset_index(drop=True)


def clip_view(table: pd.DataFrame) -> pd.DataFrame:
    """The Clips table: per clip (rows) and arm (columns): final failure, (bins not mastered / bins),
    share of starts."""
    cells = [f"{estimate_cell(p, lo, hi, m, n)} ({nm}/{b}); starts {s:.1%}" if s == s else
             f"{estimate_cell(p, lo, hi, m, n)} ({nm}/{b})"
             for p, lo, hi, m, n, nm, b, s in zip(table["final_failure"], table["final_failure_low"],
                                                   table["final_failure_high"], table["ci_method"], table["n_seeds"],
                                                   table["bins_not_mastered"], table["num_bins"], table["start_share"],
                                                   strict=True)]
    view = table.assign(cell=cells).pivot_table(index="clip", columns="arm", values="cell", aggfunc="first", sort=False)
    return view.reset_index()


def never_started(table: pd.DataFrame) -> list[str]:
    """`arm: clip` for every clip an arm's sampler never started an episode from."""
    hit = table[table["start_share"] == 0]
    return [f"`{a}`: {c}" for a, c in zip(hit["arm"], hit["clip"], strict=True)]


__all__ = ["bin_clips", "clip_failure", "clip_view", "never_started"]
