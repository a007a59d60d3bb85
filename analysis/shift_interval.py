"""Confidence intervals from the report's own permutation tests, inverted: for a difference of means over
seeds (shift_interval) and for a speedup of censored times (ratio_interval).

The report tests "level a differs from reference b" with the two-sided exact permutation test of the
difference of means (analysis.stats.permutation_pvalue). The shifts d for which that same test, applied
to ``a - d`` against ``b``, does not reject at level alpha form a 1 - alpha confidence interval for the
difference (a location-shift model: the seeds of a are those of b moved by d). It needs no normality and
no bootstrap, is exact for few seeds, and agrees with the p-value by construction: the interval leaves
out 0 exactly where p < alpha.

Shifting a by d moves the observed statistic as ``D - d`` and the statistic of a split holding k of a's
n_a values in the first group as ``T - c d`` with ``c = k / n_a - (n_a - k) / n_b < 1`` (only the
observed split has c = 1). So each other split crosses the observed value once, at ``(D - T) / (1 - c)``,
and the test's p at d depends only on how many crossings lie below d: the interval runs between order
statistics of the crossings. Too few splits for alpha (3 v 3 seeds: 20, no p below 0.1) leave it
unbounded, which is the honest answer.
"""

from __future__ import annotations

import math

import numpy as np

from analysis.stats import EXACT_PERMUTATIONS, all_splits, censored_pvalue


def shift_interval(a, b, confidence: float = 0.95) -> tuple[float, float]:
    """(low, high) confidence interval for mean(a) - mean(b) by inverting the exact two-sided permutation
    test of the difference of means (module docstring); -inf / inf where the seeds cannot bound it, NaN
    with an empty group or more splits than EXACT_PERMUTATIONS. NaNs in a or b are dropped."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a, b = a[~np.isnan(a)], b[~np.isnan(b)]
    n_a, n_b = len(a), len(b)
    if not n_a or not n_b or math.comb(n_a + n_b, n_a) > EXACT_PERMUTATIONS:
        return math.nan, math.nan
    splits = all_splits(n_a, n_b)
    first = splits[:, :n_a]
    k = np.count_nonzero(first < n_a, axis=1)  # values of a in the first group (positions 0..n_a-1)
    pooled = np.concatenate([a, b])[splits]
    stat = pooled[:, :n_a].mean(axis=1) - pooled[:, n_a:].mean(axis=1)
    observed = float(a.mean() - b.mean())
    c = k / n_a - (n_a - k) / n_b
    others = k < n_a  # every split but the observed one
    crossings = np.sort((observed - stat[others]) / (1.0 - c[others]))
    n = len(splits)
    # p(d) = 2 min(1 + r, n - r) / n with r = crossings below d; p >= alpha needs r in [m - 1, n - m].
    m = math.ceil((1.0 - confidence) * n / 2.0)
    if m < 2:  # even the most extreme split has p >= alpha: no shift is ever rejected
        return -math.inf, math.inf
    return float(crossings[m - 2]), float(crossings[n - m])


def ratio_interval(base_time, base_event, arm_time, arm_event, confidence: float = 0.95, n_permutations: int = 9999,
                   seed: int = 0) -> tuple[float, float]:
    """(low, high) confidence interval for the speedup of ``arm`` over ``base`` (base median / arm median, as
    analysis.metrics.speedup) from the Gehan permutation test of censored times (stats.censored_pvalue)
    inverted under a scale model: the speedups r for which the arm's times (censored ones too) multiplied by
    r do not differ from the baseline's at level 1 - confidence. Scaling one group changes only how its
    times order against the other's, at the ratios base time / arm time, so p is tested at each such ratio
    and between them; the interval spans the kept ones (0 or inf where the seeds cannot bound it; NaN
    without an event or a time)."""
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    bt, be = np.asarray(base_time, float), np.asarray(base_event, bool)
    at, ae = np.asarray(arm_time, float), np.asarray(arm_event, bool)
    if not len(bt) or not len(at) or not (be.any() or ae.any()) or (at <= 0).any():
        return math.nan, math.nan
    alpha = 1.0 - confidence
    crit = np.unique((bt[None, :] / at[:, None]).ravel())
    crit = crit[crit > 0]
    # one point per piece: below the first ratio, each ratio, between neighbours, above the last
    inner = np.sqrt(crit[:-1] * crit[1:])
    points = np.concatenate([[crit[0] / 2], crit, inner, [crit[-1] * 2]])
    kind = np.concatenate([[0], np.ones(len(crit)), np.full(len(inner), 2), [3]])
    order = np.argsort(points, kind="stable")
    points, kind = points[order], kind[order]
    kept = np.array([censored_pvalue(at * r, ae, bt, be, n_resamples=n_permutations, seed=seed) >= alpha
                     for r in points])
    if not kept.any():
        return math.nan, math.nan
    i, j = int(np.argmax(kept)), len(kept) - 1 - int(np.argmax(kept[::-1]))
    # an open piece's bound is the ratio at its edge; the pieces at either end reach 0 and inf
    low = 0.0 if kind[i] == 0 else float(points[i]) if kind[i] == 1 else float(points[i - 1])
    high = math.inf if kind[j] == 3 else float(points[j]) if kind[j] == 1 else float(points[j + 1])
    return low, high


__all__ = ["ratio_interval", "shift_interval"]
