"""The report's numbers: the runs read and labelled, and every table the report's files and text are
made of (`ReportData`). Nothing here writes a file or a sentence (analysis.report_files writes,
analysis.report_views words)."""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from analysis import bin_tables, clip_tables, comparisons, tables, whole_clip
from analysis.adaptation import at_evaluations, sampling_support, signal_summary, support_summary
from analysis.knobs import knob_arms, knob_levels, knob_summary
from analysis.load import load_runs, load_segments, load_table, short_arm_labels
from analysis.machines import kinds_text, machine_kinds, wall_time_comparable
from analysis.markdown import fmt
from analysis.metrics import (
    ERROR_METRICS,
    MEASURES,
    SMOOTHNESS_METRICS,
    bin_table,
    broken_episodes,
    tracking_errors,
)
from analysis.plots import arm_colors
from analysis.speedup_curve import iso_failure, speedup_curve
from analysis.stats import bootstrap_coverage
from analysis.tables import ReportOptions
from bmimic.runs.schema import BIN, ITERATION, WALL_TIME_S


def _portable_path(path):
    """``path`` relative to the working directory when it lies below it, else unchanged."""
    if not isinstance(path, str):
        return path
    return os.path.relpath(path) if Path(path).is_relative_to(Path.cwd()) else path


@dataclass
class Runs:
    """The runs of a report, read and labelled."""

    runs: pd.DataFrame
    """One row per run (load.load_runs), arms relabelled by their differing overrides."""
    opts: ReportOptions
    """The options, the baseline named by its label."""
    shared: list
    """The overrides every arm shares (left out of the labels)."""
    coverage: tuple | None
    """(fewest seeds per arm, simulated coverage of a nominal bootstrap interval) when intervals are drawn."""


def read_runs(paths: list[Path], opts: ReportOptions, allow_mixed: bool = False) -> Runs:
    """The runs under `paths`, cut at the common budget and labelled by the overrides that differ."""
    runs = load_runs(paths, allow_mixed=allow_mixed)
    if opts.max_iteration is not None:  # a common budget: longer runs are read as if they had stopped there
        runs[ITERATION] = runs[ITERATION].clip(upper=opts.max_iteration)
    for col in ("run_dir", "sweep_dir"):  # the tables travel (docs/, other machines): no absolute paths from here
        runs[col] = runs[col].map(_portable_path)
    labels, shared = short_arm_labels(runs["arm"])
    runs["arm_overrides"] = runs["arm"]
    runs["arm"] = runs["arm"].map(lambda a: labels.get(a, a))
    if opts.baseline in labels:
        opts = dataclasses.replace(opts, baseline=labels[opts.baseline])
    fewest = int(tables.seeds_per_arm(runs).min()) if runs["included"].any() else 0
    coverage = ((fewest, bootstrap_coverage(fewest, n_resamples=opts.n_resamples, confidence=opts.confidence,
                                            seed=opts.bootstrap_seed))
                if tables.use_bootstrap(runs) else None)
    return Runs(runs, opts, shared, coverage)


@dataclass
class ReportData:
    """Every table of one report, by section: inputs and budget, curves and bins, comparisons, speedups,
    tracking, segments and clips, adaptation, sensitivity. Each attribute is the frame (or value) the
    function named beside its computation in `compute` returns; `None` or empty where a section has
    nothing (one arm: no speedups; one clip: no clip table)."""

    runs: pd.DataFrame
    opts: ReportOptions
    baseline: Any
    baseline_note: str
    eval_df: pd.DataFrame
    bins: pd.DataFrame
    colors: dict
    kinds: dict
    machines: str
    measures: tuple
    overall: pd.DataFrame
    mastery_seed_df: pd.DataFrame
    mastery_df: pd.DataFrame
    times: pd.DataFrame
    time_df: pd.DataFrame
    budget: pd.DataFrame
    errors: pd.DataFrame
    broken: pd.DataFrame
    per_run: Any
    summary: pd.DataFrame
    at: str
    per_seed_curves: pd.DataFrame
    curves: pd.DataFrame
    band: str
    bin_fail: pd.DataFrame
    final_bins: pd.DataFrame
    samp: pd.DataFrame
    comp: pd.DataFrame
    comp_robust: pd.DataFrame
    shown: dict
    smooth: dict
    comp_errors: dict
    comp_base: pd.DataFrame
    support: pd.DataFrame
    support_sum: pd.DataFrame
    signals: pd.DataFrame
    seg: pd.DataFrame
    clip_tab: pd.DataFrame
    sens: pd.DataFrame
    ref: dict
    seeds: dict
    speed: pd.DataFrame | None = None
    per_bin: pd.DataFrame | None = None
    curve: pd.DataFrame | None = None
    iso: pd.DataFrame | None = None
    dots: pd.DataFrame | None = None
    clip_evals: pd.DataFrame | None = None
    knob_levels: pd.DataFrame | None = None
    knob_summary: pd.DataFrame | None = None
    uniform_arm: str | None = None
    whole_clip: whole_clip.WholeClipReport | None = None


