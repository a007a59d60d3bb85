"""analysis.shift_interval: the difference-of-means interval is the permutation test inverted, so it
must agree with analysis.stats.permutation_pvalue at every shift."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from analysis.shift_interval import ratio_interval, shift_interval
from analysis.stats import censored_pvalue, permutation_pvalue

seeds = st.lists(st.floats(0.0, 1.0, allow_nan=False, width=32), min_size=3, max_size=5, unique=True)


@settings(max_examples=40, deadline=None)
@given(a=seeds, b=seeds, confidence=st.sampled_from([0.8, 0.9, 0.95]))
def test_the_interval_holds_exactly_the_shifts_the_test_keeps(a, b, confidence):
    low, high = shift_interval(a, b, confidence)
    alpha = 1.0 - confidence
    a = np.asarray(a)
    if not math.isfinite(low):
        assert not math.isfinite(high)
        for d in (-1e3, 0.0, 1e3):  # unbounded: no shift is rejected
            assert permutation_pvalue(a - d, b) >= alpha
        return
    assert low <= a.mean() - np.mean(b) <= high
    eps = 1e-7 * max(1.0, high - low)
    for inside in (low + eps, (low + high) / 2, high - eps):
        assert permutation_pvalue(a - inside, b) >= alpha
    for outside in (low - eps, high + eps):
        assert permutation_pvalue(a - outside, b) < alpha


def test_zero_is_outside_exactly_when_p_is_below_alpha():
    rng = np.random.default_rng(0)
    for _ in range(50):
        a, b = rng.normal(0.0, 1.0, 3) + rng.choice([0.0, 2.0]), rng.normal(0.0, 1.0, 5)
        low, high = shift_interval(a, b)
        assert (not low <= 0.0 <= high) == (permutation_pvalue(a, b) < 0.05)


def test_a_planted_shift_is_covered_and_seed_counts_bound_it():
    b = np.array([0.060, 0.066, 0.067, 0.072, 0.092])
    a = b[:3] + 0.010  # three seeds of a level 0.010 worse
    low, high = shift_interval(a, b)
    assert low < 0.010 < high
    # 3 v 5 seeds: 56 splits, m = 2, so the ends are the smallest and largest crossing.
    assert high - low < 0.1
    # 3 v 3: 20 splits, no p below 0.1 -> no 95% or 90% interval can be bounded.
    assert shift_interval(a, b[:3]) == (-math.inf, math.inf)
    assert shift_interval(a, b[:3], 0.9) == (-math.inf, math.inf)
    assert all(map(math.isfinite, shift_interval(a, b[:3], 0.8)))


def test_bad_input():
    assert all(map(math.isnan, shift_interval([], [1.0, 2.0])))
    assert all(map(math.isnan, shift_interval([math.nan], [1.0, 2.0])))
    with pytest.raises(ValueError, match="confidence"):
        shift_interval([1.0, 2.0], [3.0, 4.0], 1.0)


times = st.lists(st.sampled_from([300.0, 500.0, 700.0, 900.0, 1100.0, 1300.0, 1500.0]), min_size=3, max_size=5)


@settings(max_examples=40, deadline=None)
@given(base=times, arm=times)
def test_the_speedup_interval_holds_exactly_the_ratios_the_gehan_test_keeps(base, arm):
    # times of 1500 are runs that never got there (censored at their last evaluation)
    bt, at = np.asarray(base), np.asarray(arm)
    be, ae = bt < 1500.0, at < 1500.0
    low, high = ratio_interval(bt, be, at, ae)
    if math.isnan(low):
        assert not (be.any() or ae.any())
        return

    def kept(r):
        return censored_pvalue(at * r, ae, bt, be) >= 0.05

    eps = 1e-9
    if low > 0:
        assert kept(low) or kept(low * (1 + eps))
        assert not kept(low * (1 - eps))
    if math.isfinite(high):
        assert kept(high) or kept(high * (1 - eps))
        assert not kept(high * (1 + eps))
    if not low <= 1.0 <= high:  # outside the interval the test rejects no scaling at all
        assert censored_pvalue(at, ae, bt, be) < 0.05
    # every ratio the test keeps, on a fine grid, lies inside; the grid's kept ratios reach both bounds
    grid = np.geomspace(0.05, 20.0, 1500)
    on = grid[[kept(r) for r in grid]]
    assert ((on >= low * (1 - eps)) & (on <= high * (1 + eps))).all()
    if high > low * 1.02:  # a single kept ratio (every time tied) falls between grid points
        if low > 0.05:
            assert on.min() <= low * 1.01
        if high < 20.0:
            assert on.max() >= high / 1.01


def test_a_planted_speedup_is_covered_and_too_few_seeds_leave_it_open():
    base = np.array([1100.0, 1100.0, 1200.0, 1100.0, 1000.0])
    low, high = ratio_interval(base, np.ones(5, bool), np.array([1400.0, 1400.0, 1400.0]), np.ones(3, bool))
    assert low < 1100 / 1400 < high < 1.0  # every seed slower than every baseline seed: 1 is outside
    assert ratio_interval(base, np.ones(5, bool), base[:3] / 2, np.ones(3, bool))[0] < 2.0
    # two seeds against five: no p below 0.095, so no ratio is rejected
    assert ratio_interval(base, np.ones(5, bool), np.array([500.0, 600.0]), np.ones(2, bool)) == (0.0, math.inf)
    assert all(map(math.isnan, ratio_interval(base, np.zeros(5, bool), base[:3], np.zeros(3, bool))))
