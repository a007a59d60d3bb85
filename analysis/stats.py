"""Statistics over seeds: point estimates, intervals, permutation tests and censored medians.

The rules a reviewer would apply, in one place:

- Point estimate: the interquartile mean (IQM) from ``MIN_SEEDS_IQM`` = 4 seeds up, else the mean;
  every estimate carries its label (``point_label``).
- Interval: a bootstrap over seeds (``scipy.stats.bootstrap``; BCa where it is defined, else
  percentile; several samples are resampled independently, i.e. stratified by arm) only when every
  arm of the comparison has at least ``MIN_SEEDS_BOOTSTRAP`` = 5 seeds. With fewer seeds a bootstrap
  interval mostly shows which seeds were drawn (with 3 seeds the "95 %" percentile interval is
  about the range of the seeds and covers the mean about 75 % of the time), so the per-seed values
  and their range are shown instead, labelled "range of n seeds" (``ci_method="range"``).
- A difference between two arms gets a two-sided permutation-test p-value
  (``scipy.stats.permutation_test``), exact (every relabelling) when there are at most
  ``EXACT_PERMUTATIONS`` of them, else from ``n_resamples`` random ones. The test statistic is the
  difference of means, and the difference the report prints beside the p-value is that same
  difference of means (the IQM is the point estimate of one arm, not a test statistic: with 4 seeds
  an IQM difference cannot reach p < 0.05). With n and m seeds no exact test can give p below
  ``smallest_pvalue(n, m)`` = 2 / C(n + m, n) (0.029 for 4 v 4, 0.0079 for 5 v 5), printed beside
  every p. Several arms tested against one baseline get Holm's step-down adjustment (``holm``).
- Bootstrap intervals undercover at few seeds: ``bootstrap_coverage`` simulates the actual coverage
  of the nominal interval on normal data, which the report prints beside its intervals (a nominal
  95% BCa interval of the IQM covers about 89% at 5 seeds, 91% at 7 and 94% at 10).
- Times to an event (a bin mastered, a success threshold reached) are censored at a seed's last
  evaluation when the event never came. Their per-arm summary is the Kaplan-Meier median
  (``km_median``): defined only when more than half of the seeds had the event (earlier censoring
  handled as in Kaplan-Meier), else "not reached". Two arms' times are compared with a permutation
  test of Gehan's generalised Wilcoxon scores (``gehan_scores``), which treat a censored time as
  "later than anything observed before it".
- One policy's success over the R rollouts of one evaluation is a binomial proportion: its interval is
  Wilson's score interval (``analysis.binomial.wilson_interval``), over rollouts of that policy, never
  over seeds; it stays honest at 0 of R and R of R, where p ± z·SE collapses to a point.

All randomness comes from fixed seeds, so the same runs always give the same report.
"""

from __future__ import annotations

import functools
import itertools
import math
import warnings
from collections.abc import Callable

import numpy as np

DEFAULT_RESAMPLES = 2000
"""Bootstrap resamples used by the report."""


def _scipy_stats():
    """scipy.stats, imported on first use: it takes ~0.8 s on a small CPU, and a report of one seed per
    arm (most quick checks) draws no interval and runs no test."""
    from scipy import stats

    return stats


MIN_SEEDS_BOOTSTRAP = 5
"""Fewest seeds per arm for which bootstrap intervals are drawn (else the range of the seeds)."""

MIN_SEEDS_IQM = 4
"""Fewest seeds for which the point estimate is the IQM (else the mean)."""

EXACT_PERMUTATIONS = 200_000
"""Permutation tests enumerate every relabelling up to this many (7 vs 7 seeds: 3432; 10 vs 10, the
confirmatory test of sweeps/confirm_hybrid_dance1.yaml: 184,756, a few seconds and ~30 MB)."""

CI_METHODS = ("bootstrap_bca", "bootstrap_percentile", "range")
"""Values of the ``ci_method`` column."""


