"""``python -m analysis.report PATH [PATH ...]``: figures, CSV tables and report.md for a sweep.

PATH is a sweep folder, a run folder, or any folder holding run folders (e.g. a study's committed
``docs/results/<study>/runs/``). The report goes to ``--out``, else ``<PATH>/report/`` for one
PATH, else ``report/`` in the folder the paths share. Failed, missing and unfinished jobs are
listed, never fatal; running jobs with tables are included and marked. See analysis.metrics for the
definitions and analysis.stats for the statistics the report uses.

Machine-readable outputs: ``summary.csv`` (tables.SUMMARY_COLUMNS), ``speedup.csv``
(tables.SPEEDUP_COLUMNS), ``speedup_curve.csv`` and ``iso_failure.csv`` (analysis.speedup_curve),
``baseline_comparisons.csv`` (with Holm's adjusted p), ``sampling_support.csv`` (analysis.adaptation),
plus per-seed and per-bin tables beside them.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from analysis import AnalysisError, bin_tables, clip_tables, comparisons, curve_plots, plots, tables
from analysis.adaptation import at_evaluations, sampling_support, signal_summary, support_summary
from analysis.curve_text import adaptation_section, curve_view, iso_text, speedup_curve_text
from analysis.definitions import definitions
from analysis.files import save_figure, write_csv, write_text
from analysis.inputs import MIXED_FLAG, check_options
from analysis.load import load_runs, load_segments, load_table, short_arm_labels
from analysis.machines import kinds_text, machine_kinds, wall_time_comparable
from analysis.markdown import (
    FAILURE_UNIT,
    NOT_RECORDED,
    arms_view,
    baseline_text,
    budget_section,
    evaluation_notes,
    fmt,
    mastery_view,
    md_table,
    plural,
    runs_section,
    segment_view,
    speed_view,
    tracking_view,
    winner_text,
)
from analysis.metrics import (
    ERROR_METRICS,
    MEASURES,
    SMOOTHNESS_METRICS,
    bin_table,
    broken_episodes,
    tracking_errors,
)
from analysis.speedup_curve import iso_failure, speedup_curve
from analysis.stats import MIN_SEEDS_IQM, bootstrap_coverage
from analysis.tables import ReportOptions
from bmimic import BmimicError
from bmimic.run_schema import JOINT_VEL_ERR_RADPS, MPKPE_REL_MM

TRACKING_HEADLINE = (MPKPE_REL_MM, JOINT_VEL_ERR_RADPS)
"""Tracking errors the Tracking quality section compares between arms in words (position and velocity
tracking; the policy's smoothness is SMOOTHNESS_METRICS, compared in its own block)."""


def default_out(paths: list[Path]) -> Path:
    """Where the report goes without --out: beside the runs (``<sweep>/report``)."""
    if len(paths) == 1:
        return paths[0] / "report"
    return Path(os.path.commonpath([str(p.resolve()) for p in paths])) / "report"


def _portable_path(path):
    """``path`` relative to the working directory when it lies below it, else unchanged."""
    if not isinstance(path, str):
        return path
    return os.path.relpath(path) if Path(path).is_relative_to(Path.cwd()) else path


def _sensitivity_figure(sens: pd.DataFrame, key: str, reference: dict, per_run: dict) -> Figure:
    metrics = [m for m in tables.SENSITIVITY_METRICS if m in set(sens["metric"])]
    fig = Figure(figsize=(3.5 * len(metrics), 3.2), layout="constrained")
    for ax, metric in zip(np.atleast_1d(fig.subplots(1, len(metrics))), metrics, strict=True):
        plots.plot_sensitivity(sens[sens["key"] == key], metric, ax=ax, reference=reference.get(metric),
                               per_seed=per_run.get(metric))
    return fig


def build_report(paths, out: str | Path | None = None, opts: ReportOptions | None = None,
                 allow_mixed: bool = False) -> Path:
    """Load the runs under ``paths``, write every figure, table and report.md to ``out``; return ``out``.
    ``allow_mixed``: compare runs of different motions or bin layouts (else refused)."""
    opts = opts or ReportOptions()
    paths = [Path(p) for p in ([paths] if isinstance(paths, str | Path) else paths)]
    out = Path(out) if out is not None else default_out(paths)
    if out.exists() and not out.is_dir():
        raise AnalysisError(f"--out {out}: is a file, not a folder")
    runs = load_runs(paths, allow_mixed=allow_mixed)
    if opts.max_iteration is not None:  # a common budget: longer runs are read as if they had stopped there
        runs["iteration"] = runs["iteration"].clip(upper=opts.max_iteration)
    for col in ("run_dir", "sweep_dir"):  # the tables travel (docs/, other machines): no absolute paths from here
        runs[col] = runs[col].map(_portable_path)
    labels, shared = short_arm_labels(runs["arm"])
    runs["arm_overrides"] = runs["arm"]
    runs["arm"] = runs["arm"].map(lambda a: labels.get(a, a))
    if opts.baseline in labels:
        opts = dataclasses.replace(opts, baseline=labels[opts.baseline])
    write_csv(out / "runs.csv", runs)
    fewest = int(tables.seeds_per_arm(runs).min()) if runs["included"].any() else 0
    coverage = ((fewest, bootstrap_coverage(fewest, n_resamples=opts.n_resamples, confidence=opts.confidence,
                                            seed=opts.bootstrap_seed))
                if tables.use_bootstrap(runs) else None)
    md = ["# bmimic report", "", f"Inputs: {', '.join(f'`{p}`' for p in paths)}  ",
          f"Mastery: per-visit bin failure < {opts.mastery_threshold:g} at "
          f"{plural(opts.mastery_persist, 'consecutive evaluation')} (or to the end of the run); success threshold: "
          f"overall success ≥ {opts.success_threshold:g} (the speedup curve covers 0.5–0.99). Failure unit: "
          f"{FAILURE_UNIT}, except per-bin rates (per visit).  ",
          f"Statistics: point = IQM over seeds from {MIN_SEEDS_IQM} seeds, else the mean (labelled); "
          f"{tables.interval_label(runs, opts)}"
          + (f" (a nominal {opts.confidence:.0%} BCa interval at {coverage[0]} seeds covers {coverage[1]:.0%}, "
             "simulated on normal data)" if coverage else "")
          + f"; differences: two-sided permutation tests of the difference of means, claimed at p < {opts.alpha:g}, "
          "uncorrected unless marked Holm.", ""]
    if opts.max_iteration is not None:
        md[-1:-1] = [f"Budget: every run is read up to iteration {opts.max_iteration} (`--max-iteration`), as if it "
                     "had stopped there; its later rows are left out of every number and figure.  "]
    if shared:
        md += [f"Arms are named by the overrides that differ between them; all share `{','.join(shared)}`.", ""]
    md += runs_section(runs)
    if not runs["included"].any():
        md += ["No run has usable tables yet; nothing else to report."]
        write_text(out / "report.md", "\n".join(md) + "\n")
        return out

    baseline, baseline_note = tables.choose_baseline(runs, opts.baseline)
    train, eval_df, sampler_df, robust_df = (load_table(runs, n, opts.max_iteration)
                                             for n in ("train_metrics", "eval", "sampler", "eval_robust"))
    segments = load_segments(runs)
    bins = bin_table(eval_df, segments)
    colors = plots.arm_colors(runs["arm"].dropna())
    kinds = machine_kinds(runs)
    wall_ok = wall_time_comparable(kinds)
    machines = "" if wall_ok else (
        "Wall time is not compared (no wall-time speedup is printed, and the Arms table leaves wall time out): "
        f"the runs trained on different or unrecorded machine kinds ({kinds_text(runs, kinds)}).")
    measures = MEASURES if wall_ok else tuple(m for m in MEASURES if m != "wall_time_s")
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
    at = f"iteration {fmt(common['iteration'])}, the last evaluation every run has"

    md += budget_section(budget, opts, kinds, machines)
    md += evaluation_notes(eval_df, bins)

    per_seed_curves = tables.seed_curves(train, overall, opts, errors)
    curves = tables.learning_curves(per_seed_curves, runs, opts)
    write_csv(out / "curves.csv", curves)
    figures = []
    band = ("band: bootstrap interval" if tables.use_bootstrap(runs) else "band: range of the seeds")
    for metric, (_, label) in tables.CURVE_METRICS.items():
        c = curves[curves["metric"] == metric] if len(curves) else curves
        if len(c):
            name = f"curve_{metric}.png"
            s = per_seed_curves[per_seed_curves["metric"] == metric]
            save_figure(out / name, plots.plot_learning_curve(c, label, colors=colors, per_seed=s,
                                                              title=f"IQM over seeds (mean below {MIN_SEEDS_IQM}); {band}; "
                                                                    "thin lines: seeds"))
            figures.append((name, f"Learning curve: {label}"))

    bin_fail = bin_tables.bin_failure(eval_df)
    write_csv(out / "bin_failure.csv", bin_fail)
    save_figure(out / "bin_failure_heatmap.png", plots.plot_bin_heatmaps(bin_fail, "failure_rate", bins=bins))
    figures.append(("bin_failure_heatmap.png", "Evaluated failure rate per bin, per visit, over training (mean over "
                                               "seeds; hatched: horizon-truncated)"))
    final_bins = bin_tables.final_bin_failure(eval_df, runs, opts).merge(bins[["bin", "segment"]], on="bin", how="left")
    write_csv(out / "final_bin_failure.csv", final_bins)
    save_figure(out / "final_bin_failure.png", plots.plot_final_bin_failure(final_bins, bins=bins, colors=colors))
    figures.append(("final_bin_failure.png", f"Failure per bin, per visit, at {at} (dots: seeds; {band})"))

    samp = bin_tables.sampling(sampler_df, runs)
    if len(samp):
        write_csv(out / "sampling.csv", samp)
        save_figure(out / "sampling_distribution.png",
                    plots.plot_bin_heatmaps(samp, "probability", bins=bins, cmap="viridis",
                                            scale="per_panel"))
        figures.append(("sampling_distribution.png", "Sampling distribution over training, adaptive arms (mean over seeds; each panel on its own colour "
                        "scale, from 0 to its largest probability)"))

    write_csv(out / "mastery_per_seed.csv", mastery_seed_df)
    write_csv(out / "mastery.csv", mastery_df)
    save_figure(out / "mastery.png", plots.plot_mastery(mastery_df, mastery_seed_df, bins=bins, colors=colors,
                                                        threshold=opts.mastery_threshold))
    figures.append(("mastery.png", "Mastery iteration per bin (median over seeds; dots: seeds, x: not by then)"))
    write_csv(out / "time_to_threshold.csv", times)
    write_csv(out / "time_to_threshold_summary.csv", time_df)
    write_csv(out / "budget.csv", budget.assign(machine=budget["run_dir"].map(kinds)))
    write_csv(out / "summary.csv", summary)
    comp = comparisons.comparisons(per_run, "final_failure", opts)
    comp_robust = comparisons.comparisons(per_run, "final_failure_robust", opts)
    shown = {c: label for c, label in ERROR_METRICS.items() if f"final_{c}" in per_run}
    smooth = {c: label for c, label in SMOOTHNESS_METRICS.items() if f"final_{c}" in per_run}
    comp_errors = {c: comparisons.comparisons(per_run, f"final_{c}", opts) for c in (*shown, *smooth)}
    write_csv(out / "comparisons.csv", pd.concat([comp, comp_robust, *comp_errors.values()], ignore_index=True))
    comp_base = comparisons.baseline_comparisons(per_run, "final_failure", baseline, opts)
    if len(comp_base):
        write_csv(out / "baseline_comparisons.csv", comp_base)
    if len(errors):
        write_csv(out / "tracking_errors.csv", errors)

    clips = clip_tables.bin_clips(eval_df)
    support = sampling_support(sampler_df, clips if len(clips) else None)
    support_eval = at_evaluations(support, sorted(overall["iteration"].unique())) if len(support) else support
    support_sum = support_summary(support_eval) if len(support_eval) else pd.DataFrame()
    signals = signal_summary(support) if len(support) else pd.DataFrame()

    md += ["## Summary", "", *winner_text(comp, summary, "final_failure", f"Final overall failure ({FAILURE_UNIT})",
                                          at, opts, noun="final overall failure")]
    if "final_failure_robust" in per_run:
        md += winner_text(comp_robust, summary, "final_failure_robust",
                           "Final overall failure, robust evaluation (DR, noise, pushes)", "last evaluation", opts)
    md += baseline_text(comp_base, summary, "final_failure", "Final overall failure", at, opts)
    md.append(f"- Speedups: {baseline_note}.")
    speed = curve = None
    if baseline is not None and runs.loc[runs["included"], "arm"].nunique() > 1:
        speed, per_bin = bin_tables.speedups(times, mastery_seed_df, baseline, runs, opts)
        speed = speed[speed["measure"].isin(measures)].reset_index(drop=True)
        curve = speedup_curve(overall, baseline, runs, opts)
        iso = iso_failure(overall, baseline)
        write_csv(out / "mastery_speedup.csv", per_bin)
        write_csv(out / "speedup.csv", speed)
        write_csv(out / "speedup_curve.csv", curve)
        write_csv(out / "iso_failure.csv", iso)
        dots = bin_tables.speedup_per_seed(times, baseline)
        save_figure(out / "speedup.png", plots.plot_speedup(speed, dots[dots["measure"].isin(measures)], colors=colors))
        figures.append(("speedup.png", f"Speedup vs `{baseline}` at overall success ≥ {opts.success_threshold:g} "
                                       "(baseline / arm, > 1: arm faster; dots: baseline median / each arm seed)"))
        save_figure(out / "speedup_curve.png", curve_plots.plot_speedup_curve(curve, "iteration", colors=colors))
        figures.append(("speedup_curve.png", f"Speedup vs `{baseline}` in iterations over success thresholds"))
        if len(iso):
            save_figure(out / "iso_failure.png", curve_plots.plot_iso_failure(iso, "iteration", colors=colors))
            figures.append(("iso_failure.png", f"Iso-failure ratio vs `{baseline}` over training"))
        md += speedup_curve_text(curve, speed, per_bin, time_df, opts, machines)
        md += iso_text(iso)
    if len(signals) and signals["degenerate"].any():
        md.append("- Degenerate sampler signals (see Adaptation): "
                  + ", ".join(f"`{a}`" for a in signals.loc[signals["degenerate"], "arm"]) + ".")
    md += ["", "## Arms", "", md_table(arms_view(summary, time_df, per_run, at, measures)), ""]
    seeds = tables.seeds_per_arm(runs).to_dict()
    if shown or smooth or len(broken):
        md += ["## Tracking quality", "", f"Step-weighted mean errors of the evaluation at {at}, over the steps the "
               "evaluation episodes were alive (an arm that fails more is measured over fewer steps); lower is "
               "better.", "", md_table(tracking_view(summary, {f"final_{c}": lab for c, lab in shown.items()}, seeds)),
               ""]
        for c in TRACKING_HEADLINE:
            if c in comp_errors:
                md += winner_text(comp_errors[c], summary, f"final_{c}", shown[c][0].upper() + shown[c][1:], at, opts,
                                  noun=shown[c])
        md += ["", "### Smoothness of the policy", "", "The policy's own action rate and joint acceleration at the "
               f"same evaluation ({at}) and the episodes whose world broke over all evaluations (each also a "
               "failure); lower is smoother. Joint-velocity error above is a tracking error, not smoothness. "
               f"\"{NOT_RECORDED}\": the runs' evaluation tables predate these columns.", "",
               md_table(tracking_view(summary, {**{f"final_{c}": lab for c, lab in SMOOTHNESS_METRICS.items()},
                                                "broken_episodes": "broken episodes (count, all evaluations)"},
                                      seeds)), ""]
        for c in smooth:
            md += winner_text(comp_errors[c], summary, f"final_{c}", smooth[c][0].upper() + smooth[c][1:], at, opts,
                              noun=smooth[c])
        md.append("")

    seg = bin_tables.segment_failure(eval_df, bins, mastery_df, segments, runs, opts)
    if len(seg):
        write_csv(out / "segment_failure.csv", seg)
        md += ["## Segments", "", f"Failure per motion segment at {at}, in the unit of the overall failure "
               f"({FAILURE_UNIT}, each episode charged to the segment it started in); bins not mastered: median "
               "mastery over seeds not reached.", "", md_table(segment_view(seg)), ""]

    clip_tab = clip_tables.clip_failure(eval_df, sampler_df, mastery_df, runs, opts)
    if len(clip_tab):
        write_csv(out / "clip_failure.csv", clip_tab)
        md += ["## Clips", "", f"Per clip of the motion library at {at}: failure in the unit of the overall failure "
               f"({FAILURE_UNIT}, each episode charged to the clip it started in, so the overall failure is their "
               "mean weighted by started episodes); bins not mastered: median mastery over seeds not reached; "
               "sampling probability mass: the training sampler's probability on the clip's bins, the mean over "
               "its logged iterations and seeds, the same quantity for every sampler.", "",
               md_table(clip_tables.clip_view(clip_tab)), ""]
        unused = clip_tables.never_started(clip_tab)
        md += [f"- No sampling probability at any logged iteration: {', '.join(unused)}." if unused else
               "- Every arm gave every clip sampling probability.", ""]

    if len(support):
        write_csv(out / "sampling_support.csv", support)
        write_csv(out / "sampling_support_summary.csv", support_sum)
        write_csv(out / "sampler_signals.csv", signals)
        save_figure(out / "sampling_support.png", curve_plots.plot_sampling_support(support_sum, colors=colors))
        figures.append(("sampling_support.png", "Effective support and largest probability relative to uniform of "
                                                "the sampling distribution over training (mean over seeds)"))
        clip_evals = load_table(runs, "clip_eval", opts.max_iteration)
        if len(clip_evals):
            write_csv(out / "clip_eval.csv", clip_evals)
        md += adaptation_section(support_sum, signals, clip_evals)

    sens = tables.sensitivity(runs, overview)
    if len(sens):
        write_csv(out / "sensitivity.csv", sens)
        ref = {}
        if baseline is not None and baseline in set(overview["arm"]):
            b = overview.set_index("arm").loc[baseline]
            ref = {m: {f"{baseline} (baseline)": float(b[m])} for m in tables.SENSITIVITY_METRICS if m in b}
        md += ["## Sensitivity", ""]
        for key in sorted(sens["key"].unique()):
            name = f"sensitivity_{key.replace('/', '_')}.png"
            save_figure(out / name, _sensitivity_figure(sens, key, ref, per_run))
            figures.append((name, f"Sensitivity to `{key}`"))
            view = sens[(sens["key"] == key)].pivot_table(index=["value", "series"], columns="metric", values="point")
            md += [f"`{key}`:", "", md_table(view.reset_index()), ""]

    if speed is not None:
        md += ["## Speedup", "", f"At overall success ≥ {opts.success_threshold:g} (ratio = baseline median / arm "
               "median; p: Gehan permutation test, uncorrected):", "", md_table(speed_view(speed, time_df)), ""]
        md += ["Over success thresholds (iterations; speedup_curve.csv has env steps too):", "",
               md_table(curve_view(curve)), ""]
    md += ["## Per-bin mastery", "", "Median mastery iteration over seeds (Kaplan-Meier; `–` = not reached) and "
           "(seeds that mastered the bin / seeds); † = horizon-truncated.", "", md_table(mastery_view(mastery_df)), ""]
    md += ["## Figures", ""] + [f"### {title}\n\n![{title}]({name})\n" for name, title in figures]
    md += definitions(opts, coverage)
    write_text(out / "report.md", "\n".join(md) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m analysis.report", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path, help="sweep folder, run folder(s), or folders holding runs")
    parser.add_argument("--out", type=Path, default=None, help="report folder (default: <PATH>/report)")
    parser.add_argument("--mastery-threshold", type=float, default=0.1, help="bin mastered when failure < this")
    parser.add_argument("--mastery-persist", type=int, default=2,
                        help="consecutive evaluations a bin must stay mastered (or to the end of the run)")
    parser.add_argument("--success-threshold", type=float, default=0.9, help="overall success for time to threshold")
    parser.add_argument("--baseline", default=None, help="baseline arm (default: the arm whose sampler is uniform)")
    parser.add_argument("--resamples", type=int, default=tables.DEFAULT_RESAMPLES, help="bootstrap resamples")
    parser.add_argument("--max-iteration", type=int, default=None,
                        help="read every run only up to this many iterations (a common budget for runs that went "
                             "further)")
    parser.add_argument(MIXED_FLAG, action="store_true",
                        help="compare runs trained on different motions or bin layouts (refused without it: "
                             "per-bin tables match bins by number)")
    args = parser.parse_args(argv)
    try:
        check_options(args.mastery_threshold, args.success_threshold, args.resamples, args.mastery_persist)
        if args.max_iteration is not None and args.max_iteration < 1:
            raise AnalysisError(f"--max-iteration must be >= 1, got {args.max_iteration}")
        opts = ReportOptions(mastery_threshold=args.mastery_threshold, mastery_persist=args.mastery_persist,
                             success_threshold=args.success_threshold, baseline=args.baseline,
                             n_resamples=args.resamples, max_iteration=args.max_iteration)
        out = build_report(args.paths, args.out, opts, allow_mixed=args.allow_mixed)
    except (AnalysisError, BmimicError) as e:  # BmimicError: a write the disk refuses (bmimic.atomic_io)
        print(f"error: {str(e).strip().splitlines()[0]}", file=sys.stderr)
        return 2
    print(f"report written to {out / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
