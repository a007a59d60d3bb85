"""Equivalence tests for the pre-registered studies of issue 76: "does not matter" claimed only when a
difference is shown to lie within a margin set before the runs (two one-sided tests, TOST), never from
a test that failed to reject."""

from __future__ import annotations

import math

import numpy as np

from analysis.stats import EXACT_PERMUTATIONS, all_splits


def equivalence_pvalue(a, b, margin: float) -> tuple[float, float]:
    """Two one-sided exact permutation tests (TOST) that the difference of means of ``a`` and ``b`` lies
    within (-margin, +margin): (p_low, p_high), the p-values of H0 "mean(a) - mean(b) <= -margin" and
    of H0 "mean(a) - mean(b) >= +margin". Each shifts ``b`` by the margin and enumerates every split of
    the pooled values (at most EXACT_PERMUTATIONS): p_low is the share of splits whose difference is at
    least the observed one; p_high, at most. Equivalence at level alpha is max(p_low, p_high) < alpha,
    the interval (1 - 2 alpha) of the difference lying inside the margin."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if margin <= 0 or not (len(a) and len(b)) or np.isnan(np.concatenate([a, b])).any():
        raise ValueError("equivalence_pvalue: needs a positive margin and values in both groups, none NaN")
    if math.comb(len(a) + len(b), len(a)) > EXACT_PERMUTATIONS:
        raise ValueError(f"equivalence_pvalue: more than {EXACT_PERMUTATIONS} splits; use fewer values")

    def one_sided(shifted: np.ndarray, greater: bool) -> float:
        pooled = np.concatenate([a, shifted])[all_splits(len(a), len(b))]
        null = pooled[:, :len(a)].mean(axis=1) - pooled[:, len(a):].mean(axis=1)
        observed = a.mean() - shifted.mean()
        tol = abs(np.finfo(float).eps * 100 * observed)
        return float(np.mean(null >= observed - tol) if greater else np.mean(null <= observed + tol))

    return one_sided(b - margin, greater=True), one_sided(b + margin, greater=False)
