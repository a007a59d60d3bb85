"""The report's sentences and tables for the speedup curve, the iso-failure ratios and the sampler's
adaptation (analysis.speedup_curve, analysis.adaptation)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from analysis.markdown import fmt, is_nan, mastery_speedup_line, md_table, p_text, plural, speedup_phrase
from analysis.tables import ReportOptions
from bmimic.runs.schema import ENV_STEPS, ITERATION, WALL_TIME_S


def threshold_ranges(values, grid) -> str:
    """Thresholds as runs of consecutive grid entries: ``0.5–0.7, 0.9, 0.92–0.94``."""
    grid = sorted(float(g) for g in grid)
    pos = sorted(grid.index(float(v)) for v in values)
    runs, start, prev = [], None, None
    for i in pos:
        if start is None:
            start = prev = i
        elif prev is not None and i == prev + 1:
            prev = i
        else:
            runs.append((start, prev))
            start = prev = i
    if start is not None:
        runs.append((start, prev))
    return ", ".join(fmt(grid[a]) if a == b else f"{fmt(grid[a])}–{fmt(grid[b])}" for a, b in runs)


def curve_phrase(g: pd.DataFrame, opts: ReportOptions) -> str:
    """One arm's speedup curve in one measure, in words: the range of the estimates with the thresholds
    where each end occurs, the value at the report's threshold, and where it is only a bound or not
    estimable."""
    grid = g["threshold"].tolist()
    est = g[g["status"] == "estimate"]
    parts = []
    if len(est):
        r = est["ratio"].map(fmt)
        lo, hi = est.loc[est["ratio"].idxmin()], est.loc[est["ratio"].idxmax()]
        at_lo = threshold_ranges(est.loc[r == fmt(lo["ratio"]), "threshold"], grid)
        at_hi = threshold_ranges(est.loc[r == fmt(hi["ratio"]), "threshold"], grid)
        if fmt(lo["ratio"]) == fmt(hi["ratio"]):
            parts.append(f"×{fmt(lo['ratio'])} at every threshold where both medians were reached "
                         f"({threshold_ranges(est['threshold'], grid)})")
        else:
            parts.append(f"from ×{fmt(lo['ratio'])} (at {at_lo}) to ×{fmt(hi['ratio'])} (at {at_hi}) over the "
                         f"thresholds where both medians were reached ({threshold_ranges(est['threshold'], grid)})")
    main = g[np.isclose(g["threshold"], opts.success_threshold)]
    if len(main) and main.iloc[0]["status"] == "estimate":
        m = main.iloc[0]
        ci = f" [{fmt(m['ci_low'])}, {fmt(m['ci_high'])}]" if not is_nan(m["ci_low"]) else " (no interval)"
        parts.append(f"at {opts.success_threshold:g}: ×{fmt(m['ratio'])}{ci}, "
                     f"{p_text(m['p_value'], m['smallest_p'], 'uncorrected')}")
    for status, sign, why in (("lower_bound", "≥", "the baseline's median not reached"),
                              ("upper_bound", "≤", "the arm's median not reached")):
        b = g[g["status"] == status]
        if len(b):
            lo, hi = fmt(b["ratio"].min()), fmt(b["ratio"].max())
            value = f"{sign} ×{lo}" if lo == hi else f"{sign} ×{lo} to {sign} ×{hi}"
            parts.append(f"{threshold_ranges(b['threshold'], grid)}: {value} ({why}: a bound)")
    ne = g[g["status"] == "not_estimable"]
    if len(ne):
        parts.append(f"{threshold_ranges(ne['threshold'], grid)}: not estimable (neither median reached)")
    return "; ".join(parts) if parts else "no threshold"


def speedup_curve_text(curve: pd.DataFrame, speed: pd.DataFrame, per_bin: pd.DataFrame, time_df: pd.DataFrame,
                       opts: ReportOptions, machines: str = "") -> list[str]:
    """Per arm: the speedup as a range over success thresholds (iterations, env steps), the wall-time
    speedup at the report's threshold where wall times compare (else ``machines`` says why not), and
    the per-bin mastery speedups."""
    lines = []
    t = time_df.set_index(["arm", "measure"])
    for arm, g in curve.groupby("arm", sort=True):
        base = g["baseline"].iloc[0]
        its = g[g["measure"] == "iteration"].sort_values("threshold")
        steps = g[g["measure"] == ENV_STEPS].sort_values("threshold")
        text = (f"- `{arm}` vs `{base}`, speedup in time to overall success (baseline median / arm median over "
                f"seeds; success thresholds {fmt(g['threshold'].min())}–{fmt(g['threshold'].max())}, "
                f"speedup_curve.png): in iterations {curve_phrase(its, opts)}.")
        if len(steps):
            same = np.allclose(steps["ratio"].to_numpy(float), its["ratio"].to_numpy(float), equal_nan=True) and (
                steps["status"].to_numpy() == its["status"].to_numpy()).all()
            text += (" In env steps the same (every run collects the same env steps per iteration)." if same
                     else f" In env steps {curve_phrase(steps, opts)}.")
        wall = speed[(speed["arm"] == arm) & (speed["measure"] == WALL_TIME_S)]
        if len(wall):
            r = wall.iloc[0]
            text += (f" In wall time at {opts.success_threshold:g} (one machine kind): "
                     + speedup_phrase(r, t.loc[(base, WALL_TIME_S)], t.loc[(arm, WALL_TIME_S)], "ratio") + ".")
        elif machines:
            text += " Wall time: not compared (the runs trained on different machine kinds; see Budget)."
        lines.append(text)
        lines += mastery_speedup_line(per_bin, arm, opts)
    return lines


def iso_text(iso: pd.DataFrame) -> list[str]:
    """Per arm: the iso-failure ratio at the baseline's last evaluation and its range over training."""
    lines = []
    d = iso[iso["measure"] == "iteration"]
    for arm, g in d.groupby("arm", sort=True):
        g = g.sort_values("baseline_time")
        last = g.iloc[-1]
        est = g[g["status"] == "estimate"]
        if last["status"] == "estimate":
            at_end = (f"the baseline's failure at its last evaluation ({fmt(last['failure_level'])} at iteration "
                      f"{fmt(last['baseline_time'])}) was reached by the arm at iteration {fmt(round(last['arm_time']))}: "
                      f"×{fmt(last['ratio'])}")
        elif last["status"] == "upper_bound":
            at_end = (f"the arm never reached the baseline's last failure ({fmt(last['failure_level'])}): "
                      f"≤ ×{fmt(last['ratio'])}")
        else:
            at_end = (f"the arm was at the baseline's last failure ({fmt(last['failure_level'])}) from its first "
                      f"evaluation: ≥ ×{fmt(last['ratio'])}")
        span = (f"; over the baseline's evaluations where it is an estimate, ×{fmt(est['ratio'].min())} to "
                f"×{fmt(est['ratio'].max())}" if len(est) else "")
        lines.append(f"- Iso-failure, `{arm}` vs `{g['baseline'].iloc[0]}` (iso_failure.png): {at_end}{span}.")
    return lines