def iqm(values, axis: int | None = None):
    """Interquartile mean: the mean of the values left after dropping the lowest and highest quarter.

    ``floor(n / 4)`` values are dropped at each end (so for n < 4 it is the plain mean); NaNs are
    ignored and a slice with no finite value gives NaN. IQM(1..8) = mean(3, 4, 5, 6) = 4.5.
    With ``axis`` given, the IQM is taken along that axis of an array (columns may hold different
    numbers of NaNs, e.g. seeds that stopped early).
    """
    x = np.asarray(values, dtype=float)
    if axis is None:
        x = x.reshape(-1)
        axis = 0
    x = np.moveaxis(x, axis, 0)
    x = np.sort(x, axis=0)  # NaNs sort last
    n = np.sum(~np.isnan(x), axis=0)
    k = n // 4
    rank = np.arange(x.shape[0]).reshape((-1,) + (1,) * (x.ndim - 1))
    keep = (rank >= k) & (rank < n - k)
    kept = np.where(keep, x, 0.0)
    count = keep.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = kept.sum(axis=0) / count
    out = np.where(count > 0, out, np.nan)
    return float(out) if out.ndim == 0 else out


def point_label(n: int) -> str:
    """``"iqm"`` from MIN_SEEDS_IQM seeds up, else ``"mean"``: which statistic ``point`` takes."""
    return "iqm" if n >= MIN_SEEDS_IQM else "mean"


def point(values, axis: int | None = None):
    """The point estimate over seeds: IQM from MIN_SEEDS_IQM finite values up, else the mean."""
    x = np.asarray(values, dtype=float)
    if axis is None:
        x = x.reshape(-1)
        return iqm(x) if np.sum(~np.isnan(x)) >= MIN_SEEDS_IQM else _nanmean(x)
    n = np.sum(~np.isnan(x), axis=axis)
    return np.where(n >= MIN_SEEDS_IQM, iqm(x, axis=axis), _nanmean(x, axis=axis))


