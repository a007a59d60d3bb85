"""The report's Knobs section (analysis.knobs): its figures and its markdown.

Per knob, three figures: the speedup over uniform (or over the reference where there is no uniform
arm) across success thresholds, one line per level; the evaluated failure per bin over training for
the reference and the knob's two extreme levels side by side; and the sampling distribution over bins
at three fixed iterations, one line per level (how gamma and K spread mass back from a failing bin,
what lambda keeps)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from analysis import curve_plots, plots
from analysis.files import save_figure, write_csv
from analysis.knobs import THRESHOLDS
from analysis.markdown import fmt, is_nan, md_table
from analysis.speedup_curve import speedup_curve
from analysis.tables import ReportOptions
from bmimic.runs.schema import BIN, FAILURE_RATE, ITERATION


def _file_key(knob: str) -> str:
    return knob.removeprefix("sampler.").replace("/", "_")


def sampling_iterations(samp: pd.DataFrame, fractions=(0.2, 0.5, 1.0)) -> list[int]:
    """Logged iterations nearest to these fractions of the last one (distinct, ascending)."""
    its = np.sort(samp[ITERATION].unique())
    if not len(its):
        return []
    picks = {int(its[np.argmin(np.abs(its - f * its[-1]))]) for f in fractions}
    return sorted(picks)


def plot_sampling_at(samp: pd.DataFrame, iterations: list[int], colors: dict, bins: pd.DataFrame | None = None,
                     order: list[str] | None = None) -> Figure:
    """One panel per iteration: the seed-mean sampling probability over bins, one line per arm
    (``samp``: ``arm, iteration, bin, probability``), relative to uniform (1 = uniform)."""
    fig = Figure(figsize=(3.6 * max(1, len(iterations)) + 0.6, 3.0), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, max(1, len(iterations)), sharey=True))
    arms = order or sorted(samp["arm"].unique())
    for ax, it in zip(axes, iterations, strict=False):
        at = samp[samp[ITERATION] == it]
        for arm in arms:
            g = at[at["arm"] == arm].sort_values(BIN)
            if len(g):
                n = g[BIN].nunique()
                ax.plot(g[BIN], g["probability"] * n, color=colors.get(arm), lw=1.0, label=arm)
        ax.axhline(1.0, color="0.3", lw=0.7, ls="--")
        ax.set_title(f"iteration {it}", fontsize=8)
        ax.set_xlabel("bin")
        plots._mark_segments(ax, bins, names=False)
    axes[0].set_ylabel("probability x bins (1 = uniform)")
    axes[0].legend(fontsize=6)
    return fig


def plot_over_clip_time(cells: pd.DataFrame, order: list[str]) -> Figure:
    """Two panels over clip time, one stair line per arm on its own bins: the final failure and the
    training sampler's density relative to uniform (``cells``: bin_tables.over_clip_time). A knob's few
    levels get distinct colours of their own (the report's colours for many arms can be near alike)."""
    colors = {arm: f"C{i % 10}" for i, arm in enumerate(order)}
    fig = Figure(figsize=(9.0, 3.0), layout="constrained")
    axes = fig.subplots(1, 2, sharex=True)
    for ax, column, label in ((axes[0], FAILURE_RATE, "final failure"),
                              (axes[1], "density", "sampling density (1 = uniform)")):
        for arm in order:
            g = cells[cells["arm"] == arm].sort_values("bin_start_s")
            if len(g) and g[column].notna().any():
                edges = np.append(g["bin_start_s"].to_numpy(float), g["bin_end_s"].to_numpy(float)[-1])
                ax.stairs(g[column].to_numpy(float), edges, baseline=None, color=colors.get(arm), lw=1.0, label=arm)
        ax.set_xlabel("clip time (s)")
        ax.set_ylabel(label)
    axes[1].axhline(1.0, color="0.3", lw=0.7, ls="--")
    axes[0].legend(fontsize=6)
    return fig


def write_knob_files(levels: pd.DataFrame, summary: pd.DataFrame, overall: pd.DataFrame, runs: pd.DataFrame,
                     bin_fail: pd.DataFrame, samp: pd.DataFrame, colors: dict, bins: pd.DataFrame | None,
                     uniform: str | None, opts: ReportOptions, out: Path,
                     other_layouts: list | tuple = (), clip_time: pd.DataFrame | None = None) -> list[tuple[str, str]]:
    """knob_levels.csv, knob_summary.csv and the three figures of every knob; returns (file, title). A knob
    whose levels cut the clip into other bins than the reference's (``other_layouts``: bin size) gets its
    failure and sampling over clip time instead (``clip_time``: bin_tables.over_clip_time): bins of
    different lengths share no bin axis."""
    write_csv(out / "knob_levels.csv", levels)
    write_csv(out / "knob_summary.csv", summary)
    figures = []
    for knob, g in levels.groupby("knob", sort=True):
        key = _file_key(knob)
        arms = list(g.sort_values("value")["arm"])
        ref = g.loc[g["is_reference"], "arm"].iloc[0]
        base = uniform if uniform is not None else ref
        sel = overall[overall["arm"].isin({*arms, base})]
        curve = speedup_curve(sel, base, runs[runs["arm"].isin({*arms, base})], opts, measures=(ITERATION,))
        name = f"knob_{key}_speedup.png"
        save_figure(out / name, curve_plots.plot_speedup_curve(curve, ITERATION, colors=colors))
        figures.append((name, f"`{knob}`: speedup over `{base}` in iterations across success thresholds"))
        if set(arms) & set(other_layouts):
            cells = clip_time[clip_time["arm"].isin(arms)] if clip_time is not None and len(clip_time) else None
            if cells is not None and len(cells):
                name = f"knob_{key}_clip_time.png"
                write_csv(out / f"knob_{key}_clip_time.csv", cells)
                save_figure(out / name, plot_over_clip_time(cells, arms))
                figures.append((name, f"`{knob}`: final failure and sampling density over clip time, each level on "
                                      "its own bins (mean over seeds)"))
            continue
        others = g[~g["is_reference"]].sort_values("value")
        extremes = [ref, *dict.fromkeys([others["arm"].iloc[0], others["arm"].iloc[-1]])]
        name = f"knob_{key}_bins.png"
        save_figure(out / name, plots.plot_bin_heatmaps(bin_fail[bin_fail["arm"].isin(extremes)], FAILURE_RATE,
                                                        bins=bins))
        figures.append((name, f"`{knob}`: evaluated failure per bin over training, the reference and the lowest "
                              "and highest level (mean over seeds)"))
        s = samp[samp["arm"].isin(arms)]
        if len(s):
            its = sampling_iterations(s)
            name = f"knob_{key}_sampling.png"
            save_figure(out / name, plot_sampling_at(s, its, colors, bins=bins, order=arms))
            figures.append((name, f"`{knob}`: sampling distribution over bins at iterations "
                                  f"{', '.join(map(str, its))} (mean over seeds)"))
    return figures


def _bracket(low: float, high: float) -> str:
    """`` [low, high]`` of an interval (∞ where a side is open), `` [unbounded]`` when it spans every value
    its quantity can take (a speedup's 0 to ∞, a difference's -∞ to ∞), nothing without one."""
    if math.isnan(low) or math.isnan(high):
        return ""
    if math.isinf(high) and (math.isinf(low) or low == 0):
        return " [unbounded]"
    return f" [{'-∞' if math.isinf(low) else fmt(low)}, {'∞' if math.isinf(high) else fmt(high)}]"


def _ratio_cell(ratio: float, status: str, lo: float, hi: float) -> str:
    if math.isnan(ratio):
        return "–"
    mark = {"lower_bound": "≥ ", "upper_bound": "≤ "}.get(status, "")
    return f"{mark}x{fmt(ratio)}{_bracket(lo, hi)}"


def knob_section(levels: pd.DataFrame, summary: pd.DataFrame, uniform: str | None, alpha: float) -> list[str]:
    """The markdown of the Knobs section."""
    tag = int(round(THRESHOLDS[0] * 100))
    md = ["## Knobs", "",
          f"One knob of the reference arm changed at a time. Speedup = the reference's median iterations to "
          f"{THRESHOLDS[0]:g} overall success / the level's (> 1: sooner), in brackets its {100 * (1 - alpha):g}% "
          "confidence interval from the Gehan permutation test inverted (the speedups r for which the level's "
          "times, censored ones too, multiplied by r do not differ from the reference's). Final failure "
          f"difference: the level's mean minus the reference's, with its {100 * (1 - alpha):g}% confidence interval "
          "from the exact permutation test inverted (the shifts of the level's seeds that test does not reject). "
          "Both intervals are unadjusted for the knob's levels and unbounded where the seeds cannot bound them "
          "(one or two seeds against five). \"differs\": some level's final failure or time differs from the "
          f"reference's at p < {alpha:g} (exact permutation / Gehan test) after Holm's step-down adjustment over "
          "the row's tests; \"uncorrected\" lists the levels below it before adjustment. Trend: Spearman's rank "
          "correlation of each run's final failure with the knob's value over all of the knob's runs (the "
          "reference's included; > 0: failure rises with the value) and its two-sided permutation p (final "
          "failures shuffled over the runs), a question about the whole range, outside the verdict and unadjusted.",
          ""]
    view = pd.DataFrame({
        "knob": summary["knob"],
        "reference": summary["reference_value"].map(fmt),
        "levels": summary["levels"],
        **{f"{name} to {tag}%": [f"{fmt(r[f'{name}_value'])}: " + _ratio_cell(
            r[f"{name}_speedup"], "estimate", r[f"{name}_speedup_low"], r[f"{name}_speedup_high"])
            for _, r in summary.iterrows()] for name in ("slowest", "fastest")},
        f"final failure difference [{100 * (1 - alpha):g}% interval] (lowest / highest)": [
            f"{fmt(r.lowest_failure_value)}: {fmt(r.lowest_failure_difference)}"
            f"{_bracket(r.lowest_failure_low, r.lowest_failure_high)} / {fmt(r.highest_failure_value)}: "
            f"{fmt(r.highest_failure_difference)}{_bracket(r.highest_failure_low, r.highest_failure_high)}"
            for r in summary.itertuples(index=False)],
        "trend of final failure over values (ρ, p)": [
            "–" if is_nan(r.trend_rho) else f"{r.trend_rho:+.2f} (p = {fmt(r.trend_p)}, {int(r.trend_runs)} runs)"
            for r in summary.itertuples(index=False)],
        "tests": summary["tests"],
        "verdict": [(f"{v} ({d})" if d else v) + (f"; uncorrected: {u}" if u and u != d else "")
                    for v, d, u in zip(summary["verdict"], summary["differing_levels"],
                                       summary["differing_levels_uncorrected"], strict=True)],
    })
    md += ["Which knobs matter:", "", md_table(view), ""]
    rows = []
    for r in levels.itertuples(index=False):
        d = r._asdict()
        row = {"knob": r.knob, "value": fmt(r.value) + (" (reference)" if r.is_reference else ""),
               "seeds": r.n_seeds,
               "final failure [seeds]": f"{fmt(r.final_failure)} [{fmt(r.final_failure_min)}, {fmt(r.final_failure_max)}]",
               f"vs reference [{100 * (1 - alpha):g}% interval] (p)": "–" if r.is_reference else (
                   f"{fmt(r.failure_difference)}{_bracket(r.failure_difference_low, r.failure_difference_high)}"
                   f" ({fmt(r.failure_p)})")}
        for t in THRESHOLDS:
            k = int(round(t * 100))
            row[f"iterations to {k}%"] = f"{fmt(d[f'iterations_{k}'])} ({d[f'reached_{k}']}/{r.n_seeds})"
            row[f"speedup {k}% [{100 * (1 - alpha):g}% interval]"] = "–" if r.is_reference else _ratio_cell(
                d[f"speedup_{k}"], d[f"speedup_status_{k}"], d[f"speedup_low_{k}"], d[f"speedup_high_{k}"])
            if uniform is not None:
                row[f"vs uniform {k}%"] = _ratio_cell(d[f"vs_uniform_{k}"], d[f"vs_uniform_status_{k}"], math.nan,
                                                     math.nan)
        rows.append(row)
    md += ["Per level (iterations: Kaplan-Meier median, `–` = not reached by half the seeds; (reached/seeds)):", "",
           md_table(pd.DataFrame(rows)), ""]
    return md


__all__ = ["knob_section", "plot_sampling_at", "sampling_iterations", "write_knob_files"]
