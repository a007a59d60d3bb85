"""``python -m analysis.report PATH [PATH ...]``: figures, CSV tables and report.md for a sweep.

PATH is a sweep folder, a run folder, or any folder holding run folders (e.g. a study's committed
``docs/results/<study>/runs/``). The report goes to ``--out``, else ``<PATH>/report/`` for one
PATH, else ``report/`` in the folder the paths share. Failed, missing and unfinished jobs are
listed, never fatal; running jobs with tables are included and marked. See analysis.metrics for the
definitions and analysis.stats for the statistics the report uses.

Machine-readable outputs: ``summary.csv`` (tables.SUMMARY_COLUMNS) and ``speedup.csv``
(tables.SPEEDUP_COLUMNS), plus per-seed and per-bin tables beside them.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from analysis import AnalysisError, plots, tables
from analysis.files import save_figure, write_csv, write_text
from analysis.load import load_runs, load_segments, load_table, short_arm_labels
from analysis.metrics import bin_table
from analysis.stats import MIN_SEEDS_BOOTSTRAP, MIN_SEEDS_IQM
from analysis.tables import ReportOptions

MEASURE_WORDS = {"iteration": "iterations", "env_steps": "env steps", "wall_time_s": "wall time (s)"}


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


def plural(n: int, word: str) -> str:
    """``"1 bin"``, ``"2 bins"``."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def _nan(x) -> bool:
    return x is None or (isinstance(x, float | np.floating) and math.isnan(x))


def _fmt(x, digits: int = 3) -> str:
    if _nan(x):
        return "–"
    if isinstance(x, bool | np.bool_):
        return "yes" if x else "no"
    if isinstance(x, float | np.floating):
        if math.isinf(x):
            return "∞" if x > 0 else "-∞"
        if float(x).is_integer() and abs(x) < 1e7:
            return str(int(x))
        return f"{x:.{digits}g}"
    return str(x)


def _per_seed_text(per_seed: str) -> str:
    return ", ".join(_fmt(float(v)) for v in str(per_seed).split(";") if v != "")


def estimate_cell(point, low, high, method: str, n: int, per_seed: str = "") -> str:
    """``0.1 [0.08, 0.12]`` with a bootstrap interval, else ``0.1 (range of 3 seeds: 0.08-0.12)``;
    the point is the IQM from 4 seeds, else the mean (said when it is the mean); per-seed values follow."""
    if _nan(point):
        return "–"
    if n <= 1:
        return f"{_fmt(point)} (1 seed)"
    label = "IQM" if n >= MIN_SEEDS_IQM else "mean"
    seeds = f"; seeds {_per_seed_text(per_seed)}" if per_seed else ""
    if method and method.startswith("bootstrap"):
        return f"{_fmt(point)} [{_fmt(low)}, {_fmt(high)}] ({label}{seeds})"
    return f"{_fmt(point)} ({label}; range of {n} seeds: {_fmt(low)}–{_fmt(high)}{seeds})"


def md_table(df: pd.DataFrame) -> str:
    """A GitHub markdown table of ``df`` (cells formatted with 3 significant digits)."""
    if not len(df):
        return "_(none)_\n"
    head = "| " + " | ".join(str(c) for c in df.columns) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    body = ["| " + " | ".join(_fmt(v).replace("|", "\\|") for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, rule, *body]) + "\n"


def _summary_row(summary: pd.DataFrame, arm: str, metric: str):
    r = summary[(summary["arm"] == arm) & (summary["metric"] == metric)]
    return None if not len(r) else r.iloc[0]


def _cell(summary: pd.DataFrame, arm: str, metric: str) -> str:
    r = _summary_row(summary, arm, metric)
    if r is None:
        return "–"
    p = r["iqm"] if r["n_seeds"] >= MIN_SEEDS_IQM else r["mean"]
    return estimate_cell(p, r["ci_low"], r["ci_high"], str(r["ci_method"]), int(r["n_seeds"]), str(r["per_seed"]))


