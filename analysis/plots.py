"""One function per figure: ``plot_x(df, ax=None, ...) -> matplotlib Figure``.

Figures are built on ``matplotlib.figure.Figure`` directly (no pyplot state, rendered by Agg when
saved), so importing this module never changes the caller's backend. Inputs are the tidy frames of
``analysis.report``; arms keep one colour across figures when ``colors`` is passed.
"""

from __future__ import annotations

import math
from typing import cast

import numpy as np
import pandas as pd
from matplotlib import rcParams
from matplotlib.axis import Axis
from matplotlib.figure import Figure
from matplotlib.font_manager import FontProperties
from matplotlib.ticker import MaxNLocator

from analysis.palette import arm_colors, place_legend
from bmimic.runs.schema import BIN, FAILURE_RATE, HORIZON_TRUNCATED, ITERATION

FIGSIZE = (6.0, 3.6)
"""Default size of a single-panel figure in inches (about 600x360 px at the report's 100 dpi)."""

SENSITIVITY_LABELS = {
    "final_failure": "final overall failure",
    "bins_mastered": "bins mastered",
    "time_iteration": "iterations to success threshold (median)",
}
"""Axis labels of the arm-summary metrics drawn by plot_sensitivity."""


MAX_PANEL_COLUMNS = 4
"""plot_bin_heatmaps wraps its panels into rows of at most this many (7 arms: 4 + 3)."""


