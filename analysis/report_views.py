"""The report's words: report.md's sections from a computed report (analysis.report_compute) and the
figures analysis.report_files wrote. Nothing here computes a statistic or writes a file."""

from __future__ import annotations

from analysis import clip_tables, tables, whole_clip
from analysis.curve_text import adaptation_section, curve_view, iso_text, speedup_curve_text
from analysis.definitions import definitions
from analysis.knob_report import knob_section
from analysis.markdown import (
    FAILURE_UNIT,
    NOT_RECORDED,
    arms_view,
    baseline_text,
    budget_section,
    evaluation_notes,
    mastery_view,
    md_table,
    plural,
    runs_section,
    segment_view,
    speed_view,
    tracking_view,
    winner_text,
)
from analysis.metrics import SMOOTHNESS_METRICS
from analysis.report_compute import ReportData, Runs
from analysis.stats import MIN_SEEDS_IQM
from bmimic.runs.schema import JOINT_VEL_ERR_RADPS, MPKPE_REL_MM

TRACKING_HEADLINE = (MPKPE_REL_MM, JOINT_VEL_ERR_RADPS)
"""Tracking errors the Tracking quality section compares between arms in words (position and velocity
tracking; the policy's smoothness is SMOOTHNESS_METRICS, compared in its own block)."""


def header(paths: list, r: Runs) -> list[str]:
    """The inputs, the definitions in force and the Runs section."""
    runs, opts, coverage = r.runs, r.opts, r.coverage
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
    if r.shared:
        md += [f"Arms are named by the overrides that differ between them; all share `{','.join(r.shared)}`.", ""]
    return md + runs_section(runs)


def _tracking(d: ReportData) -> list[str]:
    if not (d.shown or d.smooth or len(d.broken)):
        return []
    at, opts, shown, smooth = d.at, d.opts, d.shown, d.smooth
    md = ["## Tracking quality", "", f"Step-weighted mean errors of the evaluation at {at}, over the steps the "
          "evaluation episodes were alive (an arm that fails more is measured over fewer steps); lower is "
          "better.", "", md_table(tracking_view(d.summary, {f"final_{c}": lab for c, lab in shown.items()}, d.seeds)),
          ""]
    for c in TRACKING_HEADLINE:
        if c in d.comp_errors:
            md += winner_text(d.comp_errors[c], d.summary, f"final_{c}", shown[c][0].upper() + shown[c][1:], at, opts,
                              noun=shown[c])
    md += ["", "### Smoothness of the policy", "", "The policy's own action rate and joint acceleration at the "
           f"same evaluation ({at}) and the episodes whose world broke over all evaluations (each also a "
           "failure); lower is smoother. Joint-velocity error above is a tracking error, not smoothness. "
           f"\"{NOT_RECORDED}\": the runs' evaluation tables predate these columns.", "",
           md_table(tracking_view(d.summary, {**{f"final_{c}": lab for c, lab in SMOOTHNESS_METRICS.items()},
                                              "broken_episodes": "broken episodes (count, all evaluations)"},
                                  d.seeds)), ""]
    for c in smooth:
        md += winner_text(d.comp_errors[c], d.summary, f"final_{c}", smooth[c][0].upper() + smooth[c][1:], at, opts,
                          noun=smooth[c])
    return md + [""]


def _segments_and_clips(d: ReportData) -> list[str]:
    md = []
    if len(d.seg):
        md += ["## Segments", "", f"Failure per motion segment at {d.at}, in the unit of the overall failure "
               f"({FAILURE_UNIT}, each episode charged to the segment it started in); bins not mastered: median "
               "mastery over seeds not reached.", "", md_table(segment_view(d.seg)), ""]
    if len(d.clip_tab):
        md += ["## Clips", "", f"Per clip of the motion library at {d.at}: failure in the unit of the overall failure "
               f"({FAILURE_UNIT}, each episode charged to the clip it started in, so the overall failure is their "
               "mean weighted by started episodes); bins not mastered: median mastery over seeds not reached; "
               "sampling probability mass: the training sampler's probability on the clip's bins, the mean over "
               "its logged iterations and seeds, the same quantity for every sampler.", "",
               md_table(clip_tables.clip_view(d.clip_tab)), ""]
        unused = clip_tables.never_started(d.clip_tab)
        md += [f"- No sampling probability at any logged iteration: {', '.join(unused)}." if unused else
               "- Every arm gave every clip sampling probability.", ""]
    return md


def body(d: ReportData, figures: list[tuple[str, str]], coverage: tuple | None) -> list[str]:
    """Every section after Runs, from the tables of `d` and the figures written."""
    opts, at = d.opts, d.at
    md = budget_section(d.budget, opts, d.kinds, d.machines) + evaluation_notes(d.eval_df, d.bins)
    md += ["## Summary", "", *winner_text(d.comp, d.summary, "final_failure", f"Final overall failure ({FAILURE_UNIT})",
                                          at, opts, noun="final overall failure")]
    if "final_failure_robust" in d.per_run:
        md += winner_text(d.comp_robust, d.summary, "final_failure_robust",
                          "Final overall failure, robust evaluation (DR, noise, pushes)", "last evaluation", opts)
    md += baseline_text(d.comp_base, d.summary, "final_failure", "Final overall failure", at, opts)
    md.append(f"- Speedups: {d.baseline_note}.")
    if d.speed is not None:
        md += speedup_curve_text(d.curve, d.speed, d.per_bin, d.time_df, opts, d.machines)
        md += iso_text(d.iso)
    if len(d.signals) and d.signals["degenerate"].any():
        md.append("- Degenerate sampler signals (see Adaptation): "
                  + ", ".join(f"`{a}`" for a in d.signals.loc[d.signals["degenerate"], "arm"]) + ".")
    md += ["", "## Arms", "", md_table(arms_view(d.summary, d.time_df, d.per_run, at, d.measures)), ""]
    md += _tracking(d) + _segments_and_clips(d)
    if d.whole_clip is not None:
        md += whole_clip.section(d.whole_clip)
    if len(d.support):
        md += adaptation_section(d.support_sum, d.signals, d.clip_evals)
    if len(d.sens):
        md += ["## Sensitivity", ""]
        for key in sorted(d.sens["key"].unique()):
            view = d.sens[(d.sens["key"] == key)].pivot_table(index=["value", "series"], columns="metric",
                                                              values="point")
            md += [f"`{key}`:", "", md_table(view.reset_index()), ""]
    if d.knob_levels is not None:
        md += knob_section(d.knob_levels, d.knob_summary, d.uniform_arm, opts.alpha)
    if d.speed is not None:
        md += ["## Speedup", "", f"At overall success ≥ {opts.success_threshold:g} (ratio = baseline median / arm "
               "median; p: Gehan permutation test, uncorrected):", "", md_table(speed_view(d.speed, d.time_df)), ""]
        md += ["Over success thresholds (iterations; speedup_curve.csv has env steps too):", "",
               md_table(curve_view(d.curve)), ""]
    md += ["## Per-bin mastery", "", "Median mastery iteration over seeds (Kaplan-Meier; `–` = not reached) and "
           "(seeds that mastered the bin / seeds); † = horizon-truncated.", "", md_table(mastery_view(d.mastery_df)), ""]
    md += ["## Figures", ""] + [f"### {title}\n\n![{title}]({name})\n" for name, title in figures]
    return md + definitions(opts, coverage)


__all__ = ["TRACKING_HEADLINE", "body", "header"]
