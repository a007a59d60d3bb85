"""The figures of the speedup curve, the iso-failure ratios, the sampling distribution's support and
the whole-clip evaluations (same conventions as ``analysis.plots``: ``plot_x(df, ax=None, ...) -> Figure``, no pyplot state)."""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from analysis.palette import arm_colors, place_legend
from analysis.plots import IntegerTicks, _axes, _marker, plot_learning_curve
from bmimic.runs.schema import CLIP_TIME_S, CONDITION, FAILURE_RATE, ITERATION

CURVE_MARKERS = {"estimate": "o", "lower_bound": "^", "upper_bound": "v"}
"""Marker of each speedup status on the curve figures (not estimable: not drawn)."""


def _ratio_curve(ax, x: np.ndarray, ratio: np.ndarray, status, color, label: str,
                 low: np.ndarray | None = None, high: np.ndarray | None = None) -> float:
    """One arm's ratio curve: a line through the estimates, markers by status (^ lower bound, v upper
    bound), the interval as a band where there is one; returns the largest value drawn."""
    status = np.asarray(status, dtype=object)
    est = status == "estimate"
    ax.plot(np.where(est, x, np.nan), np.where(est, ratio, np.nan), color=color, lw=1.4, label=label)
    for s, marker in CURVE_MARKERS.items():
        sel = (status == s) & np.isfinite(ratio)
        if sel.any():
            ax.scatter(x[sel], ratio[sel], marker=marker, s=22 if s == "estimate" else 36, color=color,
                       facecolors=color if s == "estimate" else "none", lw=1, zorder=3)
    top = float(np.nanmax(np.where(np.isfinite(ratio), ratio, np.nan))) if np.isfinite(ratio).any() else 1.0
    if low is not None and high is not None:
        ok = np.isfinite(low) & np.isfinite(high)
        if ok.any():
            ax.fill_between(x, np.where(ok, low, np.nan), np.where(ok, high, np.nan), color=color, alpha=0.2, lw=0)
            top = max(top, float(np.nanmax(np.where(ok, high, np.nan))))
    return top


def _ratio_figure(df: pd.DataFrame, x: str, ax, colors: dict | None, band: bool, xlabel: str, ylabel: str,
                  title: str, cap: float = 20.0) -> Figure:
    """One _ratio_curve per arm of ``df`` (columns ``arm``, ``x``, ``ratio``, ``status`` and, with
    ``band``, ``ci_low``/``ci_high``) against ``x``, a dashed line at 1, the y axis up to the largest
    value drawn (at most ``cap``)."""
    fig, ax = _axes(ax)
    colors = colors or arm_colors(df["arm"])
    top = 1.0
    for arm, g in df.groupby("arm", sort=True):
        g = g.sort_values(x)
        lo, hi = (g["ci_low"].to_numpy(float), g["ci_high"].to_numpy(float)) if band else (None, None)
        top = max(top, _ratio_curve(ax, g[x].to_numpy(float), g["ratio"].to_numpy(float), g["status"], colors[arm],
                                    arm, lo, hi))
    ax.axhline(1.0, color="0.2", lw=0.8, ls="--")
    ax.set_ylim(0, min(top, cap) * 1.15)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=7)
    ax.grid(alpha=0.3)
    place_legend(ax)
    return fig


def plot_speedup_curve(curve: pd.DataFrame, measure: str = "iteration", ax=None,
                       colors: dict | None = None) -> Figure:
    """Speedup against the baseline (baseline median / arm median time to a success threshold) over the
    success thresholds, one line per arm: filled dots are estimates (band: bootstrap interval where there
    is one), open ^ lower bounds (the baseline's median not reached), open v upper bounds; thresholds
    where neither median was reached are not drawn. ``curve`` is speedup_curve.csv."""
    return _ratio_figure(curve[curve["measure"] == measure], "threshold", ax, colors, True,
                         "overall success threshold (1 − failed / started episodes)",
                         f"speedup in {measure.replace('_', ' ')} (baseline / arm)",
                         "dots: estimates (band: bootstrap interval); open ^: lower bound; open v: upper bound")


def plot_iso_failure(iso: pd.DataFrame, measure: str = "iteration", ax=None, colors: dict | None = None) -> Figure:
    """Iso-failure ratio over training: at each evaluation of the baseline, its time over the time the
    arm first reached the baseline's failure level there (> 1: the arm got there sooner), one line per
    arm; markers as plot_speedup_curve. ``iso`` is iso_failure.csv."""
    return _ratio_figure(iso[iso["measure"] == measure], "baseline_time", ax, colors, False,
                         f"baseline {measure.replace('_', ' ')}", "baseline time / arm time to the same failure",
                         "point curves over seeds; open ^: lower bound; open v: upper bound (arm never got there)")


