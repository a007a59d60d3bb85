"""The report's files: every CSV table and figure of a computed report (analysis.report_compute), each
written atomically (analysis.files). Returns the figures in the order report.md lists them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from analysis import curve_plots, plots, tables
from analysis.files import save_figure, write_csv
from analysis.knob_report import write_knob_files
from analysis.palette import arm_colors
from analysis.report_compute import ReportData
from analysis.report_views import at_text, band_text
from analysis.stats import MIN_SEEDS_IQM
from bmimic.runs.schema import FAILURE_RATE


def _sensitivity_figure(sens: pd.DataFrame, key: str, reference: dict, per_run: dict) -> Figure:
    metrics = [m for m in tables.SENSITIVITY_METRICS if m in set(sens["metric"])]
    fig = Figure(figsize=(3.5 * len(metrics), 3.2), layout="constrained")
    for ax, metric in zip(np.atleast_1d(fig.subplots(1, len(metrics))), metrics, strict=True):
        plots.plot_sensitivity(sens[sens["key"] == key], metric, ax=ax, reference=reference.get(metric),
                               per_seed=per_run.get(metric))
    return fig


def write_files(d: ReportData, out: Path) -> list[tuple[str, str]]:
    """Write the tables and figures of `d` into `out`; the figures as (file name, title)."""
    inp, cur, tab, arms = d.inputs, d.curves, d.bins, d.arms
    places, adapt, sens = d.places, d.adaptation, d.sensitivity
    opts, bins, at, band = inp.opts, tab.bins, at_text(inp), band_text(inp)
    colors = arm_colors(inp.runs["arm"].dropna())  # one colour per arm, in every figure
    write_csv(out / "curves.csv", cur.curves)
    figures = []
    for metric, (_, label) in tables.CURVE_METRICS.items():
        c = cur.curves[cur.curves["metric"] == metric] if len(cur.curves) else cur.curves
        if len(c):
            name = f"curve_{metric}.png"
            s = cur.per_seed_curves[cur.per_seed_curves["metric"] == metric]
            save_figure(out / name, plots.plot_learning_curve(c, label, colors=colors, per_seed=s,
                                                              title=f"IQM over seeds (mean below {MIN_SEEDS_IQM}); {band}; "
                                                                    "thin lines: seeds"))
            figures.append((name, f"Learning curve: {label}"))
    write_csv(out / "bin_failure.csv", tab.bin_fail)
    save_figure(out / "bin_failure_heatmap.png", plots.plot_bin_heatmaps(tab.bin_fail, FAILURE_RATE, bins=bins))
    figures.append(("bin_failure_heatmap.png", "Evaluated failure rate per bin, per visit, over training (mean over "
                                               "seeds; hatched: horizon-truncated)"))
    write_csv(out / "final_bin_failure.csv", tab.final_bins)
    save_figure(out / "final_bin_failure.png", plots.plot_final_bin_failure(tab.final_bins, bins=bins, colors=colors))
    figures.append(("final_bin_failure.png", f"Failure per bin, per visit, at {at} (dots: seeds; {band})"))
    if len(tab.samp):
        write_csv(out / "sampling.csv", tab.samp)
        save_figure(out / "sampling_distribution.png",
                    plots.plot_bin_heatmaps(tab.samp, "probability", bins=bins, cmap="viridis", scale="per_panel"))
        figures.append(("sampling_distribution.png", "Sampling distribution over training, adaptive arms (mean over "
                        "seeds; each panel on its own colour scale, from 0 to its largest probability)"))
    write_csv(out / "mastery_per_seed.csv", tab.mastery_seed_df)
    write_csv(out / "mastery.csv", tab.mastery_df)
    save_figure(out / "mastery.png", plots.plot_mastery(tab.mastery_df, tab.mastery_seed_df, bins=bins, colors=colors,
                                                        threshold=opts.mastery_threshold))
    figures.append(("mastery.png", "Mastery iteration per bin (median over seeds; dots: seeds, x: not by then)"))
    write_csv(out / "time_to_threshold.csv", arms.times)
    write_csv(out / "time_to_threshold_summary.csv", arms.time_df)
    write_csv(out / "budget.csv", cur.budget.assign(machine=cur.budget["run_dir"].map(inp.kinds)))
    write_csv(out / "summary.csv", arms.summary)
    write_csv(out / "comparisons.csv",
              pd.concat([arms.comp, arms.comp_robust, *arms.comp_errors.values()], ignore_index=True))
    if len(arms.comp_base):
        write_csv(out / "baseline_comparisons.csv", arms.comp_base)
    if len(arms.errors):
        write_csv(out / "tracking_errors.csv", arms.errors)
    sp = d.speedups
    if sp is not None:
        write_csv(out / "mastery_speedup.csv", sp.per_bin)
        write_csv(out / "speedup.csv", sp.speed)
        write_csv(out / "speedup_curve.csv", sp.curve)
        write_csv(out / "iso_failure.csv", sp.iso)
        dots = sp.dots[sp.dots["measure"].isin(inp.measures)]
        save_figure(out / "speedup.png", plots.plot_speedup(sp.speed, dots, colors=colors))
        figures.append(("speedup.png", f"Speedup vs `{inp.baseline}` at overall success ≥ {opts.success_threshold:g} "
                                       "(baseline / arm, > 1: arm faster; dots: baseline median / each arm seed)"))
        save_figure(out / "speedup_curve.png", curve_plots.plot_speedup_curve(sp.curve, "iteration", colors=colors))
        figures.append(("speedup_curve.png", f"Speedup vs `{inp.baseline}` in iterations over success thresholds"))
        if len(sp.iso):
            save_figure(out / "iso_failure.png", curve_plots.plot_iso_failure(sp.iso, "iteration", colors=colors))
            figures.append(("iso_failure.png", f"Iso-failure ratio vs `{inp.baseline}` over training"))
    if len(places.seg):
        write_csv(out / "segment_failure.csv", places.seg)
    if len(places.clip_tab):
        write_csv(out / "clip_failure.csv", places.clip_tab)
    if len(places.hardest_clips):
        write_csv(out / "hardest_clips.csv", places.hardest_clips)
        save_figure(out / "hardest_clips.png", curve_plots.plot_hardest_clips(places.hardest_clips, colors))
        n = places.hardest_clips["clip"].nunique()
        figures.append(("hardest_clips.png", f"Learning curves of the {n} hardest clips (highest final failure, mean "
                                             "over arms): failure per started episode by start clip (mean over "
                                             "seeds; thin lines: seeds)"))
    if len(adapt.support):
        write_csv(out / "sampling_support.csv", adapt.support)
        write_csv(out / "sampling_support_summary.csv", adapt.support_sum)
        write_csv(out / "sampler_signals.csv", adapt.signals)
        save_figure(out / "sampling_support.png", curve_plots.plot_sampling_support(adapt.support_sum, colors=colors))
        figures.append(("sampling_support.png", "Effective support and largest probability relative to uniform of "
                                                "the sampling distribution over training (mean over seeds)"))
        if adapt.clip_evals is not None and len(adapt.clip_evals):
            write_csv(out / "clip_eval.csv", adapt.clip_evals)
    if d.whole_clip is not None:
        w = d.whole_clip
        write_csv(out / "whole_clip_curves.csv", w.curves)
        write_csv(out / "whole_clip_final.csv", w.final)
        write_csv(out / "whole_clip_failure_places.csv", w.places)
        save_figure(out / "whole_clip_success.png", curve_plots.plot_whole_clip_success(w.curves, w.per_seed, colors))
        figures.append(("whole_clip_success.png", f"Whole-clip success over training per condition ({band}; thin "
                                                  "lines: seeds)"))
        if len(w.survival):
            write_csv(out / "whole_clip_survival.csv", w.survival)
            save_figure(out / "whole_clip_survival.png", curve_plots.plot_whole_clip_survival(w.survival, colors))
            figures.append(("whole_clip_survival.png", "Whole-clip rollouts still tracking over clip time, at each "
                                                       "run's last whole-clip evaluation (mean over seeds; band: range)"))
    if len(sens.sens):
        write_csv(out / "sensitivity.csv", sens.sens)
        for key in sorted(sens.sens["key"].unique()):
            name = f"sensitivity_{key.replace('/', '_')}.png"
            save_figure(out / name, _sensitivity_figure(sens.sens, key, sens.ref, arms.per_run))
            figures.append((name, f"Sensitivity to `{key}`"))
    if sens.knob_levels is not None:
        figures += write_knob_files(sens.knob_levels, sens.knob_summary, cur.overall, inp.runs, tab.bin_fail, tab.samp,
                                    colors, bins, sens.uniform_arm, opts, out, other_layouts=tab.other_layouts,
                                    clip_time=tab.clip_time)
    return figures


__all__ = ["write_files"]
