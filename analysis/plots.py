"""One function per figure: ``plot_x(df, ax=None, ...) -> matplotlib Figure``.

Figures are built on ``matplotlib.figure.Figure`` directly (no pyplot state, rendered by Agg when
saved), so importing this module never changes the caller's backend. Inputs are the tidy frames of
``analysis.report``; arms keep one colour across figures when ``colors`` is passed.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

FIGSIZE = (6.0, 3.6)
"""Default size of a single-panel figure in inches (about 600x360 px at the report's 100 dpi)."""

SENSITIVITY_LABELS = {
    "final_failure": "final overall failure",
    "mastery_median": "median mastery iteration",
    "time_iteration": "iterations to success threshold",
}
"""Axis labels of the arm-summary metrics drawn by plot_sensitivity."""


def arm_colors(arms) -> dict[str, tuple]:
    """A stable colour per arm (tab10 in sorted order; cycles past 10 arms)."""
    from matplotlib import colormaps

    cmap = colormaps["tab10"]
    return {arm: cmap(i % 10) for i, arm in enumerate(sorted(set(arms)))}


def _axes(ax, figsize=FIGSIZE):
    if ax is not None:
        return ax.figure, ax
    fig = Figure(figsize=figsize, layout="constrained")
    return fig, fig.add_subplot()


def _mark_segments(ax, bins: pd.DataFrame | None, axis: str = "x") -> None:
    """Label the bin axis with segment names: boundaries as thin lines, names on the opposite side."""
    (ax.xaxis if axis == "x" else ax.yaxis).set_major_locator(MaxNLocator(integer=True))
    if bins is None or not len(bins) or not bins["segment"].astype(bool).any():
        return
    bins = bins.sort_values("bin").reset_index(drop=True)
    change = bins["segment"].ne(bins["segment"].shift()).cumsum()
    spans = bins.groupby(change).agg(name=("segment", "first"), first=("bin", "first"), last=("bin", "last"))
    line = ax.axvline if axis == "x" else ax.axhline
    for first in spans["first"].iloc[1:]:
        line(first - 0.5, color="0.3", lw=0.6, ls=":")
    centres = ((spans["first"] + spans["last"]) / 2.0).to_list()
    twin = ax.secondary_xaxis("top") if axis == "x" else ax.secondary_yaxis("right")
    # Rotated: segments are often only a few bins wide, and horizontal names would overlap.
    rotation = 90 if axis == "x" else 0
    twin.set_ticks(centres, labels=spans["name"].to_list(), fontsize=6, rotation=rotation)
    twin.tick_params(length=0)


def _edges(centres: np.ndarray) -> np.ndarray:
    """Cell edges halfway between sorted centres, extended by half a step at both ends."""
    if len(centres) == 1:
        return np.array([centres[0] - 0.5, centres[0] + 0.5])
    mid = (centres[1:] + centres[:-1]) / 2.0
    return np.r_[2 * centres[0] - mid[0], mid, 2 * centres[-1] - mid[-1]]


def plot_learning_curve(
    curves: pd.DataFrame, ylabel: str = "", ax=None, colors: dict | None = None, title: str | None = None
) -> Figure:
    """IQM over seeds against iteration, one line per arm, with its 95 % bootstrap band.

    ``curves`` has ``arm, iteration, iqm, ci_low, ci_high`` (stats.aggregate_over_seeds for one metric).
    """
    fig, ax = _axes(ax)
    colors = colors or arm_colors(curves["arm"])
    for arm, c in curves.groupby("arm", sort=True):
        c = c.sort_values("iteration")
        x = c["iteration"].to_numpy(dtype=float)  # concatenated tables can arrive as object columns
        ax.plot(x, c["iqm"].to_numpy(dtype=float), color=colors[arm], lw=1.4, label=arm)
        ax.fill_between(x, c["ci_low"].to_numpy(dtype=float), c["ci_high"].to_numpy(dtype=float),
                        color=colors[arm], alpha=0.2, lw=0)
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return fig


def plot_bin_heatmap(
    df: pd.DataFrame,
    value: str = "failure_rate",
    ax=None,
    bins: pd.DataFrame | None = None,
    vmin: float | None = 0.0,
    vmax: float | None = None,
    title: str | None = None,
    cmap: str = "magma_r",
    colorbar: bool = True,
    max_rows: int = 400,
) -> Figure:
    """Heatmap of ``value`` over iterations (rows, increasing upwards) x bins (columns) for one arm.

    ``df`` has ``iteration, bin, value`` (e.g. the seed-mean failure of one arm); ``bins`` (from
    metrics.bin_table) adds the segment names on top. Each cell spans from halfway to the previous
    iteration to halfway to the next, so uneven evaluation spacing is drawn to scale.
    """
    fig, ax = _axes(ax)
    grid = df.pivot_table(index="iteration", columns="bin", values=value, aggfunc="mean").sort_index()
    if len(grid) > max_rows:  # more rows than pixels: keep every k-th iteration (and the last)
        keep = np.unique(np.r_[np.arange(0, len(grid), int(np.ceil(len(grid) / max_rows))), len(grid) - 1])
        grid = grid.iloc[keep]
    image = ax.pcolormesh(_edges(grid.columns.to_numpy(float)), _edges(grid.index.to_numpy(float)),
                          grid.to_numpy(dtype=float), cmap=cmap, vmin=vmin, vmax=vmax, shading="flat")
    ax.set_xlabel("bin")
    ax.set_ylabel("iteration")
    if title:
        ax.set_title(title, fontsize=8)
    _mark_segments(ax, bins)
    if colorbar:
        fig.colorbar(image, ax=ax, label=value.replace("_", " "), shrink=0.9)
    return fig


def plot_bin_heatmaps(
    df: pd.DataFrame, value: str = "failure_rate", bins: pd.DataFrame | None = None,
    vmax: float | None = None, cmap: str = "magma_r",
) -> Figure:
    """plot_bin_heatmap for every arm in ``df`` side by side, on one shared colour scale."""
    arms = sorted(df["arm"].unique())
    vmax = float(df[value].max()) if vmax is None else vmax
    fig = Figure(figsize=(min(3.2 * len(arms), 12.0) + 0.8, 3.4), layout="constrained")
    axes = fig.subplots(1, len(arms), squeeze=False, sharey=True)[0]
    image = None
    for ax, arm in zip(axes, arms, strict=True):
        plot_bin_heatmap(df[df["arm"] == arm], value, ax=ax, bins=bins, vmax=vmax, title=arm, cmap=cmap,
                         colorbar=False)
        image = ax.collections[-1]
    for ax in axes[1:]:
        ax.set_ylabel("")
    fig.colorbar(image, ax=list(axes), label=value.replace("_", " "), shrink=0.9)
    return fig


def plot_final_bin_failure(
    final: pd.DataFrame, ax=None, bins: pd.DataFrame | None = None, colors: dict | None = None
) -> Figure:
    """Final evaluated failure per bin: IQM over seeds with 95 % bootstrap bands, one line per arm.

    ``final`` has ``arm, bin, iqm, ci_low, ci_high``.
    """
    fig, ax = _axes(ax)
    colors = colors or arm_colors(final["arm"])
    for arm, f in final.groupby("arm", sort=True):
        f = f.sort_values("bin")
        ax.plot(f["bin"], f["iqm"], marker="o", ms=3, color=colors[arm], lw=1.2, label=arm)
        ax.fill_between(f["bin"], f["ci_low"], f["ci_high"], color=colors[arm], alpha=0.2, lw=0)
    ax.set_xlabel("bin")
    ax.set_ylabel("final failure rate")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    _mark_segments(ax, bins)
    return fig


def plot_mastery(
    mastery: pd.DataFrame, ax=None, bins: pd.DataFrame | None = None, colors: dict | None = None,
    threshold: float | None = None,
) -> Figure:
    """Mastery iteration per bin, one line per arm; bins never mastered are drawn as x at the arm's
    last evaluation (a lower bound). ``mastery`` is metrics.mastery_iterations(..., by=["arm"])."""
    fig, ax = _axes(ax)
    colors = colors or arm_colors(mastery["arm"])
    for arm, m in mastery.groupby("arm", sort=True):
        m = m.sort_values("bin")
        ax.plot(m["bin"], m["mastery_iteration"], marker="o", ms=3, color=colors[arm], lw=1.2, label=arm)
        never = m[~m["mastered"]]
        if len(never):
            ax.scatter(never["bin"], never["last_iteration"], marker="x", color=colors[arm], s=30)
    ax.set_xlabel("bin")
    ax.set_ylabel("mastery iteration")
    if threshold is not None:
        ax.set_title(f"first evaluation with failure < {threshold:g} (x: never, at last evaluation)", fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    _mark_segments(ax, bins)
    return fig


def plot_speedup(speedup: pd.DataFrame, ax=None, colors: dict | None = None) -> Figure:
    """Speedup against the baseline per arm and measure, with 95 % bootstrap intervals; 1 = no change.

    ``speedup`` has ``arm, measure, ratio, ci_low, ci_high`` (NaN intervals are drawn without bars).
    """
    fig, ax = _axes(ax)
    colors = colors or arm_colors(speedup["arm"])
    measures = list(dict.fromkeys(speedup["measure"]))
    arms = sorted(speedup["arm"].unique())
    width = 0.8 / max(len(arms), 1)
    for i, arm in enumerate(arms):
        s = speedup[speedup["arm"] == arm].set_index("measure").reindex(measures)
        x = np.arange(len(measures)) + (i - (len(arms) - 1) / 2) * width
        ratio = s["ratio"].to_numpy(dtype=float)
        err = np.vstack([ratio - s["ci_low"].to_numpy(dtype=float), s["ci_high"].to_numpy(dtype=float) - ratio])
        ax.bar(x, np.nan_to_num(ratio, posinf=0.0), width, color=colors[arm], label=arm)
        ax.errorbar(x, ratio, yerr=np.nan_to_num(np.abs(err), posinf=0.0), fmt="none", ecolor="0.2", capsize=3, lw=1)
    ax.axhline(1.0, color="0.2", lw=0.8, ls="--")
    ax.set_xticks(np.arange(len(measures)), labels=[m.replace("_", " ") for m in measures], fontsize=8)
    ax.set_ylabel("speedup (baseline / arm)")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7)
    return fig


def plot_sensitivity(
    sens: pd.DataFrame, metric: str, ax=None, reference: dict | None = None, colors: dict | None = None
) -> Figure:
    """One swept key against a metric: IQM with 95 % interval per value, one line per combination of
    the other swept keys (``series``); ``reference`` {label: value} draws horizontal lines (e.g. the
    baseline arm). ``sens`` has ``key, value, series, metric, iqm, ci_low, ci_high`` for one key."""
    fig, ax = _axes(ax, figsize=(4.8, 3.4))
    s = sens[sens["metric"] == metric]
    key = s["key"].iloc[0] if len(s) else ""
    series = sorted(s["series"].unique())
    palette = colors or arm_colors(series)
    for name in series:
        d = s[s["series"] == name].sort_values("value")
        y = d["iqm"].to_numpy(dtype=float)
        err = np.abs(np.vstack([y - d["ci_low"].to_numpy(dtype=float), d["ci_high"].to_numpy(dtype=float) - y]))
        ax.errorbar(d["value"].astype(float), y, yerr=np.nan_to_num(err), marker="o", ms=4, capsize=3,
                    color=palette.get(name), label=name or key)
    for i, (label, value) in enumerate((reference or {}).items()):
        if np.isfinite(value):
            ax.axhline(value, color=f"{0.2 + 0.2 * i:.1f}", lw=0.8, ls="--", label=label)
    ax.set_xlabel(key)
    ax.set_ylabel(SENSITIVITY_LABELS.get(metric, metric.replace("_", " ")))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return fig