def support_table(summary: pd.DataFrame, max_rows: int = 12) -> pd.DataFrame:
    """Effective support / largest p relative to uniform per evaluation (rows, at most ``max_rows``
    evenly spaced, always the first and last) and arm (columns); over clips in brackets for a library."""
    its = np.unique(summary[ITERATION].to_numpy())
    if len(its) > max_rows:
        its = its[np.unique(np.r_[np.linspace(0, len(its) - 1, max_rows).round().astype(int)])]
    s = summary[summary[ITERATION].isin(its)]

    def text(r) -> str:
        t = f"{r.effective_support:.3f} / ×{r.max_p_rel:.2f}"
        if not is_nan(r.clip_effective_support):
            t += f" (clips {r.clip_effective_support:.3f} / ×{r.clip_max_p_rel:.2f})"
        return t

    cells = s.assign(cell=[text(r) for r in s.itertuples(index=False)])
    view = cells.pivot(index=ITERATION, columns="arm", values="cell").reset_index()
    return view.rename(columns={ITERATION: "evaluation iteration"})


NEAR_UNIFORM = 0.99
"""Effective support at or above which a distribution is called within 1% of uniform over bins."""


def near_uniform_lines(summary: pd.DataFrame, signals: pd.DataFrame) -> list[str]:
    """For every arm with a signal that started within 1% of uniform over bins: until which evaluation
    it stayed there (mean over seeds), or that it stayed there throughout."""
    lines = []
    with_signal = set(signals.loc[signals["has_signal"] & ~signals["constant"], "arm"])
    for arm, g in summary[summary["arm"].isin(with_signal)].groupby("arm", sort=True):
        g = g.sort_values(ITERATION)
        near = (g["effective_support"] >= NEAR_UNIFORM).to_numpy()
        if not near[0]:
            continue
        its = g[ITERATION].to_numpy()
        if near.all():
            lines.append(f"- `{arm}`: within 1% of uniform over bins (effective support ≥ {NEAR_UNIFORM}) at every "
                         f"evaluation, to iteration {fmt(its[-1])}.")
        else:
            k = int(np.argmin(near))
            lines.append(f"- `{arm}`: within 1% of uniform over bins (effective support ≥ {NEAR_UNIFORM}) to "
                         f"iteration {fmt(its[k - 1])}; {g['effective_support'].iloc[k]:.3f} at {fmt(its[k])} and "
                         f"{g['effective_support'].iloc[-1]:.3f} at {fmt(its[-1])}.")
    return lines