def _nanmean(x, axis=None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a slice with no value: NaN, not a warning
        return np.nanmean(x, axis=axis)


def bootstrap_interval(
    samples: tuple[np.ndarray, ...],
    statistic: Callable,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
) -> tuple[float, float, str]:
    """``(low, high, ci_method)`` of ``statistic(*samples, axis=-1)`` by ``scipy.stats.bootstrap``.

    Each sample is a 1-D array over seeds, resampled independently of the others. BCa is tried first;
    where it is undefined (degenerate data, e.g. every seed equal, or NaN acceleration) the
    percentile interval of the same resamples is used. ``statistic`` must be vectorised (reduce the
    last axis).
    """
    data = tuple(np.asarray(s, dtype=float) for s in samples)
    if any(len(s) < 2 for s in data):
        raise ValueError("bootstrap_interval: every sample needs at least 2 seeds")
    kw = dict(statistic=statistic, n_resamples=n_resamples, confidence_level=confidence, vectorized=True,
              rng=np.random.default_rng(seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # scipy warns when BCa is undefined; that case is handled below
        res = _scipy_stats().bootstrap(data, method="BCa", **kw)
        low, high = float(res.confidence_interval.low), float(res.confidence_interval.high)
        if math.isfinite(low) and math.isfinite(high) and low <= high:
            return low, high, "bootstrap_bca"
        kw["rng"] = np.random.default_rng(seed)
        res = _scipy_stats().bootstrap(data, method="percentile", **kw)
    return float(res.confidence_interval.low), float(res.confidence_interval.high), "bootstrap_percentile"


def seed_interval(
    values, bootstrap: bool, n_resamples: int = DEFAULT_RESAMPLES, confidence: float = 0.95, seed: int = 0
) -> tuple[float, float, float, str]:
    """``(point, low, high, ci_method)`` of one arm's per-seed values (NaNs dropped).

    ``bootstrap`` (the caller's decision: every arm of the comparison has MIN_SEEDS_BOOTSTRAP seeds)
    gives a bootstrap interval of the point statistic; otherwise the interval is the range of the
    seeds (``"range"``). No value: all NaN.
    """
    x = np.asarray(values, dtype=float).reshape(-1, 1)
    if np.isnan(x).all():
        return math.nan, math.nan, math.nan, ""
    p, low, high, method = curve_intervals(x, bootstrap, n_resamples, confidence, seed)
    return float(p[0]), float(low[0]), float(high[0]), method[0]


def curve_intervals(
    matrix: np.ndarray, bootstrap: bool, n_resamples: int = DEFAULT_RESAMPLES, confidence: float = 0.95,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    """``seed_interval`` of every column of ``matrix`` [seeds, points] (NaN: that seed has no value
    there), as arrays ``(point, low, high, ci_method)``. Columns with the same seeds present are
    bootstrapped together (scipy evaluates them as one vectorised batch)."""
    m = np.asarray(matrix, dtype=float)
    cols = m.shape[1]
    pt = np.asarray(point(m, axis=0), dtype=float).reshape(cols)
    low, high = np.full(cols, np.nan), np.full(cols, np.nan)
    method = [""] * cols
    present = ~np.isnan(m)
    count = present.sum(axis=0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        lo_r, hi_r = np.nanmin(m, axis=0), np.nanmax(m, axis=0)
    for j in np.flatnonzero(count > 0):
        if not bootstrap or count[j] < 2 or lo_r[j] == hi_r[j]:
            low[j], high[j] = (lo_r[j], hi_r[j]) if not bootstrap or count[j] < 2 else (pt[j], pt[j])
            method[j] = "range" if not bootstrap or count[j] < 2 else "bootstrap_percentile"
    todo = [j for j in range(cols) if not method[j] and count[j] > 0]
    patterns: dict[bytes, list[int]] = {}
    for col in todo:
        patterns.setdefault(present[:, col].tobytes(), []).append(col)
    for cols_j in patterns.values():
        sub = m[present[:, cols_j[0]]][:, cols_j]
        n = sub.shape[0]
        stat = (lambda a, axis=-1: iqm(a, axis=axis)) if n >= MIN_SEEDS_IQM else np.mean
        for kind in ("BCa", "percentile"):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = _scipy_stats().bootstrap((sub,), stat, n_resamples=n_resamples, confidence_level=confidence,
                                    vectorized=True, axis=0, method=kind, rng=np.random.default_rng(seed))
            lo, hi = np.atleast_1d(res.confidence_interval.low), np.atleast_1d(res.confidence_interval.high)
            for k, col in enumerate(cols_j):
                if not method[col] and np.isfinite(lo[k]) and np.isfinite(hi[k]) and lo[k] <= hi[k]:
                    low[col], high[col] = lo[k], hi[k]
                    method[col] = "bootstrap_bca" if kind == "BCa" else "bootstrap_percentile"
    return pt, low, high, method


def permutation_pvalue(a, b, statistic: Callable | None = None, n_resamples: int = 9999, seed: int = 0) -> float:
    """Two-sided permutation-test p-value of ``statistic(a, b)`` (default: difference of means).

    Exact (every split of the pooled values into groups of the two sizes) when there are at most
    EXACT_PERMUTATIONS splits, else from ``n_resamples`` random splits. NaN with fewer than one value
    per group. With 3 vs 3 seeds there are 20 splits, so no p-value can be below 0.1.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a, b = a[~np.isnan(a)], b[~np.isnan(b)]
    if not len(a) or not len(b):
        return math.nan
    if np.all(np.concatenate([a, b]) == a[0]):
        return 1.0
    if statistic is None:
        def statistic(x, y, axis=-1):
            return np.mean(x, axis=axis) - np.mean(y, axis=axis)
    splits = math.comb(len(a) + len(b), len(a))
    if min(len(a), len(b)) < 2:
        # scipy refuses a group of one value; the exact test is still defined (few splits).
        return _exact_permutation_pvalue(a, b, statistic)
    if splits <= EXACT_PERMUTATIONS:
        return _enumerated_pvalue(a, b, statistic)
    res = _scipy_stats().permutation_test(
        (a, b), statistic, permutation_type="independent", alternative="two-sided", vectorized=True,
        n_resamples=n_resamples, rng=np.random.default_rng(seed),
    )
    return float(min(1.0, res.pvalue))


@functools.lru_cache(maxsize=4)
def all_splits(n_a: int, n_b: int) -> np.ndarray:
    """Every split of n_a + n_b pooled positions into groups of n_a and n_b, one row each: the first
    group's positions ascending, then the rest ascending (the order scipy enumerates them in, so the
    null distribution is the same numbers bit for bit). 10 v 10: 184,756 x 20 int8, 3.7 MB."""
    n = n_a + n_b
    first = np.fromiter(itertools.chain.from_iterable(itertools.combinations(range(n), n_a)), dtype=np.int8)
    first = first.reshape(-1, n_a)
    rest = np.ones((len(first), n), dtype=bool)
    rest[np.arange(len(first))[:, None], first] = False
    out = np.concatenate([first, np.nonzero(rest)[1].astype(np.int8).reshape(len(first), n_b)], axis=1)
    out.setflags(write=False)
    return out


def _enumerated_pvalue(a: np.ndarray, b: np.ndarray, statistic: Callable) -> float:
    """scipy.stats.permutation_test's exact two-sided p-value (every split, values within 100 float
    eps of the observed statistic counted as equal to it), from one vectorized pass over a cached
    table of the splits: scipy builds its splits in Python for every call (about a second for 10 v
    10), which a report of many comparisons repeats hundreds of times."""
    pooled = np.concatenate([a, b])[all_splits(len(a), len(b))]
    null = np.asarray(statistic(pooled[:, :len(a)], pooled[:, len(a):], axis=-1), dtype=float)
    observed = float(statistic(a, b, axis=-1))
    gamma = abs(np.finfo(float).eps * 100 * observed)
    less = np.count_nonzero(null <= observed + gamma) / len(null)
    greater = np.count_nonzero(null >= observed - gamma) / len(null)
    return float(min(1.0, 2.0 * min(less, greater)))


def _exact_permutation_pvalue(a: np.ndarray, b: np.ndarray, statistic: Callable) -> float:
    """Two-sided exact permutation p-value over every split, as scipy defines it:
    2 x min(P(T >= t), P(T <= t)), capped at 1 (for groups too small for scipy)."""
    pooled = np.concatenate([a, b])
    idx = np.arange(len(pooled))
    null_list = []
    for chosen in itertools.combinations(idx, len(a)):
        mask = np.zeros(len(pooled), dtype=bool)
        mask[list(chosen)] = True
        null_list.append(float(statistic(pooled[mask], pooled[~mask], axis=-1)))
    null = np.asarray(null_list)
    observed = float(statistic(a, b, axis=-1))
    tol = 1e-12 * max(1.0, abs(observed))
    greater = float(np.mean(null >= observed - tol))
    less = float(np.mean(null <= observed + tol))
    return float(min(1.0, 2.0 * min(greater, less)))


def smallest_pvalue(n_a: int, n_b: int, n_resamples: int = 9999) -> float:
    """The smallest two-sided p-value a permutation test of two groups of ``n_a`` and ``n_b`` values
    can give (as permutation_pvalue computes it): 2 / C(n_a + n_b, n_a) when every split is
    enumerated (4 v 4: 2/70 = 0.029; 5 v 5: 2/252 = 0.0079), 2 / (n_resamples + 1) from random
    splits; capped at 1, NaN for an empty group. Ties among the values can only raise it."""
    if n_a < 1 or n_b < 1:
        return math.nan
    splits = math.comb(n_a + n_b, n_a)
    if splits > EXACT_PERMUTATIONS and min(n_a, n_b) >= 2:
        return min(1.0, 2.0 / (n_resamples + 1))
    return min(1.0, 2.0 / splits)


def holm(pvalues) -> np.ndarray:
    """Holm's step-down adjusted p-values of a family of tests (same order as given; NaNs are left
    out of the family and stay NaN). With m tests sorted p_(1) <= ... <= p_(m), the adjusted
    p_(i) = max over j <= i of min(1, (m - j + 1) p_(j)); rejecting where it is below alpha controls
    the family-wise error rate at alpha. Holm([0.01, 0.04, 0.03]) = [0.03, 0.06, 0.06]."""
    p = np.asarray(pvalues, dtype=float).reshape(-1)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(~np.isnan(p))
    m = len(ok)
    if not m:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    adjusted = np.minimum(1.0, (m - np.arange(m)) * p[order])
    out[order] = np.maximum.accumulate(adjusted)
    return out


def bootstrap_coverage(n_seeds: int, n_draws: int = 1000, n_resamples: int = DEFAULT_RESAMPLES,
                       confidence: float = 0.95, seed: int = 0) -> float:
    """The fraction of ``n_draws`` standard-normal samples of ``n_seeds`` values whose bootstrap
    interval of the report's point statistic (seed_interval: IQM from MIN_SEEDS_IQM seeds, BCa where
    defined) contains the true centre, 0: the actual coverage of the nominal ``confidence``."""
    rng = np.random.default_rng(seed)
    hits = 0
    for i in range(n_draws):
        _, low, high, _ = seed_interval(rng.normal(size=n_seeds), True, n_resamples, confidence, seed + i)
        hits += bool(low <= 0.0 <= high)
    return hits / n_draws


def km_median(time, event, axis: int = -1):
    """Kaplan-Meier median of times with right-censoring, along ``axis``.

    ``time`` is the event time where ``event`` is true, else the censoring time (the event had not
    happened by then). The survival curve S drops by the fraction of those still at risk at each
    event (events before censorings at equal times). The median is the first time where S < 0.5;
    where S stays exactly 0.5 from an event on, the midpoint between that event and the next one
    (which gives the ordinary median for uncensored data). NaN when S never gets below 0.5: fewer
    than half of the seeds had the event ("not reached").
    """
    t = np.moveaxis(np.asarray(time, dtype=float), axis, -1)
    e = np.moveaxis(np.asarray(event, dtype=bool), axis, -1)
    n = t.shape[-1]
    if n == 0:
        return np.full(t.shape[:-1], np.nan) if t.ndim > 1 else math.nan
    order = np.argsort(np.where(e, 0, 1), axis=-1, kind="stable")  # events first ...
    t, e = np.take_along_axis(t, order, -1), np.take_along_axis(e, order, -1)
    order = np.argsort(t, axis=-1, kind="stable")  # ... then by time, keeping that order at ties
    t, e = np.take_along_axis(t, order, -1), np.take_along_axis(e, order, -1)
    at_risk = n - np.arange(n)
    surv = np.cumprod(np.where(e, 1.0 - 1.0 / at_risk, 1.0), axis=-1)
    eps = 1e-9
    le = surv <= 0.5 + eps
    lt = surv < 0.5 - eps
    j = np.argmax(le, axis=-1)[..., None]
    k = np.argmax(lt, axis=-1)[..., None]
    tj = np.take_along_axis(t, j, -1)[..., 0]
    tk = np.take_along_axis(t, k, -1)[..., 0]
    half = np.abs(np.take_along_axis(surv, j, -1)[..., 0] - 0.5) <= eps
    out = np.where(half, np.where(lt.any(-1), 0.5 * (tj + tk), np.nan), tj)
    out = np.where(le.any(-1), out, np.nan)
    return float(out) if out.ndim == 0 else out


def gehan_scores(time, event) -> np.ndarray:
    """Gehan's score of each subject in a pooled sample, as lateness: (# surely earlier than it) -
    (# surely later than it).

    ``i`` is surely earlier than ``j`` when ``i`` had its event and ``t_i < t_j``, or ``t_i == t_j``
    with ``j`` censored. Summed over one group these give Gehan's generalised Wilcoxon statistic; a
    permutation test of the groups' mean scores compares two sets of censored times (lower: sooner).
    For uncensored data it is the Wilcoxon rank-sum test.
    """
    t = np.asarray(time, dtype=float)
    e = np.asarray(event, dtype=bool)
    ti, tj = t[:, None], t[None, :]
    earlier = e[:, None] & ((ti < tj) | ((ti == tj) & ~e[None, :]))  # earlier[i, j]: i surely before j
    return earlier.sum(axis=0) - earlier.sum(axis=1)


def censored_pvalue(time_a, event_a, time_b, event_b, n_resamples: int = 9999, seed: int = 0) -> float:
    """Two-sided permutation p-value for a difference between two arms' censored times (Gehan scores)."""
    time = np.concatenate([np.asarray(time_a, float), np.asarray(time_b, float)])
    event = np.concatenate([np.asarray(event_a, bool), np.asarray(event_b, bool)])
    if not event.any():
        return math.nan  # no seed of either arm had the event: nothing to compare
    scores = gehan_scores(time, event).astype(float)
    na = len(np.asarray(time_a))
    return permutation_pvalue(scores[:na], scores[na:], n_resamples=n_resamples, seed=seed)


def restricted_km_median(time, event, axis: int = -1):
    """km_median, with "not reached" replaced by the largest follow-up time (a lower bound on the
    median): finite, so bootstrap resamples of an arm whose median is sometimes not reached still
    give a number. Only used inside resamples; the reported status comes from km_median itself."""
    med = km_median(time, event, axis=axis)
    follow = np.max(np.moveaxis(np.asarray(time, dtype=float), axis, -1), axis=-1)
    return np.where(np.isnan(med), follow, med) if np.ndim(med) else (follow if math.isnan(med) else med)