def _winner_text(comp: pd.DataFrame, summary: pd.DataFrame, metric: str, what: str, at: str,
                 opts: ReportOptions) -> list[str]:
    """Which arm has the lowest ``metric``, and for every other arm the difference and its p-value.
    Arms whose points are exactly equal to the lowest tie: no winner is named."""
    rows = summary[summary["metric"] == metric]
    if not len(rows):
        return [f"- {what}: no arm has a value yet."]
    if len(rows) == 1:
        arm = rows.iloc[0]["arm"]
        return [f"- {what} ({at}): `{arm}` {_cell(summary, arm, metric)}."]
    best = comp["best"].iloc[0] if len(comp) else rows.iloc[0]["arm"]
    tied = [best, *comp.loc[comp["difference"] == 0, "arm"]]
    if len(tied) > 1:
        lines = [f"- {what} ({at}): {', '.join(f'`{a}`' for a in sorted(tied))} tie at "
                 f"{_fmt(comp['best_point'].iloc[0])}: no winner."]
    else:
        lines = [f"- Lowest {what.lower()} ({at}): **`{best}`** {_cell(summary, best, metric)}."]
    for r in comp[comp["difference"] != 0].itertuples(index=False):
        verdict = (f"a difference at the {opts.alpha:g} level" if r.claim
                   else f"no difference shown at the {opts.alpha:g} level")
        lines.append(f"  - `{r.arm}` {_cell(summary, r.arm, metric)}: higher by {_fmt(r.difference)}, "
                     f"p = {_fmt(r.p_value, 2)} (two-sided permutation test over seeds): {verdict}.")
    return lines


def _speedup_phrase(r, time_row_base, time_row_arm, word: str) -> str:
    p = f"p = {_fmt(r.p_value, 2)}"
    if r.status == "estimate":
        ci = (f" [{_fmt(r.ci_low)}, {_fmt(r.ci_high)}]" if not _nan(r.ci_low)
              else f" (no interval below {MIN_SEEDS_BOOTSTRAP} seeds per arm)")
        return f"{word} ×{_fmt(r.ratio)}{ci}, {p}"
    if r.status == "lower_bound":
        return (f"{word} ≥ ×{_fmt(r.ratio)} (a lower bound: the baseline's median was not reached within "
                f"{_fmt(time_row_base['follow_up'])}; {p})")
    if r.status == "upper_bound":
        return (f"{word} ≤ ×{_fmt(r.ratio)} (an upper bound: the arm's median was not reached within "
                f"{_fmt(time_row_arm['follow_up'])}; {p})")
    return (f"{word}: not estimable (neither median reached: {int(time_row_arm['n_reached'])}/"
            f"{int(time_row_arm['n_seeds'])} arm seeds, {int(time_row_base['n_reached'])}/"
            f"{int(time_row_base['n_seeds'])} baseline seeds got there)")


def _speedup_text(speed: pd.DataFrame, per_bin: pd.DataFrame, time_df: pd.DataFrame, baseline: str,
                  opts: ReportOptions) -> list[str]:
    lines = []
    t = time_df.set_index(["arm", "measure"])
    for arm, g in speed.groupby("arm", sort=True):
        parts = [_speedup_phrase(r, t.loc[(baseline, r.measure)], t.loc[(arm, r.measure)], MEASURE_WORDS[r.measure])
                 for r in g.itertuples(index=False)]
        lines.append(f"- `{arm}` vs `{baseline}`, time to overall success ≥ {opts.success_threshold:g} "
                     f"(baseline median / arm median): " + "; ".join(parts) + ".")
        b = per_bin[per_bin["arm"] == arm]
        if len(b):
            est = b[b["status"] == "estimate"]
            counts = b["status"].value_counts()
            text = (f"  Per-bin mastery speedups: {plural(len(est), 'bin')} estimable"
                    + (f" (median ratio ×{_fmt(float(np.median(est['ratio'])))})" if len(est) else ""))
            for status, word in (("lower_bound", "lower bound"), ("upper_bound", "upper bound"),
                                 ("not_estimable", "not estimable")):
                if counts.get(status, 0):
                    text += f", {plural(int(counts[status]), word)}"
            sig = b[b["p_value"] < opts.alpha]
            faster, slower = int((sig["ratio"] > 1).sum()), int((sig["ratio"] < 1).sum())
            text += (f"; p < {opts.alpha:g} in {plural(len(sig), 'bin')} of {len(b)} "
                     f"({faster} faster, {slower} slower; uncorrected for {plural(len(b), 'test')}).")
            lines.append(text)
    return lines