def adaptation_section(summary: pd.DataFrame, signals: pd.DataFrame, clip_evals: pd.DataFrame | None = None
                       ) -> list[str]:
    """The Adaptation section: which arms' signals were degenerate, until when the others' were flat, the
    effective-support table and, for evaluation-driven samplers, what their clip rollouts said."""
    if not len(summary):
        return []
    lines = ["## Adaptation", "",
             "Whether each sampler moved away from where it started, from sampler.parquet: effective support "
             "(1 / Σ p²) / S and the largest probability relative to uniform, max p × S (mean over seeds, at the "
             "sampler update logged nearest before each evaluation); over the clips' masses in brackets for a "
             "library. 1.000 / ×1.00 is uniform over bins.", ""]
    degenerate = signals[signals["degenerate"]]
    if len(degenerate):
        lines.append("- **Degenerate signals:** " + ", ".join(f"`{a}`" for a in degenerate["arm"]) + ": the "
                     "sampler's own signal was the same in every bin at every logged iteration of every seed, so "
                     "it never told the sampler where to sample.")
    for r in signals[signals["has_signal"] & ~signals["degenerate"]].itertuples(index=False):
        seeds = r.flat_until.split(";")
        if any(s != "0" for s in seeds):
            lines.append(f"- `{r.arm}`: its signal was flat (equal in every bin) {flat_span(seeds)}.")
    for r in signals[signals["constant"] & signals["has_signal"]].itertuples(index=False):
        lines.append(f"- `{r.arm}`: its sampling distribution never changed over training.")
    lines += near_uniform_lines(summary, signals)
    if clip_evals is not None and len(clip_evals):
        for arm, g in clip_evals.groupby("arm", sort=True):
            per_eval = g.groupby(["run_dir", ITERATION])["failed"].agg(["all", "any"])
            n = len(per_eval)
            lines.append(f"- `{arm}` clip rollouts (one from each clip's first frame per evaluation): every clip "
                         f"failed in {int(per_eval['all'].sum())} and no clip in {int((~per_eval['any']).sum())} of "
                         f"{plural(n, 'evaluation')} (over seeds); in those the signal ranks no clip above another.")
    lines += ["", md_table(support_table(summary)), ""]
    return lines


def curve_cell(r) -> str:
    """One speedup-curve entry: ``×1.55 [1.41, 1.67]``, ``≥ ×1.28``, ``≤ ×0.8`` or ``not estimable``."""
    if r.status == "estimate":
        return f"×{fmt(r.ratio)}" + (f" [{fmt(r.ci_low)}, {fmt(r.ci_high)}]" if not is_nan(r.ci_low) else "")
    if r.status == "lower_bound":
        return f"≥ ×{fmt(r.ratio)}"
    if r.status == "upper_bound":
        return f"≤ ×{fmt(r.ratio)}"
    return "not estimable"


def flat_span(seeds: list[str]) -> str:
    """How long a signal stayed flat, from each seed's first logged iteration at which it was not
    ("never": flat to the end): "until iteration 500, 400 in 2 seeds and throughout in 3 seeds"."""
    became = [s for s in seeds if s != "never"]
    parts = [f"until iteration {', '.join(became)} in {plural(len(became), 'seed')}"] if became else []
    if len(became) < len(seeds):
        parts.append(f"throughout in {plural(len(seeds) - len(became), 'seed')}")
    return " and ".join(parts)


def curve_view(curve: pd.DataFrame, measure: str = "iteration") -> pd.DataFrame:
    """The speedup curve as a table: success threshold (rows) x arm (columns), with the seeds that got
    there (arm / baseline)."""
    c = curve[curve["measure"] == measure]
    cells = c.assign(cell=[f"{curve_cell(r)} ({r.arm_reached}/{r.arm_seeds} vs {r.baseline_reached}/"
                           f"{r.baseline_seeds} seeds)" for r in c.itertuples(index=False)])
    view = cells.pivot(index="threshold", columns="arm", values="cell").reset_index()
    return view.rename(columns={"threshold": "success threshold"})
