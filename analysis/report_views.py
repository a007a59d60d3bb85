"""The report's words: report.md's sections from a computed report (analysis.report_compute) and the
figures analysis.report_files wrote. Nothing here computes a statistic or writes a file."""

from __future__ import annotations

import pandas as pd

from analysis import tables, whole_clip
from analysis.curve_text import adaptation_section, curve_view, iso_text, speedup_curve_text
from analysis.definitions import definitions
from analysis.knob_report import knob_section
from analysis.machines import kinds_text
from analysis.markdown import (
    FAILURE_UNIT,
    NOT_RECORDED,
    arms_view,
    baseline_text,
    budget_section,
    estimate_cell,
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
from analysis.metrics import SMOOTHNESS_METRICS
from analysis.report_compute import Inputs, ReportData, Runs
from analysis.stats import MIN_SEEDS_IQM
from bmimic.runs.schema import BIN, ITERATION, JOINT_VEL_ERR_RADPS, MPKPE_REL_MM

REPORT_TITLE = "# bmimic report"
"""report.md's first line: how a later report knows the file in its --out folder is a report's, not a user's."""
SMOKE_ITERATIONS = 100
"""A report whose runs all stopped before this many PPO iterations is a pipeline check (a CPU smoke run
is 4), not a result: its title and first line say so, so that its p-values are not read as findings."""
TRACKING_HEADLINE = (MPKPE_REL_MM, JOINT_VEL_ERR_RADPS)
"""Tracking errors the Tracking quality section compares between arms in words (position and velocity
tracking; the policy's smoothness is SMOOTHNESS_METRICS, compared in its own block)."""


def at_text(inp: Inputs) -> str:
    """Where the final numbers are read (and, when the runs evaluated on different schedules, the
    iterations each was in fact read at: a run is never read past the common budget)."""
    if set(inp.final_read) <= {inp.final_iteration}:
        return f"iteration {fmt(inp.final_iteration)}, the last evaluation every run has"
    read = ", ".join(fmt(i) for i in inp.final_read)
    return (f"iteration {fmt(inp.final_iteration)}, the last iteration every run's evaluations reach; each run "
            f"is read at its last evaluation at or before it: iterations {read}")


def band_text(inp: Inputs) -> str:
    """What a curve's band is."""
    return "band: bootstrap interval" if inp.bootstrap else "band: range of the seeds"


def machines_text(inp: Inputs) -> str:
    """Why wall time is not compared ("" when it is)."""
    return "" if inp.wall_ok else (
        "Wall time is not compared (no wall-time speedup is printed, and the Arms table leaves wall time out): "
        f"the runs trained on different or unrecorded machine kinds ({kinds_text(inp.runs, inp.kinds)}).")


def _baseline_note(inp: Inputs) -> str:
    """How the speedups' baseline was chosen, or why there is none."""
    if inp.baseline is None:
        return "no arm has sampler.name == uniform and no --baseline was given: speedups are skipped"
    if not inp.uniform_arms:
        return f"baseline `{inp.baseline}` (given)"
    others = inp.uniform_arms[1:]
    return f"baseline `{inp.baseline}` (its sampler is uniform)" + (
        f"; other uniform arms: {', '.join(f'`{a}`' for a in others)} (pick one with --baseline)" if others else "")


def header(paths: list, r: Runs) -> list[str]:
    """The inputs, the definitions in force and the Runs section."""
    runs, opts, coverage = r.runs, r.opts, r.coverage
    done = (runs.loc[runs["included"], ITERATION] if "included" in runs else runs[ITERATION]).dropna()
    smoke = len(done) > 0 and float(done.max()) < SMOKE_ITERATIONS  # (a status without an iteration says nothing)
    title = [f"{REPORT_TITLE} (smoke scale: not a result)", "",
             f"**Smoke scale.** Every run stopped before iteration {SMOKE_ITERATIONS}: this report checks the "
             "pipeline; its numbers and tests say nothing about the samplers.", ""] if smoke else [REPORT_TITLE, ""]
    md = [*title, f"Inputs: {', '.join(f'`{p}`' for p in paths)}  ",
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


def schedule_section(runs: pd.DataFrame, judged) -> list[str]:
    """The arms whose sampler anneals over a schedule of its own (sampler.schedule_iterations: EGM's exponent and
    uniform share) and whether it had finished at `judged`, the iteration the report reads: a peer read
    mid-schedule is not the peer as its paper runs it (issue 76). Empty when no arm has one."""
    used = runs[runs["included"]] if "included" in runs else runs
    lines = []
    for arm, group in used.groupby("arm", sort=True):
        lengths = sorted({n for d in group["run_dir"] if isinstance(d, str) and (n := _schedule(d)) is not None})
        if not lengths or judged is None:
            continue
        state = ("had finished" if judged >= lengths[-1] else
                 f"had not finished: the report reads {judged / lengths[-1]:.0%} of the way through it")
        lines.append(f"- `{arm}` anneals over {plural(lengths[-1], 'iteration')} (sampler.schedule_iterations"
                     + (f"; its seeds' schedules: {', '.join(map(str, lengths))}" if len(lengths) > 1 else "")
                     + f"); at iteration {fmt(judged)}, where this report reads it, its schedule {state}.")
    return ["## Samplers with schedules of their own", "", *lines, ""] if lines else []


def _schedule(run_dir: str) -> int | None:
    """A run's sampler.schedule_iterations as it trained: the resolved config's, else the composed one's, where
    null is the run's max_iterations (placement fills it so; a config holds null only since that rule); None
    for a sampler without one."""
    from analysis.run_files import config_value
    from bmimic.runs.folder import read_hydra_config, read_resolved_config

    for cfg in (read_resolved_config(run_dir) or {}, read_hydra_config(run_dir) or {}):
        sampler = cfg.get("sampler")
        if isinstance(sampler, dict) and "schedule_iterations" in sampler:
            value = sampler["schedule_iterations"]
            value = config_value(cfg, "max_iterations") if value is None else value
            return int(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else None
    return None


def _tracking(d: ReportData) -> list[str]:
    inp, arms = d.inputs, d.arms
    if not (arms.shown or arms.smooth or len(arms.broken)):
        return []
    at, opts, shown, smooth = at_text(inp), inp.opts, arms.shown, arms.smooth
    md = ["## Tracking quality", "", f"Step-weighted mean errors of the evaluation at {at}, over the steps the "
          "evaluation episodes were alive (an arm that fails more is measured over fewer steps); lower is "
          "better.", "",
          md_table(tracking_view(arms.summary, {f"final_{c}": lab for c, lab in shown.items()}, inp.seeds)),
          ""]
    for c in TRACKING_HEADLINE:
        if c in arms.comp_errors:
            md += winner_text(arms.comp_errors[c], arms.summary, f"final_{c}", shown[c][0].upper() + shown[c][1:], at,
                              opts, noun=shown[c])
    md += ["", "### Smoothness of the policy", "", "The policy's own action rate and joint acceleration at the "
           f"same evaluation ({at}) and the episodes whose world broke over all evaluations (each also a "
           "failure); lower is smoother. Joint-velocity error above is a tracking error, not smoothness. "
           f"\"{NOT_RECORDED}\": the runs' evaluation tables predate these columns.", "",
           md_table(tracking_view(arms.summary, {**{f"final_{c}": lab for c, lab in SMOOTHNESS_METRICS.items()},
                                                 "broken_episodes": "broken episodes (count, all evaluations)"},
                                  inp.seeds)), ""]
    for c in smooth:
        md += winner_text(arms.comp_errors[c], arms.summary, f"final_{c}", smooth[c][0].upper() + smooth[c][1:], at,
                          opts, noun=smooth[c])
    return md + [""]


CLIP_FAILURE_HEADER = "final failure (failed / started episodes, by start clip)"
CLIP_MASS_HEADER = "sampling probability mass (mean over training)"


def _clip_view(table: pd.DataFrame) -> pd.DataFrame:
    """The Clips table, one row per clip and arm, every column named with its unit."""
    return pd.DataFrame({
        "clip": table["clip"],
        "arm": table["arm"],
        CLIP_FAILURE_HEADER: [estimate_cell(p, lo, hi, m, n) for p, lo, hi, m, n in zip(
            table["final_failure"], table["final_failure_low"], table["final_failure_high"], table["ci_method"],
            table["n_seeds"], strict=True)],
        "bins not mastered / bins": [f"{nm}/{b}" for nm, b in zip(table["bins_not_mastered"], table["num_bins"],
                                                                  strict=True)],
        CLIP_MASS_HEADER: [f"{s:.1%}" if s == s else "–" for s in table["sampling_mass"]],
    })


def _never_started(table: pd.DataFrame) -> list[str]:
    """`arm: clip` for every clip an arm's sampler gave no probability at any logged iteration."""
    hit = table[table["sampling_mass"] == 0]
    return [f"`{a}`: {c}" for a, c in zip(hit["arm"], hit["clip"], strict=True)]


CLIP_WINDOW_SUCCESS_LINE = 0.95
"""Final window success a library's clips are counted at (the library issue's target: >= 95% on 34 of 36)."""


def _clips_at_success(clip_tab: pd.DataFrame) -> list[str]:
    """Per arm: how many clips reach CLIP_WINDOW_SUCCESS_LINE (final failure <= 1 - the line), by the point
    over seeds and, for several seeds, by each seed's own failures (a seed's count is what one policy does)."""
    lines = []
    limit = 1.0 - CLIP_WINDOW_SUCCESS_LINE + 1e-12
    for arm, g in clip_tab.groupby("arm", sort=True):
        k = int((g["final_failure"] <= limit).sum())
        line = (f"- `{arm}`: {k} of {len(g)} clips at final success >= {CLIP_WINDOW_SUCCESS_LINE:g} (failure "
                f"<= {1.0 - CLIP_WINDOW_SUCCESS_LINE:.2g})")
        n_seeds = int(g["n_seeds"].max())
        if n_seeds > 1:
            per = tables.count_per_seed(g["seeds"], g["per_seed"], lambda v: v <= limit)
            point = "IQM" if n_seeds >= MIN_SEEDS_IQM else "mean"  # clip_failure's point
            line += f" by the {point} over seeds; per seed: " + ", ".join(f"{n} (seed {s})" for s, n in per.items())
        if (g["end_iterations"] != g["iterations"]).any():  # a run went past the common budget
            ends = dict(zip(g["seeds"].iloc[0].split(";"), g["end_iterations"].iloc[0].split(";"), strict=True))
            at_end = tables.count_per_seed(g["seeds"], g["per_seed_at_end"], lambda v: v <= limit)
            line += "; at each seed's own last evaluation: " + ", ".join(
                f"{n} (seed {s}, iteration {ends[str(s)]})" for s, n in at_end.items())
        lines.append(line + ".")
    return lines


def _segments_and_clips(d: ReportData) -> list[str]:
    inp, places = d.inputs, d.places
    md = []
    if len(places.seg):
        md += ["## Segments", "", f"Failure per motion segment at {at_text(inp)}, in the unit of the overall failure "
               f"({FAILURE_UNIT}, each episode charged to the segment it started in); bins not mastered: median "
               "mastery over seeds not reached.", "", md_table(segment_view(places.seg)), ""]
    if len(places.clip_tab):
        md += ["## Clips", "", f"Per clip of the motion library at {at_text(inp)}: failure in the unit of the overall failure "
               f"({FAILURE_UNIT}, each episode charged to the clip it started in, so the overall failure is their "
               "mean weighted by started episodes); bins not mastered: median mastery over seeds not reached; "
               "sampling probability mass: the training sampler's probability on the clip's bins, the mean over "
               "its logged iterations and seeds, the same quantity for every sampler.", "",
               md_table(_clip_view(places.clip_tab)), ""]
        md += _clips_at_success(places.clip_tab)
        unused = _never_started(places.clip_tab)
        md += [f"- No sampling probability at any logged iteration: {', '.join(unused)}." if unused else
               "- Every arm gave every clip sampling probability.", ""]
    return md


def body(d: ReportData, figures: list[tuple[str, str]], coverage: tuple | None) -> list[str]:
    """Every section after Runs, from the tables of `d` and the figures written."""
    inp, cur, tab, arms, adapt, sens = d.inputs, d.curves, d.bins, d.arms, d.adaptation, d.sensitivity
    opts, at, machines = inp.opts, at_text(inp), machines_text(inp)
    md = budget_section(cur.budget, opts, inp.kinds, machines) + evaluation_notes(tab.eval_df, tab.bins)
    if tab.other_layouts:
        md += [f"- Cut into other bins than the baseline's: {', '.join(f'`{a}`' for a in tab.other_layouts)}. Their "
               "overall failure, times to success and tracking errors are compared as any arm's (their bins mastered "
               "count their own bins); they are left out "
               "of the per-bin comparisons (mastery per bin, per-bin speedups, segments, failure and sampling "
               "over bins, the bin figures of their knob), which match bins by number.", ""]
    md += ["## Summary", "", *winner_text(arms.comp, arms.summary, "final_failure",
                                          f"Final overall failure ({FAILURE_UNIT})",
                                          at, opts, noun="final overall failure")]
    if "final_failure_robust" in arms.per_run:
        md += winner_text(arms.comp_robust, arms.summary, "final_failure_robust",
                          "Final overall failure, robust evaluation (DR, noise, pushes)", "last evaluation", opts)
    md += baseline_text(arms.comp_base, arms.summary, "final_failure", "Final overall failure", at, opts)
    md.append(f"- Speedups: {_baseline_note(inp)}.")
    sp = d.speedups
    if sp is not None:
        md += speedup_curve_text(sp.curve, sp.speed, sp.per_bin, arms.time_df, opts, machines)
        md += iso_text(sp.iso)
    if len(adapt.signals) and adapt.signals["degenerate"].any():
        md.append("- Degenerate sampler signals (see Adaptation): "
                  + ", ".join(f"`{a}`" for a in adapt.signals.loc[adapt.signals["degenerate"], "arm"]) + ".")
    md += ["", "## Arms", "", md_table(arms_view(arms.summary, arms.time_df, arms.per_run, at, inp.measures)), ""]
    md += _tracking(d) + _segments_and_clips(d)
    if d.whole_clip is not None:
        md += whole_clip.section(d.whole_clip)
    if len(adapt.support):
        md += adaptation_section(adapt.support_sum, adapt.signals, adapt.clip_evals)
    if len(sens.sens):
        md += ["## Sensitivity", ""]
        for key in sorted(sens.sens["key"].unique()):
            view = sens.sens[(sens.sens["key"] == key)].pivot_table(index=["value", "series"], columns="metric",
                                                              values="point")
            md += [f"`{key}`:", "", md_table(view.reset_index()), ""]
    if sens.knob_levels is not None:
        md += knob_section(sens.knob_levels, sens.knob_summary, sens.uniform_arm, opts.alpha)
    if sp is not None:
        md += ["## Speedup", "", f"At overall success ≥ {opts.success_threshold:g} (ratio = baseline median / arm "
               "median; p: Gehan permutation test, uncorrected):", "", md_table(speed_view(sp.speed, arms.time_df)), ""]
        md += ["Over success thresholds (iterations; speedup_curve.csv has env steps too):", "",
               md_table(curve_view(sp.curve)), ""]
    md += per_bin_mastery(tab.mastery_df)
    md += ["## Figures", ""] + [f"### {title}\n\n![{title}]({name})\n" for name, title in figures]
    return md + definitions(opts, coverage)


MASTERY_TABLE_MAX_BINS = 1000
"""Most bins the per-bin mastery table prints on the report's page (the committed studies have up to 627);
a larger library's table is mastery.csv beside the report: 8,018 rows of markdown read as nothing."""


def per_bin_mastery(mastery_df: pd.DataFrame) -> list[str]:
    """The Per-bin mastery section: the table, or where it is when there are too many bins to print."""
    md = ["## Per-bin mastery", ""]
    n_bins = mastery_df[BIN].nunique() if len(mastery_df) else 0
    if n_bins > MASTERY_TABLE_MAX_BINS:
        return md + [f"{n_bins} bins, more than this page prints ({MASTERY_TABLE_MAX_BINS}): the median mastery "
                     "iteration of every bin and arm is mastery.csv beside this report (and the figure below); per "
                     "clip, bins not mastered are in Clips above.", ""]
    return md + ["Median mastery iteration over seeds (Kaplan-Meier; `–` = not reached) and (seeds that mastered "
                 "the bin / seeds); † = horizon-truncated.", "", md_table(mastery_view(mastery_df)), ""]


__all__ = ["MASTERY_TABLE_MAX_BINS", "TRACKING_HEADLINE", "body", "header", "per_bin_mastery"]