def _sensitivity_figure(sens: pd.DataFrame, key: str, reference: dict, per_run: dict) -> Figure:
    metrics = [m for m in tables.SENSITIVITY_METRICS if m in set(sens["metric"])]
    fig = Figure(figsize=(3.5 * len(metrics), 3.2), layout="constrained")
    for ax, metric in zip(np.atleast_1d(fig.subplots(1, len(metrics))), metrics, strict=True):
        plots.plot_sensitivity(sens[sens["key"] == key], metric, ax=ax, reference=reference.get(metric),
                               per_seed=per_run.get(metric))
    return fig


def _evaluation_notes(eval_df: pd.DataFrame, bins: pd.DataFrame) -> list[str]:
    lines = []
    if "visits" not in eval_df.columns or eval_df["visits"].isna().any():
        lines.append("- Some runs' eval.parquet predates per-visit accounting: there `failure_rate` is the failure "
                     "rate of the episodes that *started* in a bin (a failure was charged to the start bin), and "
                     "bins whose episodes run out of clip before the horizon are not flagged.")
    truncated = bins.loc[bins["horizon_truncated"], "bin"].tolist()
    if truncated:
        one = len(truncated) == 1
        its, they = ("its", "it is") if one else ("their", "they are")
        lines.append(f"- Horizon-truncated {'bin' if one else 'bins'} {', '.join(map(str, truncated))}: {its} "
                     f"episodes reach the end of the clip before the evaluation horizon, so {they} hatched in the "
                     f"figures and count{'s' if one else ''} as mastered only when an episode tracked all of "
                     f"{its} frames after entering from an earlier bin.")
    return lines + ([""] if lines else [])