def compute(runs: pd.DataFrame, opts: ReportOptions) -> ReportData:
    """Every table of the report of `runs` (some included), in the order the report has always made them."""
    baseline, baseline_note = tables.choose_baseline(runs, opts.baseline)
    train, eval_df, sampler_df, robust_df = (load_table(runs, n, opts.max_iteration)
                                             for n in ("train_metrics", "eval", "sampler", "eval_robust"))
    segments = load_segments(runs)
    bins = bin_table(eval_df, segments)
    colors = arm_colors(runs["arm"].dropna())
    kinds = machine_kinds(runs)
    wall_ok = wall_time_comparable(kinds)
    machines = "" if wall_ok else (
        "Wall time is not compared (no wall-time speedup is printed, and the Arms table leaves wall time out): "
        f"the runs trained on different or unrecorded machine kinds ({kinds_text(runs, kinds)}).")
    measures = MEASURES if wall_ok else tuple(m for m in MEASURES if m != WALL_TIME_S)
    overall = tables.overall(eval_df)
    robust_overall = tables.overall(robust_df) if len(robust_df) else None
    mastery_seed_df = bin_tables.mastery_seeds(eval_df, opts)
    mastery_df = bin_tables.mastery(mastery_seed_df, bins)
    times = bin_tables.run_times(overall, opts)
    time_df = bin_tables.time_summary(times)
    budget = tables.budgets(runs, train)
    errors = tracking_errors(eval_df)
    broken = broken_episodes(eval_df)
    per_run = tables.per_run_metrics(runs, overall, robust_overall, mastery_seed_df, budget, errors, broken)
    summary = tables.summary(per_run, runs, opts)
    overview = tables.arm_overview(summary, time_df)
    common = tables.common_budget(overall)
    at = f"iteration {fmt(common[ITERATION])}, the last evaluation every run has"
    per_seed_curves = tables.seed_curves(train, overall, opts, errors)
    curves = tables.learning_curves(per_seed_curves, runs, opts)
    band = ("band: bootstrap interval" if tables.use_bootstrap(runs) else "band: range of the seeds")
    bin_fail = bin_tables.bin_failure(eval_df)
    final_bins = bin_tables.final_bin_failure(eval_df, runs, opts).merge(bins[[BIN, "segment"]], on=BIN, how="left")
    samp = bin_tables.sampling(sampler_df, runs)
    comp = comparisons.comparisons(per_run, "final_failure", opts)
    comp_robust = comparisons.comparisons(per_run, "final_failure_robust", opts)
    shown = {c: label for c, label in ERROR_METRICS.items() if f"final_{c}" in per_run}
    smooth = {c: label for c, label in SMOOTHNESS_METRICS.items() if f"final_{c}" in per_run}
    comp_errors = {c: comparisons.comparisons(per_run, f"final_{c}", opts) for c in (*shown, *smooth)}
    comp_base = comparisons.baseline_comparisons(per_run, "final_failure", baseline, opts)
    clips = clip_tables.bin_clips(eval_df)
    support = sampling_support(sampler_df, clips if len(clips) else None)
    support_eval = at_evaluations(support, sorted(overall[ITERATION].unique())) if len(support) else support
    support_sum = support_summary(support_eval) if len(support_eval) else pd.DataFrame()
    signals = signal_summary(support) if len(support) else pd.DataFrame()
    extra = {}
    if baseline is not None and runs.loc[runs["included"], "arm"].nunique() > 1:
        speed, per_bin = bin_tables.speedups(times, mastery_seed_df, baseline, runs, opts)
        extra = {"speed": speed[speed["measure"].isin(measures)].reset_index(drop=True), "per_bin": per_bin,
                 "curve": speedup_curve(overall, baseline, runs, opts), "iso": iso_failure(overall, baseline),
                 "dots": bin_tables.speedup_per_seed(times, baseline)}
    seeds = tables.seeds_per_arm(runs).to_dict()
    seg = bin_tables.segment_failure(eval_df, bins, mastery_df, segments, runs, opts)
    clip_tab = clip_tables.clip_failure(eval_df, sampler_df, mastery_df, runs, opts)
    if len(support):
        extra["clip_evals"] = load_table(runs, "clip_eval", opts.max_iteration)
    whole = whole_clip.compute(runs, opts)
    if whole is not None:
        extra["whole_clip"] = whole
    sens = tables.sensitivity(runs, overview)
    knobs = knob_arms(runs)
    if len(knobs) and "final_failure" in per_run:
        uniform = sorted(set(runs.loc[runs["included"] & (runs["sampler"] == "uniform"), "arm"]))
        extra["uniform_arm"] = uniform[0] if len(uniform) == 1 else None
        extra["knob_levels"] = knob_levels(knobs, per_run["final_failure"], overall, opts, extra["uniform_arm"])
        extra["knob_summary"] = knob_summary(extra["knob_levels"], opts.alpha)
    ref = {}
    if len(sens) and baseline is not None and baseline in set(overview["arm"]):
        b = overview.set_index("arm").loc[baseline]
        ref = {m: {f"{baseline} (baseline)": float(b[m])} for m in tables.SENSITIVITY_METRICS if m in b}
    return ReportData(runs, opts, baseline, baseline_note, eval_df, bins, colors, kinds, machines, measures, overall,
                      mastery_seed_df, mastery_df, times, time_df, budget, errors, broken, per_run, summary, at,
                      per_seed_curves, curves, band, bin_fail, final_bins, samp, comp, comp_robust, shown, smooth,
                      comp_errors, comp_base, support, support_sum, signals, seg, clip_tab, sens, ref, seeds, **extra)


__all__ = ["ReportData", "Runs", "compute", "read_runs"]
