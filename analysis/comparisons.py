"""Arms compared over seeds: against the lowest arm (post hoc) and against the baseline (with Holm's
adjustment), by a two-sided permutation test of the difference of per-seed means, the difference the
report prints beside each p (analysis.stats for the test, the smallest attainable p and Holm)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from analysis.stats import MIN_SEEDS_IQM, holm, iqm, permutation_pvalue, smallest_pvalue
from analysis.tables import ReportOptions

COMPARISON_COLUMNS = ["metric", "arm", "best", "point", "best_point", "mean", "best_mean", "difference", "p_value",
                      "smallest_p", "claim"]
"""Columns of comparisons.csv: ``point`` is the arm's point estimate (IQM from 4 seeds), ``difference``
the difference of the per-seed means (arm - best), the statistic the permutation test tests."""

BASELINE_COLUMNS = ["metric", "arm", "baseline", "point", "baseline_point", "mean", "baseline_mean", "difference",
                    "p_value", "p_holm", "smallest_p", "claim", "claim_holm"]
"""Columns of baseline_comparisons.csv: as COMPARISON_COLUMNS, plus Holm's adjusted p over the arms
tested against the baseline and whether the difference holds after it."""


def comparisons(per_run: dict[str, pd.DataFrame], metric: str, opts: ReportOptions) -> pd.DataFrame:
    """Every arm against the arm with the lowest point estimate of ``metric`` (lower is better; the
    best arm is picked after seeing the data, so these tests are post hoc and uncorrected):
    COMPARISON_COLUMNS, where ``claim`` means p < alpha (two-sided permutation test of the difference
    of the per-seed means) and the means differ."""
    if metric not in per_run:
        return pd.DataFrame(columns=COMPARISON_COLUMNS)
    values, points = _seed_values(per_run[metric])
    best = min(points, key=lambda a: (points[a], a))
    return pd.DataFrame(_against(metric, values, points, best, opts), columns=COMPARISON_COLUMNS)


def baseline_comparisons(per_run: dict[str, pd.DataFrame], metric: str, baseline: str | None,
                         opts: ReportOptions) -> pd.DataFrame:
    """Every arm against ``baseline`` (e.g. uniform sampling): BASELINE_COLUMNS, tested as in
    :func:`comparisons`, one test per arm; ``p_holm`` adjusts for their number (stats.holm).
    Empty without the baseline or the metric."""
    if metric not in per_run or baseline is None:
        return pd.DataFrame(columns=BASELINE_COLUMNS)
    values, points = _seed_values(per_run[metric])
    if baseline not in values:
        return pd.DataFrame(columns=BASELINE_COLUMNS)
    out = pd.DataFrame(_against(metric, values, points, baseline, opts),
                       columns=[c for c in BASELINE_COLUMNS if c not in ("p_holm", "claim_holm")])
    out.insert(9, "p_holm", holm(out["p_value"]) if len(out) else [])
    out["claim_holm"] = (out["difference"] != 0) & (out["p_holm"] < opts.alpha)
    return out[BASELINE_COLUMNS]


def _seed_values(df: pd.DataFrame) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """Per arm: the per-seed values (by seed) and their point (IQM from MIN_SEEDS_IQM seeds, else the mean)."""
    values = {a: g.sort_values("seed")["value"].to_numpy(dtype=float) for a, g in df.groupby("arm", sort=True)}
    return values, {a: (iqm(v) if len(v) >= MIN_SEEDS_IQM else float(np.mean(v))) for a, v in values.items()}


def _against(metric: str, values: dict[str, np.ndarray], points: dict[str, float], ref: str,
             opts: ReportOptions) -> list[tuple]:
    """Rows ``metric, arm, ref, point, ref point, mean, ref mean, difference of means, p, smallest p,
    claim``: the difference tested is the one reported."""
    rows = []
    for arm, v in values.items():
        if arm == ref:
            continue
        p = permutation_pvalue(v, values[ref], n_resamples=opts.n_permutations, seed=opts.bootstrap_seed)
        mean, ref_mean = float(np.mean(v)), float(np.mean(values[ref]))
        diff = mean - ref_mean
        smallest = smallest_pvalue(len(v), len(values[ref]), opts.n_permutations)
        rows.append((metric, arm, ref, points[arm], points[ref], mean, ref_mean, diff, p, smallest,
                     bool(diff != 0 and p < opts.alpha)))
    return rows