def build_report(paths, out: str | Path | None = None, opts: ReportOptions | None = None) -> Path:
    """Load the runs under ``paths``, write every figure, table and report.md to ``out``; return ``out``."""
    opts = opts or ReportOptions()
    paths = [Path(p) for p in ([paths] if isinstance(paths, str | Path) else paths)]
    out = Path(out) if out is not None else default_out(paths)
    runs = load_runs(paths)
    for col in ("run_dir", "sweep_dir"):  # the tables travel (docs/, other machines): no absolute paths from here
        runs[col] = runs[col].map(_portable_path)
    labels, shared = short_arm_labels(runs["arm"])
    runs["arm_overrides"] = runs["arm"]
    runs["arm"] = runs["arm"].map(lambda a: labels.get(a, a))
    if opts.baseline in labels:
        opts = dataclasses.replace(opts, baseline=labels[opts.baseline])
    write_csv(out / "runs.csv", runs)
    md = ["# bmimic report", "", f"Inputs: {', '.join(f'`{p}`' for p in paths)}  ",
          f"Mastery: failure < {opts.mastery_threshold:g} at {plural(opts.mastery_persist, 'consecutive evaluation')} "
          f"(or to the end of the run); success threshold: overall success ≥ {opts.success_threshold:g}.  ",
          f"Statistics: point = IQM over seeds from {MIN_SEEDS_IQM} seeds, else the mean (labelled); "
          f"{tables.interval_label(runs, opts)}; differences: two-sided permutation tests, claimed at "
          f"p < {opts.alpha:g}.", ""]
    if shared:
        md += [f"Arms are named by the overrides that differ between them; all share `{','.join(shared)}`.", ""]
    md += _runs_section(runs)
    if not runs["included"].any():
        md += ["No run has usable tables yet; nothing else to report."]
        write_text(out / "report.md", "\n".join(md) + "\n")
        return out

    baseline, baseline_note = tables.choose_baseline(runs, opts.baseline)
    train, eval_df, sampler_df, robust_df = (load_table(runs, n) for n in ("train_metrics", "eval", "sampler",
                                                                          "eval_robust"))
    segments = load_segments(runs)
    bins = bin_table(eval_df, segments)
    colors = plots.arm_colors(runs["arm"].dropna())
    overall = tables.overall(eval_df)
    robust_overall = tables.overall(robust_df) if len(robust_df) else None
    mastery_seed_df = tables.mastery_seeds(eval_df, opts)
    mastery_df = tables.mastery(mastery_seed_df, bins)
    times = tables.run_times(overall, opts)
    time_df = tables.time_summary(times)
    budget = tables.budgets(runs, train)
    per_run = tables.per_run_metrics(runs, overall, robust_overall, mastery_seed_df, budget)
    summary = tables.summary(per_run, runs, opts)
    overview = tables.arm_overview(summary, time_df)
    common = tables.common_budget(overall)
    at = f"iteration {_fmt(common['iteration'])}, the last evaluation every run has"

    md += _budget_section(budget, opts)
    md += _evaluation_notes(eval_df, bins)

    per_seed_curves = tables.seed_curves(train, overall, opts)
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

    bin_fail = tables.bin_failure(eval_df)
    write_csv(out / "bin_failure.csv", bin_fail)
    save_figure(out / "bin_failure_heatmap.png", plots.plot_bin_heatmaps(bin_fail, "failure_rate", bins=bins))
    figures.append(("bin_failure_heatmap.png", "Evaluated failure rate per bin over training (mean over seeds; "
                                               "hatched: horizon-truncated)"))
    final_bins = tables.final_bin_failure(eval_df, runs, opts).merge(bins[["bin", "segment"]], on="bin", how="left")
    write_csv(out / "final_bin_failure.csv", final_bins)
    save_figure(out / "final_bin_failure.png", plots.plot_final_bin_failure(final_bins, bins=bins, colors=colors))
    figures.append(("final_bin_failure.png", f"Failure per bin at {at} (dots: seeds; {band})"))

    samp = tables.sampling(sampler_df, runs)
    if len(samp):
        write_csv(out / "sampling.csv", samp)
        save_figure(out / "sampling_distribution.png",
                    plots.plot_bin_heatmaps(samp, "probability", bins=bins, cmap="viridis"))
        figures.append(("sampling_distribution.png", "Sampling distribution over training, adaptive arms (mean over seeds)"))

    write_csv(out / "mastery_per_seed.csv", mastery_seed_df)
    write_csv(out / "mastery.csv", mastery_df)
    save_figure(out / "mastery.png", plots.plot_mastery(mastery_df, mastery_seed_df, bins=bins, colors=colors,
                                                        threshold=opts.mastery_threshold))
    figures.append(("mastery.png", "Mastery iteration per bin (median over seeds; dots: seeds, x: not by then)"))
    write_csv(out / "time_to_threshold.csv", times)
    write_csv(out / "time_to_threshold_summary.csv", time_df)
    write_csv(out / "budget.csv", budget)
    write_csv(out / "summary.csv", summary)
    comp = tables.comparisons(per_run, "final_failure", opts)
    comp_robust = tables.comparisons(per_run, "final_failure_robust", opts)
    write_csv(out / "comparisons.csv", pd.concat([comp, comp_robust], ignore_index=True))

    md += ["## Summary", "", *_winner_text(comp, summary, "final_failure", "Final overall failure", at, opts)]
    if "final_failure_robust" in per_run:
        md += _winner_text(comp_robust, summary, "final_failure_robust",
                           "Final overall failure, robust evaluation (DR, noise, pushes)", "last evaluation", opts)
    md.append(f"- Speedups: {baseline_note}.")
    speed = None
    if baseline is not None and runs.loc[runs["included"], "arm"].nunique() > 1:
        speed, per_bin = tables.speedups(times, mastery_seed_df, baseline, runs, opts)
        write_csv(out / "mastery_speedup.csv", per_bin)
        write_csv(out / "speedup.csv", speed)
        save_figure(out / "speedup.png", plots.plot_speedup(speed, tables.speedup_per_seed(times, baseline), colors=colors))
        figures.append(("speedup.png", f"Speedup vs `{baseline}` (baseline / arm, > 1: arm faster; dots: "
                                       "baseline median / each arm seed)"))
        md += _speedup_text(speed, per_bin, time_df, baseline, opts)
    md += ["", "## Arms", "", md_table(_arms_view(summary, time_df, per_run, at)), ""]

    seg = tables.segment_failure(eval_df, bins, mastery_df, segments, runs, opts)
    if len(seg):
        write_csv(out / "segment_failure.csv", seg)
        md += ["## Segments", "", f"Failure per motion segment at {at} (mean over its bins per seed); "
               "(n/m): n of the segment's m bins not mastered (median over seeds not reached).", "",
               md_table(_segment_view(seg)), ""]

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
        md += ["## Speedup", "", md_table(speed), ""]
    md += ["## Per-bin mastery", "", "Median mastery iteration over seeds (Kaplan-Meier; `–` = not reached) and "
           "(seeds that mastered the bin / seeds); † = horizon-truncated.", "", md_table(_mastery_view(mastery_df)), ""]
    md += ["## Figures", ""] + [f"### {title}\n\n![{title}]({name})\n" for name, title in figures]
    md += _definitions(opts)
    write_text(out / "report.md", "\n".join(md) + "\n")
    return out