class IntegerTicks(MaxNLocator):
    """Integer ticks (bins, iterations), only as many as the axis has room for at the width of its
    longest label: MaxNLocator's "auto" allows a tick per three font sizes whatever the labels, so on
    a narrow panel 200 bins read "0 80160240320"; one integer in view still gets its tick."""

    def __init__(self) -> None:
        super().__init__(nbins="auto", integer=True, min_n_ticks=1)

    def __call__(self):
        axis, ax = cast(Axis, self.axis), cast(Axis, self.axis).axes  # set once the locator is on an axis
        vmin, vmax = axis.get_view_interval()
        horizontal = axis is ax.xaxis
        size = FontProperties(size=rcParams["xtick.labelsize" if horizontal else "ytick.labelsize"]).get_size_in_points()
        chars = max(len(str(int(round(v)))) for v in (vmin, vmax) if math.isfinite(v)) if (
            math.isfinite(vmin) or math.isfinite(vmax)) else 1
        # A label's width (digits ~0.6 em) plus a gap of about 1.5 em; vertically a line and a gap.
        room_pt = (ax.bbox.width if horizontal else ax.bbox.height) / ax.figure.dpi * 72.0
        per_tick_pt = size * (0.6 * chars + 1.5) if horizontal else size * 2.5
        self.set_params(nbins=max(1, int(room_pt // per_tick_pt) - 1))
        return super().__call__()


def _axes(ax, figsize=FIGSIZE):
    if ax is not None:
        return ax.figure, ax
    fig = Figure(figsize=figsize, layout="constrained")
    return fig, fig.add_subplot()


def _mark_segments(ax, bins: pd.DataFrame | None, axis: str = "x", hatch_above: bool = False,
                   names: bool = True) -> None:
    """Label the bin axis with segment names: boundaries as thin lines, names on the opposite side
    (horizontal where every name fits its span, else rotated; long names shortened; none with
    ``names=False``, for panels below another); hatch the horizon-truncated bins (over the cells of a
    heatmap with ``hatch_above``, else behind the lines)."""
    (ax.xaxis if axis == "x" else ax.yaxis).set_major_locator(IntegerTicks())
    if bins is None or not len(bins):
        return
    bins = bins.sort_values(BIN).reset_index(drop=True)
    if HORIZON_TRUNCATED in bins and bins[HORIZON_TRUNCATED].any():
        span = ax.axvspan if axis == "x" else ax.axhspan
        for b in bins.loc[bins[HORIZON_TRUNCATED].astype(bool), BIN]:
            span(b - 0.5, b + 0.5, facecolor="none", edgecolor="0.55", hatch="///", lw=0,
                 zorder=3 if hatch_above else 0.5)
    if not bins["segment"].astype(bool).any():
        return
    change = bins["segment"].ne(bins["segment"].shift()).cumsum()
    spans = bins.groupby(change).agg(name=("segment", "first"), first=("bin", "first"), last=("bin", "last"))
    line = ax.axvline if axis == "x" else ax.axhline
    for first in spans["first"].iloc[1:]:
        line(first - 0.5, color="0.3", lw=0.6, ls=":")
    if not names:
        return
    centres = ((spans["first"] + spans["last"]) / 2.0).to_list()
    labels = [n if len(n) <= 18 else n[:17] + "…" for n in spans["name"].astype(str)]
    twin = ax.secondary_xaxis("top") if axis == "x" else ax.secondary_yaxis("right")
    # Characters that fit a segment's span at fontsize 7 on a ~5 inch axis: about 70 per axis width.
    width_bins = max(len(bins), 1)
    fits = all(len(n) <= 70 * (r.last - r.first + 1) / width_bins for n, r in zip(labels, spans.itertuples(),
                                                                                 strict=True))
    rotation = 0 if (fits or axis != "x") else 90
    twin.set_ticks(centres, labels=labels, fontsize=7, rotation=rotation)
    twin.tick_params(length=0)


def _marker(n_points: int) -> dict:
    """Markers where a line has few points (a single evaluation is otherwise invisible)."""
    return {"marker": "o", "ms": 4} if n_points <= 25 else {}


def _seed_values(per_seed) -> np.ndarray:
    """Per-seed values from a ``"a;b;c"`` cell (censored ``>t`` entries dropped)."""
    return np.array([float(v) for v in str(per_seed).split(";") if v and not v.startswith(">")], dtype=float)


def _edges(centres: np.ndarray, floor: float | None = None) -> np.ndarray:
    """Cell edges halfway between sorted centres, extended by half a step at both ends (the first
    edge not below ``floor``: iteration 0's cell does not reach negative iterations)."""
    if len(centres) == 1:
        edges = np.array([centres[0] - 0.5, centres[0] + 0.5])
    else:
        mid = (centres[1:] + centres[:-1]) / 2.0
        edges = np.r_[2 * centres[0] - mid[0], mid, 2 * centres[-1] - mid[-1]]
    if floor is not None and centres[0] >= floor + 0.5:
        edges[0] = max(edges[0], floor)
    return edges


def plot_learning_curve(
    curves: pd.DataFrame, ylabel: str = "", ax=None, colors: dict | None = None, title: str | None = None,
    per_seed: pd.DataFrame | None = None,
) -> Figure:
    """Point estimate over seeds against iteration, one line per arm, with its band and each seed.

    ``curves`` has ``arm, iteration, point, ci_low, ci_high`` (tables.learning_curves for one metric);
    ``per_seed`` (``arm, run_dir, iteration, value``) adds one thin line per seed.
    """
    fig, ax = _axes(ax)
    colors = colors or arm_colors(curves["arm"])
    if per_seed is not None and len(per_seed):
        for (arm, _), c in per_seed.sort_values(ITERATION).groupby(["arm", "run_dir"], sort=True):
            x = c[ITERATION].to_numpy(dtype=float)
            ax.plot(x, c["value"].to_numpy(dtype=float), color=colors.get(arm, "0.5"), lw=0.6, alpha=0.45,
                    **({"marker": ".", "ms": 3} if len(x) <= 25 else {}))
    for arm, c in curves.groupby("arm", sort=True):
        c = c.sort_values(ITERATION)
        x = c[ITERATION].to_numpy(dtype=float)  # concatenated tables can arrive as object columns
        ax.plot(x, c["point"].to_numpy(dtype=float), color=colors[arm], lw=1.6, label=arm, **_marker(len(x)))
        ax.fill_between(x, c["ci_low"].to_numpy(dtype=float), c["ci_high"].to_numpy(dtype=float),
                        color=colors[arm], alpha=0.2, lw=0)
    ax.xaxis.set_major_locator(IntegerTicks())
    ax.set_xlabel("iteration")
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title, fontsize=8)
    ax.grid(alpha=0.3)
    place_legend(ax)
    return fig


def plot_bin_heatmap(
    df: pd.DataFrame,
    value: str = FAILURE_RATE,
    ax=None,
    bins: pd.DataFrame | None = None,
    vmin: float | None = 0.0,
    vmax: float | None = None,
    title: str | None = None,
    cmap: str = "magma_r",
    colorbar: bool = True,
    max_rows: int = 400,
    segment_names: bool = True,
) -> Figure:
    """Heatmap of ``value`` over iterations (rows, increasing upwards) x bins (columns) for one arm.

    ``df`` has ``iteration, bin, value`` (e.g. the seed-mean failure of one arm); ``bins`` (from
    metrics.bin_table) adds the segment boundaries and, with ``segment_names``, their names on top.
    Each cell spans from halfway to the previous iteration to halfway to the next, so uneven evaluation
    spacing is drawn to scale. The colour bar says when cells above ``vmax`` saturate.
    """
    fig, ax = _axes(ax)
    grid = df.pivot_table(index=ITERATION, columns=BIN, values=value, aggfunc="mean").sort_index()
    if len(grid) > max_rows:  # more rows than pixels: keep every k-th iteration (and the last)
        keep = np.unique(np.r_[np.arange(0, len(grid), int(np.ceil(len(grid) / max_rows))), len(grid) - 1])
        grid = grid.iloc[keep]
    cells = grid.to_numpy(dtype=float)
    image = ax.pcolormesh(_edges(grid.columns.to_numpy(float)), _edges(grid.index.to_numpy(float), floor=-0.5),
                          cells, cmap=cmap, vmin=vmin, vmax=vmax, shading="flat")
    ax.set_xlabel("bin")
    ax.set_ylabel("iteration")
    if len(grid) <= 8:  # few evaluations (a smoke run): a tick on each row
        ax.set_yticks(grid.index.to_numpy(float), labels=[f"{i:g}" for i in grid.index])
    else:
        ax.yaxis.set_major_locator(IntegerTicks())
    if title:
        ax.set_title(title, fontsize=8)
    _mark_segments(ax, bins, hatch_above=True, names=segment_names)
    if colorbar:
        fig.colorbar(image, ax=ax, label=value.replace("_", " "), shrink=0.9, extend=_extend(cells, vmax))
    return fig


def _extend(cells: np.ndarray, vmax: float | None) -> str:
    """``max`` (a pointed colour bar) when some cells lie above the scale and saturate."""
    return "max" if vmax is not None and np.nanmax(cells, initial=-np.inf) > vmax else "neither"


def plot_bin_heatmaps(
    df: pd.DataFrame, value: str = FAILURE_RATE, bins: pd.DataFrame | None = None,
    vmax: float | None = None, cmap: str = "magma_r", scale: str = "shared",
) -> Figure:
    """plot_bin_heatmap for every arm in ``df``, in rows of at most MAX_PANEL_COLUMNS panels (segment
    names above the top row only). ``scale="shared"``: one colour scale from 0 to ``vmax`` (default:
    the largest value), for values every arm measures alike (failure rates); ``"per_panel"``: each
    panel from 0 to its own largest value with its own colour bar, for distributions whose peaks
    differ by orders of magnitude between arms (sampling probabilities: one arm's bright bin would
    leave the others dark)."""
    if scale not in ("shared", "per_panel"):
        raise ValueError(f"scale must be 'shared' or 'per_panel', got {scale!r}")
    arms = sorted(df["arm"].unique())
    ncols = min(len(arms), MAX_PANEL_COLUMNS)
    nrows = math.ceil(len(arms) / ncols)
    shared = scale == "shared"
    vmax = (float(df[value].max()) if vmax is None else vmax) if shared else None
    fig = Figure(figsize=(3.4 * ncols + 0.8, 2.6 * nrows + 1.0), layout="constrained")
    axes = fig.subplots(nrows, ncols, squeeze=False, sharex=True, sharey=True).ravel()
    image = None
    for i, (ax, arm) in enumerate(zip(axes, arms, strict=False)):
        cells = df[df["arm"] == arm]
        plot_bin_heatmap(cells, value, ax=ax, bins=bins, vmax=vmax if shared else float(cells[value].max()),
                         title=arm, cmap=cmap, colorbar=not shared, segment_names=i < ncols)
        image = ax.collections[0]
        if i % ncols:
            ax.set_ylabel("")
        bottom = i + ncols >= len(arms)  # no panel below: its bin axis is labelled
        ax.xaxis.set_tick_params(labelbottom=bottom)
        ax.set_xlabel("bin" if bottom else "")
    for ax in axes[len(arms):]:
        ax.set_visible(False)
    if shared and image is not None:
        fig.colorbar(image, ax=list(axes[:len(arms)]), label=value.replace("_", " "), shrink=0.9,
                     extend=_extend(df[value].to_numpy(float), vmax))
    return fig


def plot_final_bin_failure(
    final: pd.DataFrame, ax=None, bins: pd.DataFrame | None = None, colors: dict | None = None
) -> Figure:
    """Failure per bin at the final comparison point: point estimate over seeds with its band (bootstrap
    interval or range of the seeds) and each seed as a dot, one line per arm.

    ``final`` has ``arm, bin, point, ci_low, ci_high, per_seed`` (tables.final_bin_failure).
    """
    fig, ax = _axes(ax)
    colors = colors or arm_colors(final["arm"])
    arms = sorted(final["arm"].unique())
    for i, (arm, f) in enumerate(final.groupby("arm", sort=True)):
        f = f.sort_values(BIN)
        x = f[BIN].to_numpy(dtype=float)
        ax.plot(x, f["point"], marker="o", ms=3, color=colors[arm], lw=1.2, label=arm)
        ax.fill_between(x, f["ci_low"].to_numpy(dtype=float), f["ci_high"].to_numpy(dtype=float),
                        color=colors[arm], alpha=0.2, lw=0)
        jitter = (i - (len(arms) - 1) / 2) * 0.12
        seeds = [_seed_values(cell) for cell in f["per_seed"]]  # one scatter per arm, bin after bin
        counts = np.fromiter((len(v) for v in seeds), dtype=int, count=len(seeds))
        ax.scatter(np.repeat(x + jitter, counts), np.concatenate(seeds) if seeds else np.empty(0), s=6,
                   color=colors[arm], alpha=0.6, lw=0)
    ax.set_xlabel("bin")
    ax.set_ylabel("failure rate")
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    place_legend(ax)
    _mark_segments(ax, bins)
    return fig


def plot_mastery(
    mastery: pd.DataFrame, per_seed: pd.DataFrame | None = None, ax=None, bins: pd.DataFrame | None = None,
    colors: dict | None = None, threshold: float | None = None,
) -> Figure:
    """Median mastery iteration over seeds per bin, one line per arm; each seed as a dot (x at its last
    evaluation when it had not mastered the bin by then); a bin whose median was not reached as an
    open triangle at the arm's last follow-up (a lower bound). ``mastery`` is tables.mastery,
    ``per_seed`` tables.mastery_seeds."""
    fig, ax = _axes(ax)
    colors = colors or arm_colors(mastery["arm"])
    arms = sorted(mastery["arm"].unique())
    for i, (arm, m) in enumerate(mastery.groupby("arm", sort=True)):
        m = m.sort_values(BIN)
        jitter = (i - (len(arms) - 1) / 2) * 0.12
        ax.plot(m[BIN], m["mastery_iteration"], marker="o", ms=4, color=colors[arm], lw=1.2, label=arm)
        never = m[m["mastery_iteration"].isna()]
        if len(never):
            ax.scatter(never[BIN], never["follow_up"], marker="^", facecolors="none", edgecolors=colors[arm], s=30)
        if per_seed is not None and len(per_seed):
            s = per_seed[per_seed["arm"] == arm]
            got = s[s["mastered"]]
            ax.scatter(got[BIN] + jitter, got[ITERATION], s=6, color=colors[arm], alpha=0.6, lw=0)
            cen = s[~s["mastered"]]
            ax.scatter(cen[BIN] + jitter, cen["last_iteration"], s=10, marker="x", color=colors[arm], alpha=0.6,
                       lw=0.8)
    ax.set_xlabel("bin")
    ax.set_ylabel("mastery iteration")
    ax.yaxis.set_major_locator(IntegerTicks())
    if threshold is not None:
        ax.set_title(f"median over seeds of the first sustained failure < {threshold:g}\n"
                     "dots: seeds; x: seed not there by its last evaluation; open ^: median not reached", fontsize=7)
    ax.grid(alpha=0.3)
    place_legend(ax)
    _mark_segments(ax, bins)
    return fig


STATUS_MARKS = {"estimate": "", "lower_bound": "≥", "upper_bound": "≤", "not_estimable": "n/e"}
"""How plot_speedup labels a bar of each speedup status."""


def plot_speedup(speedup: pd.DataFrame, per_seed: pd.DataFrame | None = None, ax=None,
                 colors: dict | None = None) -> Figure:
    """Speedup against the baseline per arm and measure; 1 = no change. Bars show the estimate or the
    bound (labelled ≥ / ≤; n/e: not estimable, no bar), whiskers the bootstrap interval where there is
    one, dots ``per_seed`` (``arm, measure, value``: baseline median / that arm seed's time).
    """
    fig, ax = _axes(ax)
    colors = colors or arm_colors(speedup["arm"])
    measures = list(dict.fromkeys(speedup["measure"]))
    arms = sorted(speedup["arm"].unique())
    width = 0.8 / max(len(arms), 1)
    top = 1.0
    for i, arm in enumerate(arms):
        s = speedup[speedup["arm"] == arm].set_index("measure").reindex(measures)
        x = np.arange(len(measures)) + (i - (len(arms) - 1) / 2) * width
        ratio = s["ratio"].to_numpy(dtype=float)
        shown = np.where(np.isfinite(ratio), ratio, 0.0)
        ax.bar(x, shown, width, color=colors[arm], label=arm, alpha=0.85)
        low, high = s["ci_low"].to_numpy(dtype=float), s["ci_high"].to_numpy(dtype=float)
        has = np.isfinite(low) & np.isfinite(high) & np.isfinite(ratio)
        if has.any():
            ax.errorbar(x[has], ratio[has], yerr=np.abs(np.vstack([ratio[has] - low[has], high[has] - ratio[has]])),
                        fmt="none", ecolor="0.2", capsize=3, lw=1)
            top = max(top, float(np.max(high[has])))
        for xi, r, status in zip(x, ratio, s["status"].fillna("not_estimable"), strict=True):
            mark = STATUS_MARKS.get(status, "")
            if mark:
                ax.annotate(mark, (xi, r if np.isfinite(r) else 0.0), ha="center", va="bottom", fontsize=8,
                            xytext=(0, 2), textcoords="offset points")
        if per_seed is not None and len(per_seed):
            for j, measure in enumerate(measures):
                v = per_seed[(per_seed["arm"] == arm) & (per_seed["measure"] == measure)]["value"].to_numpy(float)
                v = v[np.isfinite(v)]
                ax.scatter(np.full(len(v), x[j]), v, s=8, color="0.15", zorder=3, lw=0)
                top = max(top, float(v.max()) if len(v) else top)
        top = max(top, float(np.nanmax(np.where(np.isfinite(ratio), ratio, np.nan))) if np.isfinite(ratio).any() else top)
    ax.axhline(1.0, color="0.2", lw=0.8, ls="--")
    ax.set_ylim(0, top * 1.15)
    ax.set_xticks(np.arange(len(measures)), labels=[m.replace("_", " ") for m in measures], fontsize=8)
    ax.set_ylabel("speedup (baseline / arm)")
    ax.grid(alpha=0.3, axis="y")
    place_legend(ax)
    return fig


def plot_sensitivity(
    sens: pd.DataFrame, metric: str, ax=None, reference: dict | None = None, colors: dict | None = None,
    per_seed: pd.DataFrame | None = None,
) -> Figure:
    """One swept key against a metric: point estimate with its interval (bootstrap or range of the seeds)
    per value, one line per combination of the other swept keys (``series``), each seed as a dot
    (``per_seed``: ``arm, value`` rows of tables.per_run_metrics for this metric); ``reference``
    {label: value} draws horizontal lines (e.g. the baseline arm). ``sens`` has ``key, value, series,
    arm, metric, point, ci_low, ci_high`` for one key."""
    fig, ax = _axes(ax, figsize=(4.8, 3.4))
    s = sens[sens["metric"] == metric]
    key = s["key"].iloc[0] if len(s) else ""
    series = sorted(s["series"].unique())
    palette = colors or arm_colors(series)
    for name in series:
        d = s[s["series"] == name].sort_values("value")
        y = d["point"].to_numpy(dtype=float)
        err = np.abs(np.vstack([y - d["ci_low"].to_numpy(dtype=float), d["ci_high"].to_numpy(dtype=float) - y]))
        ax.errorbar(d["value"].astype(float), y, yerr=np.nan_to_num(err), marker="o", ms=4, capsize=3,
                    color=palette.get(name), label=name or key)
        if per_seed is not None and len(per_seed):
            x_of = dict(zip(d["arm"], d["value"].astype(float), strict=True))
            pts = per_seed[per_seed["arm"].isin(x_of)]
            ax.scatter(pts["arm"].map(x_of), pts["value"], s=8, color=palette.get(name), alpha=0.6, lw=0)
    for i, (label, value) in enumerate((reference or {}).items()):
        if np.isfinite(value):
            ax.axhline(value, color=f"{0.2 + 0.2 * i:.1f}", lw=0.8, ls="--", label=label)
    ax.set_xlabel(key)
    ax.set_ylabel(SENSITIVITY_LABELS.get(metric, metric.replace("_", " ")))
    if metric in ("bins_mastered", "time_iteration"):
        ax.yaxis.set_major_locator(IntegerTicks())
    ax.grid(alpha=0.3)
    place_legend(ax)
    return fig
