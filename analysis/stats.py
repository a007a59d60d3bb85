"""Statistics over seeds: interquartile mean and percentile bootstrap intervals.

Seeds are the unit of resampling. With several groups (arms) each group is resampled on its own
(a stratified bootstrap), so a ratio between arms keeps each arm's seed count. All randomness comes
from ``numpy.random.default_rng(seed)``: the same inputs give the same interval, which keeps reports
reproducible.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
import pandas as pd

DEFAULT_RESAMPLES = 2000
"""Bootstrap resamples used by the report; enough for stable 95 % percentile bounds."""


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


def _iqm_seeds(x):
    return iqm(x, axis=0)


def bootstrap_ci(
    *samples,
    statistic: Callable = _iqm_seeds,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
):
    """Point estimate and percentile bootstrap interval of ``statistic(*samples)``.

    Each sample is an array whose first axis is seeds (``[n_seeds]`` or ``[n_seeds, n_points]``);
    every resample draws seeds with replacement from each sample independently (stratified by
    sample). ``statistic`` must reduce axis 0 (the seeds) and act elementwise on any further axes,
    e.g. ``lambda x: iqm(x, axis=0)`` (the default) or ``lambda b, a: iqm(b, axis=0) / iqm(a, axis=0)``
    for a ratio of two arms: resamples are evaluated in batches stacked on axis 1, which makes
    thousands of resamples cost a few array operations. Returns ``(point, low, high)``, floats or
    arrays of the statistic's shape; resamples that give NaN (e.g. no seed with a value) are ignored.
    """
    if not samples:
        raise ValueError("bootstrap_ci needs at least one sample")
    if not 0.0 < confidence < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    arrays = [np.asarray(s, dtype=float) for s in samples]
    for a in arrays:
        if a.ndim == 0 or a.shape[0] == 0:
            raise ValueError("bootstrap_ci: every sample needs at least one seed")
    point = np.asarray(statistic(*arrays), dtype=float)
    rng = np.random.default_rng(seed)
    indices = [rng.integers(0, a.shape[0], size=(a.shape[0], n_resamples)) for a in arrays]
    batch = max(1, int(4_000_000 // max(a.size for a in arrays)))
    draws = np.concatenate([
        np.asarray(statistic(*(a[idx[:, i:i + batch]] for a, idx in zip(arrays, indices, strict=True))), float)
        for i in range(0, n_resamples, batch)
    ])
    alpha = (1.0 - confidence) / 2.0
    with warnings.catch_warnings():
        # A point where every resample is NaN gets a NaN interval; numpy warns about that.
        warnings.simplefilter("ignore", RuntimeWarning)
        low, high = np.nanquantile(draws, [alpha, 1.0 - alpha], axis=0)
    if point.ndim == 0:
        return float(point), float(low), float(high)
    return point, np.asarray(low), np.asarray(high)


def aggregate_over_seeds(
    df: pd.DataFrame,
    value: str,
    by: list[str],
    x: str,
    n_resamples: int = DEFAULT_RESAMPLES,
    confidence: float = 0.95,
    seed: int = 0,
    unit: str = "seed",
) -> pd.DataFrame:
    """IQM over seeds with a bootstrap interval, for each group in ``by`` and each value of ``x``.

    ``df`` is tidy with columns ``unit`` (the resampled unit: ``seed``, or ``run_dir`` so that two
    runs that share a seed stay two samples), ``x``, ``value`` and ``by``. Within a group the units
    are resampled together across all ``x`` (a seed's whole curve moves as one). Returns columns
    ``by + [x, "iqm", "mean", "ci_low", "ci_high", "n_seeds"]``; ``n_seeds`` counts the units with a
    value at that ``x`` (fewer where a run stopped early).
    """
    rows = []
    for key, group in df.groupby(by, sort=True):
        key = key if isinstance(key, tuple) else (key,)
        group = group.dropna(subset=[value])
        if group.empty:  # e.g. no episode finished yet in a very short run: no curve, not an error
            continue
        wide = group.pivot_table(index=unit, columns=x, values=value, aggfunc="mean")
        matrix = wide.to_numpy(dtype=float)
        point, low, high = bootstrap_ci(
            matrix,
            n_resamples=n_resamples,
            confidence=confidence,
            seed=seed,
        )
        point, low, high = np.atleast_1d(point), np.atleast_1d(low), np.atleast_1d(high)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # an x where no seed has a value
            mean = np.nanmean(matrix, axis=0)
        n = np.sum(~np.isnan(matrix), axis=0)
        for j, xv in enumerate(wide.columns):
            rows.append((*key, xv, point[j], mean[j], low[j], high[j], int(n[j])))
    return pd.DataFrame(rows, columns=[*by, x, "iqm", "mean", "ci_low", "ci_high", "n_seeds"])


def intervals_overlap(a_low: float, a_high: float, b_low: float, b_high: float) -> bool:
    """Whether two intervals share a point (the report's "within noise" test for two arms)."""
    return bool(max(a_low, b_low) <= min(a_high, b_high))
