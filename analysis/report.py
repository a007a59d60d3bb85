"""``python -m analysis.report PATH [PATH ...]``: figures, CSV tables and report.md for a sweep.

PATH is a sweep folder, a run folder, or any folder holding run folders. The report goes to
``--out``, else ``<PATH>/report/`` for one PATH, else ``report/`` in the folder the paths share.
Failed, missing and unfinished jobs are listed, never fatal; running jobs with tables are included
and marked. See analysis.metrics for the definitions the report uses.
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
from analysis.stats import intervals_overlap
from analysis.tables import ReportOptions


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


def _fmt(x, digits: int = 3) -> str:
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    if isinstance(x, float | np.floating):
        if math.isinf(x):
            return "∞"
        if float(x).is_integer() and abs(x) < 1e7:
            return str(int(x))
        return f"{x:.{digits}g}"
    return str(x)


def _ci(point, low, high) -> str:
    if point is None or (isinstance(point, float) and math.isnan(point)):
        return "never" if point is not None else "–"
    return f"{_fmt(point)} [{_fmt(low)}, {_fmt(high)}]"


def md_table(df: pd.DataFrame) -> str:
    """A GitHub markdown table of ``df`` (cells formatted with 3 significant digits)."""
    if not len(df):
        return "_(none)_\n"
    head = "| " + " | ".join(str(c) for c in df.columns) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    body = ["| " + " | ".join(_fmt(v).replace("|", "\\|") for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, rule, *body]) + "\n"


def _winner_text(summary: pd.DataFrame, opts: ReportOptions) -> list[str]:
    """Which arm ends with the lowest overall failure, by how much, and whether that is within noise."""
    s = summary.dropna(subset=["final_failure"]).sort_values("final_failure")
    if not len(s):
        return ["No arm has a final evaluation yet."]
    best = s.iloc[0]
    lines = [f"- Lowest final overall failure: **`{best['arm']}`** at "
             f"{_ci(best['final_failure'], best['final_failure_low'], best['final_failure_high'])} "
             f"(IQM over {best['n_seeds']} seeds, {opts.confidence:.0%} bootstrap interval)."]
    for _, other in s.iloc[1:].iterrows():
        noise = intervals_overlap(best["final_failure_low"], best["final_failure_high"],
                                  other["final_failure_low"], other["final_failure_high"])
        verdict = "the intervals overlap, so this difference is within noise" if noise else "the intervals do not overlap"
        lines.append(f"  - vs `{other['arm']}` at {_ci(other['final_failure'], other['final_failure_low'], other['final_failure_high'])}"
                     f": lower by {_fmt(other['final_failure'] - best['final_failure'])}; {verdict}.")
    return lines


def _speedup_text(speed: pd.DataFrame, baseline: str, opts: ReportOptions) -> list[str]:
    lines = []
    for arm, g in speed.groupby("arm", sort=True):
        g = g.set_index("measure")
        parts = []
        for measure, word in (("iteration", "iterations"), ("env_steps", "env steps"), ("wall_time_s", "wall time")):
            r = g.loc[measure]
            if math.isnan(r["ratio"]):
                parts.append(f"{word}: – ({r['note']})")
                continue
            if r["bound"]:  # against an arm that never got there "within noise" would mislead
                tail = f"; {'a lower' if r['bound'] == 'lower' else 'an upper'} bound"
            else:
                tail = "; CI contains 1: within noise" if r["ci_low"] <= 1.0 <= r["ci_high"] else ""
            parts.append(f"{word} ×{_fmt(r['ratio'])} [{_fmt(r['ci_low'])}, {_fmt(r['ci_high'])}]{tail}")
        note = g.loc["iteration", "note"]
        lines.append(f"- `{arm}` vs `{baseline}`, time to success ≥ {opts.success_threshold:g}: " + "; ".join(parts)
                     + (f" ({note})" if note else "") + ".")
        m = g.loc["mastery_median"]
        lines.append(f"  Median per-bin mastery speedup ×{_fmt(m['ratio'])} ({m['note']}).")
    return lines


def _sensitivity_figure(sens: pd.DataFrame, key: str, reference: dict) -> Figure:
    metrics = ["final_failure", "mastery_median", "time_iteration"]
    fig = Figure(figsize=(10.5, 3.2), layout="constrained")
    for ax, metric in zip(fig.subplots(1, 3), metrics, strict=True):
        plots.plot_sensitivity(sens[sens["key"] == key], metric, ax=ax, reference=reference.get(metric))
    return fig


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
          f"Mastery threshold: failure < {opts.mastery_threshold:g}; success threshold: overall success ≥ "
          f"{opts.success_threshold:g}; intervals: {opts.confidence:.0%} percentile bootstrap over seeds "
          f"({opts.n_resamples} resamples, RNG seed {opts.bootstrap_seed}).", ""]
    if shared:
        md += [f"Arms are named by the overrides that differ between them; all share `{','.join(shared)}`.", ""]
    md += _runs_section(runs)
    if not runs["included"].any():
        md += ["No run has usable tables yet; nothing else to report."]
        write_text(out / "report.md", "\n".join(md) + "\n")
        return out

    baseline, baseline_note = tables.choose_baseline(runs, opts.baseline)
    train, eval_df, sampler_df = (load_table(runs, n) for n in ("train_metrics", "eval", "sampler"))
    segments = load_segments(runs)
    bins = bin_table(eval_df, segments)
    colors = plots.arm_colors(runs["arm"].dropna())
    overall = tables.overall(eval_df)
    bin_fail = tables.bin_failure(eval_df)
    mastery_df = tables.mastery(bin_fail, bins, opts)
    times = tables.run_times(overall, opts)
    summary = tables.arm_summary(runs, overall, mastery_df, times, opts)

    curves = tables.learning_curves(train, overall, opts)
    write_csv(out / "curves.csv", curves)
    figures = []
    for metric, (_, label) in tables.CURVE_METRICS.items():
        c = curves[curves["metric"] == metric] if len(curves) else curves
        if len(c):
            name = f"curve_{metric}.png"
            save_figure(out / name, plots.plot_learning_curve(c, label, colors=colors,
                                                              title="IQM over seeds, 95% bootstrap band"))
            figures.append((name, f"Learning curve: {label}"))

    write_csv(out / "bin_failure.csv", bin_fail)
    save_figure(out / "bin_failure_heatmap.png", plots.plot_bin_heatmaps(bin_fail, "failure_rate", bins=bins))
    figures.append(("bin_failure_heatmap.png", "Evaluated failure rate per bin over training (mean over seeds)"))
    final_bins = tables.final_bin_failure(eval_df, opts).merge(bins[["bin", "segment"]], on="bin", how="left")
    write_csv(out / "final_bin_failure.csv", final_bins)
    save_figure(out / "final_bin_failure.png", plots.plot_final_bin_failure(final_bins, bins=bins, colors=colors))
    figures.append(("final_bin_failure.png", "Final evaluated failure per bin (IQM over seeds, 95% interval)"))

    samp = tables.sampling(sampler_df, runs)
    if len(samp):
        write_csv(out / "sampling.csv", samp)
        save_figure(out / "sampling_distribution.png",
                    plots.plot_bin_heatmaps(samp, "probability", bins=bins, cmap="viridis"))
        figures.append(("sampling_distribution.png", "Sampling distribution over training, adaptive arms (mean over seeds)"))

    write_csv(out / "mastery.csv", mastery_df)
    save_figure(out / "mastery.png", plots.plot_mastery(mastery_df, bins=bins, colors=colors,
                                                        threshold=opts.mastery_threshold))
    figures.append(("mastery.png", "Mastery iteration per bin"))
    write_csv(out / "time_to_threshold.csv", times)
    write_csv(out / "summary.csv", summary)

    md += ["## Summary", "", *_winner_text(summary, opts), f"- Speedups: {baseline_note}."]
    speed = None
    if baseline is not None and len(summary) > 1:
        per_bin, speed = tables.speedups(mastery_df, times, baseline, opts)
        write_csv(out / "mastery_speedup.csv", per_bin)
        write_csv(out / "speedup.csv", speed)
        save_figure(out / "speedup.png", plots.plot_speedup(speed.dropna(subset=["ratio"]), colors=colors))
        figures.append(("speedup.png", f"Speedup vs `{baseline}` (baseline / arm, > 1: arm faster)"))
        md += _speedup_text(speed, baseline, opts)
    md += ["", "## Arms", "", md_table(_summary_view(summary)), ""]

    seg = tables.segment_failure(eval_df, bins, mastery_df, segments, opts)
    if len(seg):
        write_csv(out / "segment_failure.csv", seg)
        md += ["## Segments", "", "Final failure per motion segment (mean over its bins, IQM over seeds, 95% interval); "
               "(n/m): n of the segment's m bins never mastered.", "",
               md_table(_segment_view(seg)), ""]

    sens = tables.sensitivity(runs, summary)
    if len(sens):
        write_csv(out / "sensitivity.csv", sens)
        ref = {}
        if baseline is not None:
            b = summary.set_index("arm").loc[baseline]
            ref = {m: {f"{baseline} (baseline)": float(b[m])}
                   for m in ("final_failure", "mastery_median", "time_iteration")}
        md += ["## Sensitivity", ""]
        for key in sorted(sens["key"].unique()):
            name = f"sensitivity_{key.replace('/', '_')}.png"
            save_figure(out / name, _sensitivity_figure(sens, key, ref))
            figures.append((name, f"Sensitivity to `{key}`"))
            view = sens[(sens["key"] == key)].pivot_table(index=["value", "series"], columns="metric", values="iqm")
            md += [f"`{key}`:", "", md_table(view.reset_index()), ""]

    if speed is not None:
        md += ["## Speedup", "", md_table(speed), "", "Per-bin mastery (iteration; – = never):", "",
               md_table(_mastery_view(mastery_df)), ""]
    md += ["## Figures", ""] + [f"### {title}\n\n![{title}]({name})\n" for name, title in figures]
    md += _definitions(opts)
    write_text(out / "report.md", "\n".join(md) + "\n")
    return out


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


def _summary_view(summary: pd.DataFrame) -> pd.DataFrame:
    return pd.DataFrame({
        "arm": summary["arm"],
        "seeds (running)": [f"{n} ({r})" for n, r in zip(summary["n_seeds"], summary["n_running"], strict=True)],
        "final failure": [_ci(p, lo, hi) for p, lo, hi in zip(summary["final_failure"], summary["final_failure_low"],
                                                              summary["final_failure_high"], strict=True)],
        "bins never mastered": [f"{n}/{b}" for n, b in zip(summary["bins_never_mastered"], summary["num_bins"], strict=True)],
        "median mastery it.": summary["mastery_median"],
        "reached threshold": [f"{n}/{s}" for n, s in zip(summary["n_reached"], summary["n_seeds"], strict=True)],
        "iterations to threshold": [_ci(p, lo, hi) for p, lo, hi in zip(
            summary["time_iteration"], summary["time_iteration_low"], summary["time_iteration_high"], strict=True)],
        "env steps to threshold": [_ci(p, lo, hi) for p, lo, hi in zip(
            summary["time_env_steps"], summary["time_env_steps_low"], summary["time_env_steps_high"], strict=True)],
        "wall time to threshold (s)": [_ci(p, lo, hi) for p, lo, hi in zip(
            summary["time_wall_time_s"], summary["time_wall_time_s_low"], summary["time_wall_time_s_high"], strict=True)],
    })


def _segment_view(seg: pd.DataFrame) -> pd.DataFrame:
    seg = seg.assign(cell=[f"{_ci(p, lo, hi)} ({n}/{b})" for p, lo, hi, n, b in zip(
        seg["final_failure"], seg["final_failure_low"], seg["final_failure_high"], seg["bins_never_mastered"],
        seg["num_bins"], strict=True)])
    view = seg.pivot_table(index=["segment", "difficulty"], columns="arm", values="cell", aggfunc="first", sort=False)
    return view.reset_index()


def _mastery_view(mastery_df: pd.DataFrame) -> pd.DataFrame:
    view = mastery_df.pivot(index="bin", columns="arm", values="mastery_iteration").reset_index()
    segments = mastery_df.drop_duplicates("bin")[["bin", "segment"]]
    return segments.merge(view, on="bin")


def _definitions(opts: ReportOptions) -> list[str]:
    return ["## Definitions", "",
            "- Overall failure of an evaluation = unweighted mean of the per-bin failure rates; success = 1 − failure.",
            f"- A bin's mastery iteration = the first evaluation at which the arm's seed-mean failure rate of that bin "
            f"is < {opts.mastery_threshold:g}; it need not stay below afterwards. Never below: `–` (never).",
            "- Per-bin mastery speedup = baseline / arm. Bins never mastered by either arm are excluded; a bin "
            "mastered by one arm only counts the other at its last evaluation (a lower bound on the ratio when the "
            "baseline never mastered it, an upper bound when the arm never did).",
            f"- Time to threshold = first evaluation with overall success ≥ {opts.success_threshold:g}, per seed, in "
            "iterations, env steps and wall time; seeds that never reached it count at their last evaluation (a lower "
            "bound), `never` when no seed of the arm reached it.",
            "- IQM = mean of the middle half of the seeds (floor(n/4) dropped at each end). Intervals: percentile "
            "bootstrap over seeds, stratified by arm for ratios. A difference is called within noise when two "
            "arms' intervals overlap or a ratio's interval contains 1.", ""]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m analysis.report", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=Path, help="sweep folder, run folder(s), or folders holding runs")
    parser.add_argument("--out", type=Path, default=None, help="report folder (default: <PATH>/report)")
    parser.add_argument("--mastery-threshold", type=float, default=0.1, help="bin mastered when failure < this")
    parser.add_argument("--success-threshold", type=float, default=0.9, help="overall success for time to threshold")
    parser.add_argument("--baseline", default=None, help="baseline arm (default: the arm whose sampler is uniform)")
    parser.add_argument("--resamples", type=int, default=tables.DEFAULT_RESAMPLES, help="bootstrap resamples")
    args = parser.parse_args(argv)
    opts = ReportOptions(mastery_threshold=args.mastery_threshold, success_threshold=args.success_threshold,
                         baseline=args.baseline, n_resamples=args.resamples)
    try:
        out = build_report(args.paths, args.out, opts)
    except AnalysisError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"report written to {out / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