def plot_sampling_support(summary: pd.DataFrame, colors: dict | None = None) -> Figure:
    """Two panels over training, one line per arm (mean over seeds): the effective support of the
    sampling distribution, (1 / Σ p²) / S (1 = uniform), and its largest probability relative to
    uniform, max p × S; dashed where a library's clip-level values exist (over the C clips' masses).
    ``summary`` is sampling_support.csv."""
    fig = Figure(figsize=(9.0, 3.4), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2)
    colors = colors or arm_colors(summary["arm"])
    for arm, g in summary.groupby("arm", sort=True):
        g = g.sort_values(ITERATION)
        x = g[ITERATION].to_numpy(float)
        ax1.plot(x, g["effective_support"].to_numpy(float), color=colors[arm], lw=1.4, label=arm, **_marker(len(x)))
        ax2.plot(x, g["max_p_rel"].to_numpy(float), color=colors[arm], lw=1.4, label=arm, **_marker(len(x)))
        if g["clip_effective_support"].notna().any():
            ax1.plot(x, g["clip_effective_support"].to_numpy(float), color=colors[arm], lw=1.0, ls="--")
            ax2.plot(x, g["clip_max_p_rel"].to_numpy(float), color=colors[arm], lw=1.0, ls="--")
    ax1.set_ylim(0, 1.05)
    ax1.set_ylabel("effective support (1 / Σ p²) / S")
    ax2.set_ylabel("largest p relative to uniform (max p × S)")
    ax2.set_ylim(bottom=0)
    for ax in (ax1, ax2):
        ax.set_xlabel("iteration")
        ax.xaxis.set_major_locator(IntegerTicks())
        ax.grid(alpha=0.3)
    place_legend(ax1)
    if summary["clip_effective_support"].notna().any():
        ax1.set_title("solid: over bins; dashed: over clips (their masses)", fontsize=7)
    return fig


def plot_whole_clip_success(curves: pd.DataFrame, per_seed: pd.DataFrame, colors: dict | None = None) -> Figure:
    """Whole-clip success against iteration, one panel per condition (``metric``), one line per arm: the
    point over seeds with its band, and each seed. ``curves`` and ``per_seed`` are analysis.whole_clip's."""
    conditions = sorted(curves["metric"].unique())
    fig = Figure(figsize=(4.6 * len(conditions), 3.4), layout="constrained")
    colors = colors or arm_colors(curves["arm"])
    for ax, condition in zip(np.atleast_1d(fig.subplots(1, len(conditions))), conditions, strict=True):
        plot_learning_curve(curves[curves["metric"] == condition], "whole-clip success (completed / rollouts)", ax=ax,
                            colors=colors, title=condition, per_seed=per_seed[per_seed["metric"] == condition])
        ax.set_ylim(-0.02, 1.02)
    return fig


def plot_whole_clip_survival(survival: pd.DataFrame, colors: dict | None = None) -> Figure:
    """Fraction of whole-clip rollouts still tracking against time into the clip, at each run's last
    whole-clip evaluation, one panel per condition, one line per arm (mean over seeds, band: their range)."""
    conditions = sorted(survival[CONDITION].unique())
    fig = Figure(figsize=(4.6 * len(conditions), 3.4), layout="constrained")
    colors = colors or arm_colors(survival["arm"])
    for ax, condition in zip(np.atleast_1d(fig.subplots(1, len(conditions))), conditions, strict=True):
        for arm, g in survival[survival[CONDITION] == condition].groupby("arm", sort=True):
            g = g.sort_values(CLIP_TIME_S)
            x = g[CLIP_TIME_S].to_numpy(float)
            ax.step(x, g["tracking_frac"].to_numpy(float), where="post", color=colors[arm], lw=1.4, label=arm)
            ax.fill_between(x, g["low"].to_numpy(float), g["high"].to_numpy(float), step="post", color=colors[arm],
                            alpha=0.2, lw=0)
        ax.set_ylim(-0.02, 1.02)
        ax.set_xlabel("time into the clip (s)")
        ax.set_ylabel("rollouts still tracking")
        ax.set_title(condition, fontsize=8)
        ax.grid(alpha=0.3)
        place_legend(ax)
    return fig


def plot_hardest_clips(curves: pd.DataFrame, colors: dict | None = None) -> Figure:
    """Failure per started episode against iteration for each clip of ``curves`` (analysis.clip_tables.
    hardest_clip_curves, one panel per clip, hardest first), one line per arm: the mean over seeds, and
    each seed thin."""
    clips = list(curves["clip"].cat.categories)  # hardest first
    ncols = min(3, len(clips))
    nrows = -(-len(clips) // ncols)
    fig = Figure(figsize=(3.3 * ncols, 2.6 * nrows), layout="constrained")
    colors = colors or arm_colors(curves["arm"])
    axes = np.atleast_1d(fig.subplots(nrows, ncols, sharex=True)).ravel()
    for ax, clip in zip(axes, clips, strict=False):
        for arm, g in curves[curves["clip"] == clip].groupby("arm", sort=True, observed=True):
            for _, run in g.groupby("run_dir", sort=True):
                ax.plot(run[ITERATION].to_numpy(float), run[FAILURE_RATE].to_numpy(float), color=colors[arm],
                        lw=0.6, alpha=0.45)
            mean = g.groupby(ITERATION, sort=True)[FAILURE_RATE].mean()
            ax.plot(mean.index.to_numpy(float), mean.to_numpy(float), color=colors[arm], lw=1.6, label=arm,
                    **_marker(len(mean)))
        ax.set_title(str(clip), fontsize=8)
        ax.set_ylim(bottom=0.0)
        ax.grid(alpha=0.3)
        ax.xaxis.set_major_locator(IntegerTicks())
    for ax in axes[len(clips):]:
        ax.set_visible(False)
    for ax in axes[::ncols]:
        ax.set_ylabel("failure (by start clip)")
    for ax in axes[max(0, len(clips) - ncols):len(clips)]:
        ax.set_xlabel("iteration")
    place_legend(axes[0])
    return fig
