"""The report's numbers: the runs read and labelled, and every table the report's files and text are
made of (`ReportData`). Nothing here writes a file or a sentence (analysis.report_files writes,
analysis.report_views words)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from analysis import bin_tables, clip_tables, comparisons, tables, whole_clip
from analysis.adaptation import at_evaluations, sampling_support, signal_summary, support_summary
from analysis.knobs import knob_arms, knob_levels, knob_summary, knob_trends
from analysis.load import load_runs, load_segments, load_table, short_arm_labels
from analysis.machines import machine_kinds, wall_time_comparable
from analysis.metrics import (
    ERROR_METRICS,
    MEASURES,
    SMOOTHNESS_METRICS,
    bin_table,
    broken_episodes,
    tracking_errors,
)
from analysis.speedup_curve import iso_failure, speedup_curve
from analysis.stats import bootstrap_coverage
from analysis.tables import ReportOptions
from bmimic.runs.folder import portable_path
from bmimic.runs.schema import BIN, ITERATION, WALL_TIME_S


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
        runs[col] = runs[col].map(lambda p: portable_path(p) if isinstance(p, str) else p)
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
class Inputs:
    """What the report is of and how it reads: the runs, the options, the baseline, the
    machine kinds and the measures of time it may compare."""

    runs: pd.DataFrame
    opts: ReportOptions
    baseline: Any
    uniform_arms: list
    """The arms whose sampler is uniform, the baseline chosen among them (empty when --baseline named it)."""
    kinds: dict
    wall_ok: bool
    """Wall time may be compared: every run trained on one recorded machine kind."""
    measures: tuple
    seeds: dict
    final_iteration: Any
    """The evaluation the final numbers are read at: the last one every run has."""
    bootstrap: bool
    """Intervals are bootstrap intervals (every arm has enough seeds), else the range of the seeds."""
    final_read: tuple = ()
    """The iterations the runs are read at for ``final_iteration``: each run's last evaluation at or before
    it, so more than one when the runs evaluated on different schedules (a run stopped between two of
    another's evaluations)."""


@dataclass
class Curves:
    """Learning curves: the overall evaluation per run and iteration, per seed and over seeds; the budgets."""

    overall: pd.DataFrame
    per_seed_curves: pd.DataFrame
    curves: pd.DataFrame
    budget: pd.DataFrame


@dataclass
class Bins:
    """Per bin: the evaluation, failure over training and at the end, the sampling distribution, mastery."""

    eval_df: pd.DataFrame
    bins: pd.DataFrame
    bin_fail: pd.DataFrame
    final_bins: pd.DataFrame
    samp: pd.DataFrame
    mastery_seed_df: pd.DataFrame
    mastery_df: pd.DataFrame
    other_layouts: list = dataclasses.field(default_factory=list)
    """Arms cut into other bins than the baseline's (a bin-size knob): left out of every per-bin table and figure."""
    clip_time: pd.DataFrame = dataclasses.field(default_factory=pd.DataFrame)
    """With other layouts: every arm's final failure and sampling density per bin over clip time
    (bin_tables.over_clip_time), which arms of any layout share."""


@dataclass
class Arms:
    """Per run and per arm: final metrics, times to the success threshold, tracking errors, broken
    episodes, and the comparisons between arms and against the baseline."""

    per_run: Any
    summary: pd.DataFrame
    times: pd.DataFrame
    time_df: pd.DataFrame
    errors: pd.DataFrame
    broken: pd.DataFrame
    comp: pd.DataFrame
    comp_robust: pd.DataFrame
    comp_errors: dict
    comp_base: pd.DataFrame
    shown: dict
    """Tracking-error columns the runs have: column -> label."""
    smooth: dict
    """Smoothness columns the runs have: column -> label."""


@dataclass
class Speedups:
    """Against the baseline (two or more arms): time to the success threshold, per bin, over thresholds,
    iso-failure over training, and each seed's ratio."""

    speed: pd.DataFrame
    per_bin: pd.DataFrame
    curve: pd.DataFrame
    iso: pd.DataFrame
    dots: pd.DataFrame


@dataclass
class Places:
    """Failure per motion segment and per clip of a library."""

    seg: pd.DataFrame
    clip_tab: pd.DataFrame
    hardest_clips: pd.DataFrame
    """clip_tables.hardest_clip_curves: the hardest clips' failure at every evaluation (empty: one clip)."""


@dataclass
class Adaptation:
    """How the sampling distribution adapted: its support over training and the samplers' signals."""

    support: pd.DataFrame
    support_sum: pd.DataFrame
    signals: pd.DataFrame
    clip_evals: pd.DataFrame | None = None


@dataclass
class Sensitivity:
    """Metrics against a swept key's values, and the knob study's levels against uniform sampling."""

    sens: pd.DataFrame
    ref: dict
    knob_levels: pd.DataFrame | None = None
    knob_summary: pd.DataFrame | None = None
    uniform_arm: str | None = None


@dataclass
class ReportData:
    """Every table of one report, by section; each section is built in `compute` and read by the view and
    the files of that section. A section without anything is empty (one clip: no clip table) or None
    (one arm: no speedups; no whole-clip evaluation)."""

    inputs: Inputs
    curves: Curves
    bins: Bins
    arms: Arms
    places: Places
    adaptation: Adaptation
    sensitivity: Sensitivity
    speedups: Speedups | None = None
    whole_clip: whole_clip.WholeClipReport | None = None


def compute(runs: pd.DataFrame, opts: ReportOptions) -> ReportData:
    """Every table of the report of `runs` (those included): inputs first, then each section's tables from them."""
    baseline, uniform_arms = tables.choose_baseline(runs, opts.baseline)
    train, eval_df, sampler_df, robust_df = (load_table(runs, n, opts.max_iteration)
                                             for n in ("train_metrics", "eval", "sampler", "eval_robust"))
    segments = load_segments(runs)
    # Per-bin tables match bins by number: only arms cut into the baseline's bins share them; per-clip
    # tables only need each bin in the same clip.
    same_bins, other_bins = bin_tables.bin_layouts(eval_df, baseline)
    same_clips, other_clips = (bin_tables.bin_layouts(eval_df, baseline, ("clip",)) if "clip" in eval_df
                               else (same_bins, []))

    def of(df: pd.DataFrame, arms: list, others: list) -> pd.DataFrame:
        return df[df["arm"].isin(arms)] if others else df

    eval_bins, sampler_bins = of(eval_df, same_bins, other_bins), of(sampler_df, same_bins, other_bins)
    eval_clips, sampler_clips = of(eval_df, same_clips, other_clips), of(sampler_df, same_clips, other_clips)
    bins = bin_table(eval_bins, segments)
    kinds = machine_kinds(runs)
    wall_ok = wall_time_comparable(kinds)
    measures = MEASURES if wall_ok else tuple(m for m in MEASURES if m != WALL_TIME_S)
    overall = tables.overall(eval_df)
    robust_overall = tables.overall(robust_df) if len(robust_df) else None
    mastery_seed_df = bin_tables.mastery_seeds(eval_df, opts)
    mastery_bins = of(mastery_seed_df, same_bins, other_bins)
    mastery_all = bin_tables.mastery(mastery_seed_df, bins)  # per arm and bin; each layout's rows taken below
    mastery_df = of(mastery_all, same_bins, other_bins).reset_index(drop=True)
    times = bin_tables.run_times(overall, opts)
    time_df = bin_tables.time_summary(times)
    budget = tables.budgets(runs, train)
    errors = tracking_errors(eval_df)
    broken = broken_episodes(eval_df)
    per_run = tables.per_run_metrics(runs, overall, robust_overall, mastery_seed_df, budget, errors, broken)
    summary = tables.summary(per_run, runs, opts)
    overview = tables.arm_overview(summary, time_df)
    common = tables.common_budget(overall)
    per_seed_curves = tables.seed_curves(train, overall, opts, errors)
    curves = tables.learning_curves(per_seed_curves, runs, opts)
    bin_fail = bin_tables.bin_failure(eval_bins)
    final_bins = bin_tables.final_bin_failure(eval_bins, runs, opts).merge(bins[[BIN, "segment"]], on=BIN, how="left")
    samp = bin_tables.sampling(sampler_bins, runs)
    comp = comparisons.comparisons(per_run, "final_failure", opts)
    comp_robust = comparisons.comparisons(per_run, "final_failure_robust", opts)
    shown = {c: label for c, label in ERROR_METRICS.items() if f"final_{c}" in per_run}
    smooth = {c: label for c, label in SMOOTHNESS_METRICS.items() if f"final_{c}" in per_run}
    comp_errors = {c: comparisons.comparisons(per_run, f"final_{c}", opts) for c in (*shown, *smooth)}
    comp_base = comparisons.baseline_comparisons(per_run, "final_failure", baseline, opts)
    clips = clip_tables.bin_clips(eval_clips)
    support = sampling_support(sampler_clips if len(clips) else sampler_df, clips if len(clips) else None)
    support_eval = at_evaluations(support, overall[["run_dir", ITERATION]]) if len(support) else support
    support_sum = support_summary(support_eval) if len(support_eval) else pd.DataFrame()
    signals = signal_summary(support) if len(support) else pd.DataFrame()
    speedups = None
    if baseline is not None and runs.loc[runs["included"], "arm"].nunique() > 1:
        speed, per_bin = bin_tables.speedups(times, mastery_bins, baseline, runs, opts)
        speedups = Speedups(speed[speed["measure"].isin(measures)].reset_index(drop=True), per_bin,
                            speedup_curve(overall, baseline, runs, opts), iso_failure(overall, baseline),
                            bin_tables.speedup_per_seed(times, baseline))
    seeds = tables.seeds_per_arm(runs).to_dict()
    seg = bin_tables.segment_failure(eval_bins, bins, mastery_df, segments, runs, opts)
    clip_tab = clip_tables.clip_failure(eval_clips, sampler_clips, of(mastery_all, same_clips, other_clips), runs, opts)
    adaptation = Adaptation(support, support_sum, signals,
                            load_table(runs, "clip_eval", opts.max_iteration) if len(support) else None)
    whole = whole_clip.compute(runs, opts)
    sens = tables.sensitivity(runs, overview)
    ref = {}
    if len(sens) and baseline is not None and baseline in set(overview["arm"]):
        b = overview.set_index("arm").loc[baseline]
        ref = {m: {f"{baseline} (baseline)": float(b[m])} for m in tables.SENSITIVITY_METRICS if m in b}
    sensitivity = Sensitivity(sens, ref)
    knobs = knob_arms(runs)
    if len(knobs) and "final_failure" in per_run:
        uniform = sorted(set(runs.loc[runs["included"] & (runs["sampler"] == "uniform"), "arm"]))
        sensitivity.uniform_arm = uniform[0] if len(uniform) == 1 else None
        sensitivity.knob_levels = knob_levels(knobs, per_run["final_failure"], overall, opts, sensitivity.uniform_arm)
        sensitivity.knob_summary = knob_summary(sensitivity.knob_levels, opts.alpha,
                                                knob_trends(knobs, per_run["final_failure"], opts))
    return ReportData(
        inputs=Inputs(runs, opts, baseline, uniform_arms, kinds, wall_ok, measures, seeds, common[ITERATION],
                      tables.use_bootstrap(runs),
                      tuple(sorted(tables.final_overall(overall)[ITERATION].unique().tolist()))),
        curves=Curves(overall, per_seed_curves, curves, budget),
        bins=Bins(eval_df, bins, bin_fail, final_bins, samp, mastery_seed_df, mastery_df, other_bins,
                  bin_tables.over_clip_time(eval_df, sampler_df) if other_bins else pd.DataFrame()),
        arms=Arms(per_run, summary, times, time_df, errors, broken, comp, comp_robust, comp_errors, comp_base, shown,
                  smooth),
        places=Places(seg, clip_tab, clip_tables.hardest_clip_curves(eval_clips, clip_tab)), adaptation=adaptation, sensitivity=sensitivity, speedups=speedups,
        whole_clip=whole)


__all__ = ["Adaptation", "Arms", "Bins", "Curves", "Inputs", "Places", "ReportData", "Runs", "Sensitivity", "Speedups",
           "compute", "read_runs"]