def _budget_section(budget: pd.DataFrame, opts: ReportOptions) -> list[str]:
    if not len(budget):
        return []
    g = budget.groupby("arm", sort=True)
    view = pd.DataFrame({
        "arm": list(g.groups),
        "iterations": [_span(x) for _, x in g["iterations"]],
        "env steps": [_span(x) for _, x in g["env_steps"]],
        "wall time (s)": [_span(x) for _, x in g["wall_time_s"]],
    })
    lines = ["## Budget", "", "Completed per run (min–max over seeds). Arms are compared at equal iterations and "
             "env steps; wall time is reported, not compared.", "", md_table(view)]
    warning = tables.budget_warning(budget, opts)
    if warning:
        lines += [warning, ""]
    return lines


def _span(x: pd.Series) -> str:
    lo, hi = float(x.min()), float(x.max())
    return _fmt(lo) if lo == hi else f"{_fmt(lo)}–{_fmt(hi)}"


def _runs_section(runs: pd.DataFrame) -> list[str]:
    counts = runs.groupby(["arm", "status"]).size().unstack(fill_value=0).reset_index()
    lines = ["## Runs", "", md_table(counts), ""]
    running = runs[runs["included"] & (runs["status"] == "running")]
    if len(running):
        lines += ["Still running, included with their partial tables (marked `running`):", ""]
        lines += [f"- `{r.arm}` seed {r.seed}: up to iteration {r.iteration} (`{r.run_dir}`)" for r in running.itertuples()]
        lines.append("")
    excluded = runs[~runs["included"]]
    if len(excluded):
        lines += ["Not included (failed, missing or without usable tables):", ""]
        lines += [f"- `{r.arm}` seed {r.seed}: {r.status} — {r.problem} (`{r.run_dir}`)" for r in excluded.itertuples()]
        lines.append("")
    return lines


def _time_cell(time_df: pd.DataFrame, arm: str, measure: str) -> str:
    r = time_df[(time_df["arm"] == arm) & (time_df["measure"] == measure)]
    if not len(r):
        return "–"
    r = r.iloc[0]
    head = _fmt(r["median"]) if not _nan(r["median"]) else f"not reached (> {_fmt(r['follow_up'])})"
    seeds = ", ".join(_fmt(float(v)) if not v.startswith(">") else f">{_fmt(float(v[1:]))}"
                      for v in str(r["per_seed"]).split(";"))
    return f"{head} ({int(r['n_reached'])}/{int(r['n_seeds'])} seeds; {seeds})"


def _arms_view(summary: pd.DataFrame, time_df: pd.DataFrame, per_run: dict, at: str) -> pd.DataFrame:
    arms = sorted(set(summary["arm"]))
    view = {"arm": arms, "seeds": [int(summary.loc[summary["arm"] == a, "n_seeds"].max()) for a in arms],
            f"final failure ({at.split(',')[0]})": [_cell(summary, a, "final_failure") for a in arms]}
    if "final_failure_equal_env_steps" in per_run:
        view["final failure (equal env steps)"] = [_cell(summary, a, "final_failure_equal_env_steps") for a in arms]
    if "final_failure_robust" in per_run:
        view["final failure, robust eval"] = [_cell(summary, a, "final_failure_robust") for a in arms]
    view["bins mastered"] = [_cell(summary, a, "bins_mastered") for a in arms]
    for m in ("iteration", "env_steps", "wall_time_s"):
        view[f"{MEASURE_WORDS[m]} to threshold (median)"] = [_time_cell(time_df, a, m) for a in arms]
    return pd.DataFrame(view)


