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
from analysis.report_compute import ReportData
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
    opts, colors, bins, at, band = d.opts, d.colors, d.bins, d.at, d.band
    write_csv(out / "curves.csv", d.curves)
    figures = []
    for metric, (_, label) in tables.CURVE_METRICS.items():
        c = d.curves[d.curves["metric"] == metric] if len(d.curves) else d.curves
        if len(c):
            name = f"curve_{metric}.png"
            s = d.per_seed_curves[d.per_seed_curves["metric"] == metric]
            save_figure(out / name, plots.plot_learning_curve(c, label, colors=colors, per_seed=s,
                                                              title=f"IQM over seeds (mean below {MIN_SEEDS_IQM}); {band}; "
                                                                    "thin lines: seeds"))
            figures.append((name, f"Learning curve: {label}"))
    write_csv(out / "bin_failure.csv", d.bin_fail)
    save_figure(out / "bin_failure_heatmap.png", plots.plot_bin_heatmaps(d.bin_fail, FAILURE_RATE, bins=bins))
    figures.append(("bin_failure_heatmap.png", "Evaluated failure rate per bin, per visit, over training (mean over "
                                               "seeds; hatched: horizon-truncated)"))
    write_csv(out / "final_bin_failure.csv", d.final_bins)
    save_figure(out / "final_bin_failure.png", plots.plot_final_bin_failure(d.final_bins, bins=bins, colors=colors))
    figures.append(("final_bin_failure.png", f"Failure per bin, per visit, at {at} (dots: seeds; {band})"))
    if len(d.samp):
        write_csv(out / "sampling.csv", d.samp)
        save_figure(out / "sampling_distribution.png",
                    plots.plot_bin_heatmaps(d.samp, "probability", bins=bins, cmap="viridis", scale="per_panel"))
        figures.append(("sampling_distribution.png", "Sampling distribution over training, adaptive arms (mean over "
                        "seeds; each panel on its own colour scale, from 0 to its largest probability)"))
    write_csv(out / "mastery_per_seed.csv", d.mastery_seed_df)
    write_csv(out / "mastery.csv", d.mastery_df)
    save_figure(out / "mastery.png", plots.plot_mastery(d.mastery_df, d.mastery_seed_df, bins=bins, colors=colors,
                                                        threshold=opts.mastery_threshold))
    figures.append(("mastery.png", "Mastery iteration per bin (median over seeds; dots: seeds, x: not by then)"))
    write_csv(out / "time_to_threshold.csv", d.times)
    write_csv(out / "time_to_threshold_summary.csv", d.time_df)
    write_csv(out / "budget.csv", d.budget.assign(machine=d.budget["run_dir"].map(d.kinds)))
    write_csv(out / "summary.csv", d.summary)
    write_csv(out / "comparisons.csv", pd.concat([d.comp, d.comp_robust, *d.comp_errors.values()], ignore_index=True))
    if len(d.comp_base):
        write_csv(out / "baseline_comparisons.csv", d.comp_base)
    if len(d.errors):
        write_csv(out / "tracking_errors.csv", d.errors)
    if d.speed is not None:
        write_csv(out / "mastery_speedup.csv", d.per_bin)
        write_csv(out / "speedup.csv", d.speed)
        write_csv(out / "speedup_curve.csv", d.curve)
        write_csv(out / "iso_failure.csv", d.iso)
        assert d.dots is not None and d.iso is not None  # built with the speedups (report_compute)
        dots = d.dots[d.dots["measure"].isin(d.measures)]
        save_figure(out / "speedup.png", plots.plot_speedup(d.speed, dots, colors=colors))
        figures.append(("speedup.png", f"Speedup vs `{d.baseline}` at overall success ≥ {opts.success_threshold:g} "
                                       "(baseline / arm, > 1: arm faster; dots: baseline median / each arm seed)"))
        save_figure(out / "speedup_curve.png", curve_plots.plot_speedup_curve(d.curve, "iteration", colors=colors))
        figures.append(("speedup_curve.png", f"Speedup vs `{d.baseline}` in iterations over success thresholds"))
        if len(d.iso):
            save_figure(out / "iso_failure.png", curve_plots.plot_iso_failure(d.iso, "iteration", colors=colors))
            figures.append(("iso_failure.png", f"Iso-failure ratio vs `{d.baseline}` over training"))
    if len(d.seg):
        write_csv(out / "segment_failure.csv", d.seg)
    if len(d.clip_tab):
        write_csv(out / "clip_failure.csv", d.clip_tab)
    if len(d.support):
        write_csv(out / "sampling_support.csv", d.support)
        write_csv(out / "sampling_support_summary.csv", d.support_sum)
        write_csv(out / "sampler_signals.csv", d.signals)
        save_figure(out / "sampling_support.png", curve_plots.plot_sampling_support(d.support_sum, colors=colors))
        figures.append(("sampling_support.png", "Effective support and largest probability relative to uniform of "
                                                "the sampling distribution over training (mean over seeds)"))
        if d.clip_evals is not None and len(d.clip_evals):
            write_csv(out / "clip_eval.csv", d.clip_evals)
    if d.whole_clip is not None:
        w = d.whole_clip
        write_csv(out / "whole_clip_curves.csv", w.curves)
        write_csv(out / "whole_clip_final.csv", w.final)
        save_figure(out / "whole_clip_success.png", curve_plots.plot_whole_clip_success(w.curves, w.per_seed, colors))
        figures.append(("whole_clip_success.png", f"Whole-clip success over training per condition ({band}; thin "
                                                  "lines: seeds)"))
        if len(w.survival):
            write_csv(out / "whole_clip_survival.csv", w.survival)
            save_figure(out / "whole_clip_survival.png", curve_plots.plot_whole_clip_survival(w.survival, colors))
            figures.append(("whole_clip_survival.png", "Whole-clip rollouts still tracking over clip time, at each "
                                                       "run's last whole-clip evaluation (mean over seeds; band: range)"))
    if len(d.sens):
        write_csv(out / "sensitivity.csv", d.sens)
        for key in sorted(d.sens["key"].unique()):
            name = f"sensitivity_{key.replace('/', '_')}.png"
            save_figure(out / name, _sensitivity_figure(d.sens, key, d.ref, d.per_run))
            figures.append((name, f"Sensitivity to `{key}`"))
    if d.knob_levels is not None:
        figures += write_knob_files(d.knob_levels, d.knob_summary, d.overall, d.runs, d.bin_fail, d.samp, colors, bins,
                                    d.uniform_arm, opts, out)
    return figures


__all__ = ["write_files"]
