"""Per-clip results of a motion library: final failure, bins never mastered, where the sampler put its mass.

A clip's failure is in the unit of the overall failure: failed evaluation episodes over the episodes
that started in the clip (metrics.start_failure), at the common final evaluation, so the overall
failure is the start-weighted mean of the clips'. Bins never mastered are the clip's bins whose
median mastery over seeds was not reached (mastery uses the per-visit bin rate). The sampling mass is
the clip's share of the training sampler's probability (sampler.parquet's ``probability`` summed over
the clip's bins), a mean over the logged iterations and then over seeds: the same quantity for every
sampler, whatever its own accounting counts. Empty for a single clip or for tables without a `clip`
column (runs from before motion libraries)."""

from __future__ import annotations

import pandas as pd

from analysis.metrics import at_budget, final_rows, start_failure
from analysis.stats import seed_interval
from analysis.tables import ReportOptions, per_seed_text, seeds_text, use_bootstrap
from bmimic.runs.schema import BIN, FAILURE_RATE, ITERATION


def bin_clips(eval_df: pd.DataFrame) -> pd.Series:
    """The clip of each bin (index: bin), from the evaluation table; empty without a `clip` column."""
    if "clip" not in eval_df.columns or eval_df["clip"].nunique() < 2:
        return pd.Series(dtype=object)
    return eval_df.drop_duplicates(BIN).set_index(BIN)["clip"].sort_index()


def clip_mass(sampler_df: pd.DataFrame, clips: pd.Series) -> pd.Series:
    """Per ``arm, clip``: the clip's probability mass in the training sampler, the mean over each run's
    logged iterations, then over the arm's runs (empty without sampler tables)."""
    if not len(sampler_df) or "probability" not in sampler_df.columns:
        return pd.Series(dtype=float)
    df = sampler_df.assign(clip=sampler_df[BIN].map(clips))
    per_it = df.groupby(["arm", "run_dir", ITERATION, "clip"])["probability"].sum()
    per_run = per_it.groupby(["arm", "run_dir", "clip"]).mean()
    return per_run.groupby(["arm", "clip"]).mean()


def clip_failure(eval_df: pd.DataFrame, sampler_df: pd.DataFrame, mastery_df: pd.DataFrame, runs: pd.DataFrame,
                 opts: ReportOptions) -> pd.DataFrame:
    """One row per ``arm, clip``: final failure per started episode (point and interval over seeds; each
    seed's in ``per_seed``, in the order of ``seeds``, read at ``iterations``: the common budget), its bins,
    bins never mastered, and the mean sampling probability mass (NaN without sampler tables). A run that went
    past the common budget is also read at its own last evaluation: ``per_seed_at_end`` at
    ``end_iterations`` (equal to ``per_seed`` and ``iterations`` when every run ends at the budget)."""
    clips = bin_clips(eval_df)
    if clips.empty:
        return pd.DataFrame()
    common = float(eval_df.groupby("run_dir")[ITERATION].max().min())
    last = at_budget(eval_df, "iteration", common)
    per_run = start_failure(last, clips).rename(columns={"group": "clip"})
    at_end = start_failure(final_rows(eval_df), clips).rename(columns={"group": "clip"}).set_index(["arm", "clip", "seed"])
    never = mastery_df[mastery_df["mastery_iteration"].isna()].assign(clip=lambda d: d[BIN].map(clips))
    never = never.groupby(["arm", "clip"]).size()
    mass = clip_mass(sampler_df, clips)
    boot = use_bootstrap(runs)
    rows = []
    for (arm, clip), g in per_run.groupby(["arm", "clip"], sort=False):
        p, low, high, method = seed_interval(g[FAILURE_RATE].dropna(), boot, opts.n_resamples, opts.confidence,
                                             opts.bootstrap_seed)
        g = g.sort_values("seed", kind="stable")
        end = at_end.loc[[(arm, clip, seed) for seed in g["seed"]]]
        rows.append({"arm": arm, "clip": clip, "num_bins": int((clips == clip).sum()), "final_failure": p,
                     "final_failure_low": low, "final_failure_high": high, "ci_method": method, "n_seeds": len(g),
                     "seeds": seeds_text(g["seed"]), "per_seed": per_seed_text(g[FAILURE_RATE]),
                     "iterations": seeds_text(g[ITERATION]), "end_iterations": seeds_text(end[ITERATION]),
                     "per_seed_at_end": per_seed_text(end[FAILURE_RATE]),
                     "bins_not_mastered": int(never.get((arm, clip), 0)),
                     "sampling_mass": float(mass.get((arm, clip), float("nan")))})
    order = {c: i for i, c in enumerate(dict.fromkeys(clips))}
    out = pd.DataFrame(rows)
    return out.sort_values(["clip", "arm"], key=lambda s: s.map(order) if s.name == "clip" else s).reset_index(drop=True)


HARDEST_CLIPS = 6
"""How many clips the hardest clips' learning-curve figure shows."""


def hardest_clip_curves(eval_df: pd.DataFrame, clip_tab: pd.DataFrame, k: int = HARDEST_CLIPS) -> pd.DataFrame:
    """``clip, arm, run_dir, iteration, failure_rate``: failure per started episode at every evaluation of
    the ``k`` clips with the highest final failure (mean over arms of clip_failure's point), hardest first
    (``clip`` ordered so); empty for a single clip."""
    clips = bin_clips(eval_df)
    if clips.empty or not len(clip_tab):
        return pd.DataFrame()
    order = clip_tab.groupby("clip", sort=False)["final_failure"].mean().sort_values(ascending=False, kind="stable")
    hardest = list(order.index[:k])
    curves = start_failure(eval_df, clips).rename(columns={"group": "clip"})
    curves = curves[curves["clip"].isin(hardest)][["clip", "arm", "run_dir", ITERATION, FAILURE_RATE]]
    curves["clip"] = pd.Categorical(curves["clip"], categories=hardest, ordered=True)
    return curves.sort_values(["clip", "arm", "run_dir", ITERATION]).reset_index(drop=True)


__all__ = ["HARDEST_CLIPS", "bin_clips", "clip_failure", "clip_mass", "hardest_clip_curves"]