def _segment_view(seg: pd.DataFrame) -> pd.DataFrame:
    seg = seg.assign(cell=[f"{estimate_cell(p, lo, hi, m, n)} ({nm}/{b})" for p, lo, hi, m, n, nm, b in zip(
        seg["final_failure"], seg["final_failure_low"], seg["final_failure_high"], seg["ci_method"], seg["n_seeds"],
        seg["bins_not_mastered"], seg["num_bins"], strict=True)])
    view = seg.pivot_table(index=["segment", "difficulty"], columns="arm", values="cell", aggfunc="first", sort=False)
    return view.reset_index()


def _mastery_view(mastery_df: pd.DataFrame) -> pd.DataFrame:
    cells = mastery_df.assign(cell=[f"{_fmt(m)} ({k}/{n})" for m, k, n in zip(
        mastery_df["mastery_iteration"], mastery_df["n_mastered"], mastery_df["n_seeds"], strict=True)])
    view = cells.pivot(index="bin", columns="arm", values="cell").reset_index()
    meta = mastery_df.drop_duplicates("bin")[["bin", "segment", "horizon_truncated"]]
    meta = meta.assign(bin=[f"{b}†" if t else str(b) for b, t in zip(meta["bin"], meta["horizon_truncated"],
                                                                      strict=True)], _key=meta["bin"])
    view = meta.merge(view.rename(columns={"bin": "_key"}), on="_key").drop(columns=["_key", "horizon_truncated"])
    return view


def _definitions(opts: ReportOptions) -> list[str]:
    return ["## Definitions", "",
            "- Evaluation (every `eval.every_iters`, sampler-independent, deterministic policy): episodes start at "
            "stratified frames of every bin and run for the horizon; a bin's failure rate is the failures that "
            "happened at its frames over the episodes that visited it. Overall failure of an evaluation = the "
            "unweighted mean of the per-bin failure rates; success = 1 − failure.",
            f"- A bin counts as mastered at an evaluation where its failure rate is < {opts.mastery_threshold:g} "
            "(a horizon-truncated bin also needs an episode that tracked all its frames after entering from an "
            "earlier bin). Its mastery iteration in one seed = the first evaluation from which it counts as "
            f"mastered for {plural(opts.mastery_persist, 'consecutive evaluation')} or for the rest of the run; "
            "a seed that never got there is censored at its last evaluation.",
            f"- Time to threshold = the first evaluation from which overall success ≥ {opts.success_threshold:g} "
            "with the same persistence, per seed, in iterations, env steps and wall time (censored likewise).",
            "- Per arm, such times are summarised by the Kaplan-Meier median over seeds: only when more than half "
            "of the seeds got there (censored seeds count as not yet), else `not reached`.",
            "- Speedup = baseline median / arm median (> 1: the arm is faster). `estimate` when both medians are "
            "defined (bootstrap interval over seeds, each arm resampled on its own, when every arm has "
            f"≥ {MIN_SEEDS_BOOTSTRAP} seeds); `lower_bound` when only the baseline's median was not reached (its "
            "last follow-up over the arm's median); `upper_bound` the reverse; `not_estimable` when neither was.",
            f"- Point estimates: IQM (mean of the middle half of the seeds) from {MIN_SEEDS_IQM} seeds, else the "
            f"mean. Intervals: BCa bootstrap (percentile where BCa is undefined) only when every arm has "
            f"≥ {MIN_SEEDS_BOOTSTRAP} seeds; with fewer, the range of the seeds, labelled so. Per-seed values are "
            "listed beside every estimate.",
            f"- Differences: two-sided permutation test over seeds (exact for small n); claimed at p < {opts.alpha:g}. "
            "Times to an event are compared with Gehan's generalised Wilcoxon scores (censoring-aware). Exact ties "
            "name no winner.", ""]


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
    args = parser.parse_args(argv)
    if args.mastery_persist < 1:
        print(f"error: --mastery-persist must be >= 1, got {args.mastery_persist}", file=sys.stderr)
        return 2
    opts = ReportOptions(mastery_threshold=args.mastery_threshold, mastery_persist=args.mastery_persist,
                         success_threshold=args.success_threshold, baseline=args.baseline, n_resamples=args.resamples)
    try:
        out = build_report(args.paths, args.out, opts)
    except AnalysisError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"report written to {out / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
