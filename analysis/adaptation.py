"""Whether a sampler adapted: how concentrated its distribution was, and whether its signal said anything.

From sampler.parquet (the distribution after each logged update and the sampler's own signal,
``smoothed_failure_rate``):

- *effective support* of a distribution p over S bins = (1 / sum p^2) / S: 1 for uniform, 1/S when
  all mass is on one bin; the same over the C clips of a library with the clips' masses;
- *largest p relative to uniform* = max p x S (max clip mass x C over clips): 1 for uniform;
- the sampler's *signal is flat* at an iteration when it is equal in every bin (within 1e-9
  relative): then it carries no information about where to sample, and a sampler that depends on it
  (the design saturated at a failure rate of 1 everywhere, PHC when every clip failed every
  evaluation) samples as it would with no signal. Samplers without a signal (uniform: NaN) have none.

An arm whose signal was flat at every logged iteration of every seed had a *degenerate* signal; the
report names those arms, and for the others says until when the signal stayed flat.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from bmimic.runs.schema import BIN, ITERATION

FLAT_TOLERANCE = 1e-9
"""Relative spread below which a signal counts as equal in every bin."""

SUPPORT_COLUMNS = ["run_dir", "arm", "seed", ITERATION, "num_bins", "effective_support", "max_p_rel",
                   "num_clips", "clip_effective_support", "clip_max_p_rel", "signal_flat"]
"""Columns of the per-run support table (clip columns NaN for a single motion; ``signal_flat`` NaN for a
sampler without a signal)."""


def _per_iteration(g: pd.DataFrame, clips: pd.Series | None) -> pd.Series:
    p = g["probability"].to_numpy(dtype=float)
    s = len(p)
    out = {"num_bins": s, "effective_support": 1.0 / float(np.sum(p * p)) / s, "max_p_rel": float(p.max()) * s}
    if clips is not None and len(clips):
        mass = pd.Series(p, index=g[BIN].to_numpy()).groupby(clips).sum().to_numpy(dtype=float)
        c = len(mass)
        out.update(num_clips=c, clip_effective_support=1.0 / float(np.sum(mass * mass)) / c,
                   clip_max_p_rel=float(mass.max()) * c)
    else:
        out.update(num_clips=np.nan, clip_effective_support=np.nan, clip_max_p_rel=np.nan)
    sig = g["smoothed_failure_rate"].to_numpy(dtype=float) if "smoothed_failure_rate" in g else np.array([np.nan])
    if np.isnan(sig).all():
        out["signal_flat"] = np.nan
    else:
        lo, hi = np.nanmin(sig), np.nanmax(sig)
        out["signal_flat"] = float(hi - lo <= FLAT_TOLERANCE * max(1.0, abs(hi)))
    return pd.Series(out)


def sampling_support(sampler_df: pd.DataFrame, clips: pd.Series | None = None) -> pd.DataFrame:
    """SUPPORT_COLUMNS, one row per run and logged iteration; ``clips`` maps bin -> clip (a library)."""
    if not len(sampler_df):
        return pd.DataFrame(columns=SUPPORT_COLUMNS)
    rows = sampler_df.sort_values(BIN).groupby(["run_dir", "arm", "seed", ITERATION], sort=True).apply(
        lambda g: _per_iteration(g, clips), include_groups=False)
    out = rows.reset_index()
    out["signal_flat"] = out["signal_flat"].astype(float)
    return out[SUPPORT_COLUMNS]


def at_evaluations(support: pd.DataFrame, evaluations: pd.DataFrame) -> pd.DataFrame:
    """Per run, the support row nearest before each of that run's own evaluations (``evaluations``: one row
    per ``run_dir`` and ``iteration``; the distribution the evaluated policy was trained with last),
    labelled with the evaluation's ``iteration``. A run is never read at an evaluation it did not have (one
    that stopped earlier, or evaluated on another schedule, than the others)."""
    frames = []
    own = evaluations.groupby("run_dir")[ITERATION].agg(lambda v: sorted(set(v)))
    for run, g in support.groupby("run_dir", sort=True):
        g = g.sort_values(ITERATION)
        its = g[ITERATION].to_numpy()
        for e in own.get(run, []):
            i = np.searchsorted(its, e, side="right") - 1
            if i >= 0:
                frames.append(g.iloc[[i]].assign(**{ITERATION: e}))
    return pd.concat(frames, ignore_index=True) if frames else support.iloc[:0]


def support_summary(support: pd.DataFrame) -> pd.DataFrame:
    """Per ``arm, iteration``: the mean over seeds of every support column, and ``n_seeds``."""
    cols = ["effective_support", "max_p_rel", "clip_effective_support", "clip_max_p_rel"]
    g = support.groupby(["arm", ITERATION], sort=True)
    out = g[cols].mean().reset_index()
    out.insert(2, "n_seeds", g["run_dir"].nunique().to_numpy())
    return out


def signal_summary(support: pd.DataFrame) -> pd.DataFrame:
    """Per arm: ``has_signal``, ``degenerate`` (flat at every logged iteration of every seed),
    ``flat_until`` (per seed, ``;``-separated: the first logged iteration at which the signal was not
    flat, ``never`` when it stayed flat) and ``constant`` (the distribution equal to its first logged
    one at every iteration of every seed, within 1e-9: it never moved)."""
    rows = []
    for arm, g in support.groupby("arm", sort=True):
        has = bool(g["signal_flat"].notna().any())
        firsts = []
        for _, r in g.sort_values(ITERATION).groupby("run_dir", sort=True):
            moved = r.loc[r["signal_flat"] == 0, ITERATION]
            firsts.append(str(int(moved.iloc[0])) if len(moved) else "never")
        degenerate = has and all(f == "never" for f in firsts)
        constant = bool(g.groupby("run_dir")[["effective_support", "max_p_rel"]]
                        .agg(lambda v: float(v.max() - v.min())).max().max() <= 1e-9)
        rows.append({"arm": arm, "has_signal": has, "degenerate": degenerate,
                     "flat_until": ";".join(firsts) if has else "", "constant": constant})
    return pd.DataFrame(rows, columns=["arm", "has_signal", "degenerate", "flat_until", "constant"])
