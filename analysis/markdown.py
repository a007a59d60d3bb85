"""The report's text: number formatting, markdown tables and the sentences of report.md."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import pandas as pd

from analysis import tables
from analysis.stats import MIN_SEEDS_BOOTSTRAP, MIN_SEEDS_IQM
from analysis.tables import ReportOptions
from bmimic.runs.schema import BIN, ENV_STEPS, HORIZON_TRUNCATED, ITERATION, WALL_TIME_S

MEASURE_WORDS = {ITERATION: "iterations", ENV_STEPS: "env steps", WALL_TIME_S: "wall time (s)"}


def _verdict(claim: bool, opts: ReportOptions) -> str:
    return f"a difference at the {opts.alpha:g} level" if claim else f"no difference shown at the {opts.alpha:g} level"


def plural(n: int, word: str) -> str:
    """``"1 bin"``, ``"2 bins"``."""
    return f"{n} {word}" if n == 1 else f"{n} {word}s"


def is_nan(x) -> bool:
    """None or a float NaN (a missing number in a table)."""
    return x is None or (isinstance(x, float | np.floating) and math.isnan(x))


def fmt(x, digits: int = 3) -> str:
    """A table cell: 3 significant digits, whole numbers without decimals, - for missing, yes/no, infinities."""
    if is_nan(x):
        return "–"
    if isinstance(x, bool | np.bool_):
        return "yes" if x else "no"
    if isinstance(x, float | np.floating):
        if math.isinf(x):
            return "∞" if x > 0 else "-∞"
        if float(x).is_integer() and abs(float(x)) < 1e7:
            return str(int(x))
        return f"{x:.{digits}g}"
    return str(x)


def per_seed_list(per_seed: str) -> str:
    """A `per_seed` column value (`;`-separated) as a comma-separated list of formatted numbers."""
    return ", ".join(fmt(float(v)) for v in str(per_seed).split(";") if v != "")


def estimate_cell(point, low, high, method: str, n: int, per_seed: str = "") -> str:
    """``0.1 [0.08, 0.12]`` with a bootstrap interval, else ``0.1 (range of 3 seeds: 0.08-0.12)``;
    the point is the IQM from 4 seeds, else the mean (said when it is the mean); per-seed values follow."""
    if is_nan(point):
        return "–"
    if n <= 1:
        return f"{fmt(point)} (1 seed)"
    label = "IQM" if n >= MIN_SEEDS_IQM else "mean"
    seeds = f"; seeds {per_seed_list(per_seed)}" if per_seed else ""
    if method and method.startswith("bootstrap"):
        return f"{fmt(point)} [{fmt(low)}, {fmt(high)}] ({label}{seeds})"
    return f"{fmt(point)} ({label}; range of {n} seeds: {fmt(low)}–{fmt(high)}{seeds})"


def md_table(df: pd.DataFrame) -> str:
    """A GitHub markdown table of ``df`` (cells formatted with 3 significant digits)."""
    if not len(df):
        return "_(none)_\n"
    head = "| " + " | ".join(str(c) for c in df.columns) + " |"
    rule = "|" + "|".join("---" for _ in df.columns) + "|"
    body = ["| " + " | ".join(fmt(v).replace("|", "\\|") for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, rule, *body]) + "\n"


def summary_row(summary: pd.DataFrame, arm: str, metric: str):
    """The summary.csv row of `arm` and `metric` (None when absent)."""
    r = summary[(summary["arm"] == arm) & (summary["metric"] == metric)]
    return None if not len(r) else r.iloc[0]


def cell(summary: pd.DataFrame, arm: str, metric: str) -> str:
    """The estimate_cell of `arm`'s `metric` in summary.csv (- when absent)."""
    r = summary_row(summary, arm, metric)
    return "–" if r is None else row_cell(r)


def row_cell(r: Mapping, prefix: str = "") -> str:
    """The estimate_cell of one row of tables.summary_rows (a summary.csv row, or keys that each start
    with `prefix` in a wider row): the IQM from MIN_SEEDS_IQM seeds, else the mean; - without seeds."""
    n = r.get(f"{prefix}n_seeds")
    if n is None or is_nan(n):
        return "–"
    point = r[f"{prefix}iqm"] if n >= MIN_SEEDS_IQM else r[f"{prefix}mean"]
    return estimate_cell(point, r[f"{prefix}ci_low"], r[f"{prefix}ci_high"], str(r[f"{prefix}ci_method"]), int(n),
                         str(r[f"{prefix}per_seed"]))


def p_text(p: float, smallest: float, corrected: str = "uncorrected") -> str:
    """``p = 0.029 (uncorrected; smallest attainable 0.029)``: a p-value, what it is corrected for,
    and the smallest p the test could give with these seeds (stats.smallest_pvalue)."""
    return f"p = {fmt(p, 2)} ({corrected}; smallest attainable {fmt(smallest, 2)})"


def winner_text(comp: pd.DataFrame, summary: pd.DataFrame, metric: str, what: str, at: str,
                 opts: ReportOptions, noun: str | None = None) -> list[str]:
    """Which arm has the lowest ``metric``, and for every other arm the difference of means and its
    p-value. The lowest arm is picked after seeing the data, so the tests are post hoc and say so.
    Arms whose points are exactly equal to the lowest tie: no winner is named. ``noun``: ``what`` as
    it reads after "Lowest" (default: lower-cased)."""
    rows = summary[summary["metric"] == metric]
    if not len(rows):
        return [f"- {what}: no arm has a value yet."]
    if len(rows) == 1:
        arm = rows.iloc[0]["arm"]
        return [f"- {what} ({at}): `{arm}` {cell(summary, arm, metric)}."]
    best = comp["best"].iloc[0] if len(comp) else rows.iloc[0]["arm"]
    tied = [best, *comp.loc[comp["point"] == comp["best_point"], "arm"]]
    if len(tied) > 1:
        lines = [f"- {what} ({at}): {', '.join(f'`{a}`' for a in sorted(tied))} tie at "
                 f"{fmt(comp['best_point'].iloc[0])}: no winner."]
    elif len(comp) == 1:  # two arms: one two-sided test, whichever arm is named first
        lines = [f"- Lowest {noun or what.lower()} ({at}): **`{best}`** {cell(summary, best, metric)}."]
    else:
        lines = [f"- Lowest {noun or what.lower()} ({at}): **`{best}`** {cell(summary, best, metric)}. This arm "
                 f"was picked after seeing the data: the {len(comp)} tests against it below are post hoc and "
                 "uncorrected (for that choice and for their number)."]
    corrected = "one two-sided test" if len(comp) == 1 else "post hoc, uncorrected"
    for r in comp[comp["point"] != comp["best_point"]].itertuples(index=False):
        lines.append(f"  - `{r.arm}` {cell(summary, r.arm, metric)}: {_direction(r.difference)} "
                     f"(difference of means over seeds, the statistic tested), "
                     f"{p_text(r.p_value, r.smallest_p, corrected)}: {_verdict(r.claim, opts)}.")
    return lines


def _direction(difference: float) -> str:
    """``mean higher by 0.01`` / ``mean lower by 0.01`` / ``equal means``."""
    if difference == 0 or is_nan(difference):
        return "equal means"
    return f"mean {'lower' if difference < 0 else 'higher'} by {fmt(abs(difference))}"


def baseline_text(comp: pd.DataFrame, summary: pd.DataFrame, metric: str, what: str, at: str,
                  opts: ReportOptions) -> list[str]:
    """Every arm's ``metric`` against the baseline's (:func:`analysis.comparisons.baseline_comparisons`): a
    sentence and a table with the uncorrected and Holm-adjusted p-values."""
    if not len(comp):
        return []
    base = comp["baseline"].iloc[0]
    k = len(comp)
    lines = [f"- {what} against the baseline `{base}` {cell(summary, base, metric)} ({at}): two-sided permutation "
             f"tests of the difference of per-seed means, one per arm; `p` is uncorrected, `p (Holm)` is adjusted "
             f"for the {plural(k, 'test')} (Holm's step-down), and the verdict uses it.", ""]
    view = pd.DataFrame({
        "arm": [f"`{a}`" for a in comp["arm"]],
        "mean (arm)": comp["mean"], "mean (baseline)": comp["baseline_mean"],
        "difference of means (arm − baseline)": comp["difference"],
        "p (uncorrected)": [fmt(p, 2) for p in comp["p_value"]],
        f"p (Holm, {plural(k, 'test')})": [fmt(p, 2) for p in comp["p_holm"]],
        "smallest attainable p": [fmt(p, 2) for p in comp["smallest_p"]],
        "verdict (Holm)": [_verdict(c, opts) for c in comp["claim_holm"]],
    })
    return lines + [md_table(view)]


def speedup_phrase(r, time_row_base, time_row_arm, word: str) -> str:
    """One measure's speedup in words: the estimate with its interval, or the bound and why."""
    from analysis.stats import smallest_pvalue

    p = p_text(r.p_value, smallest_pvalue(int(time_row_arm["n_seeds"]), int(time_row_base["n_seeds"])))
    if r.status == "estimate":
        ci = (f" [{fmt(r.ci_low)}, {fmt(r.ci_high)}]" if not is_nan(r.ci_low)
              else f" (no interval below {MIN_SEEDS_BOOTSTRAP} seeds per arm)")
        return f"{word} ×{fmt(r.ratio)}{ci}, {p}"
    if r.status == "lower_bound":
        return (f"{word} ≥ ×{fmt(r.ratio)} (a lower bound: the baseline's median was not reached within "
                f"{fmt(time_row_base['follow_up'])}; {p})")
    if r.status == "upper_bound":
        return (f"{word} ≤ ×{fmt(r.ratio)} (an upper bound: the arm's median was not reached within "
                f"{fmt(time_row_arm['follow_up'])}; {p})")
    return (f"{word}: not estimable (neither median reached: {int(time_row_arm['n_reached'])}/"
            f"{int(time_row_arm['n_seeds'])} arm seeds, {int(time_row_base['n_reached'])}/"
            f"{int(time_row_base['n_seeds'])} baseline seeds got there)")


def speedup_text(speed: pd.DataFrame, per_bin: pd.DataFrame, time_df: pd.DataFrame, baseline: str,
                  opts: ReportOptions) -> list[str]:
    """Per arm: the speedups against the baseline at the report's success threshold and a summary of its
    per-bin mastery speedups."""
    lines = []
    t = time_df.set_index(["arm", "measure"])
    for arm, g in speed.groupby("arm", sort=True):
        parts = [speedup_phrase(r, t.loc[(baseline, r.measure)], t.loc[(arm, r.measure)], MEASURE_WORDS[r.measure])
                 for r in g.itertuples(index=False)]
        lines.append(f"- `{arm}` vs `{baseline}`, time to overall success ≥ {opts.success_threshold:g} "
                     f"(baseline median / arm median): " + "; ".join(parts) + ".")
        lines += mastery_speedup_line(per_bin, arm, opts)
    return lines


def speed_view(speed: pd.DataFrame, time_df: pd.DataFrame) -> pd.DataFrame:
    """The Speedup table (speedup.csv) with its columns named, and the smallest attainable p."""
    from analysis.stats import smallest_pvalue

    n = time_df.drop_duplicates("arm").set_index("arm")["n_seeds"]
    return pd.DataFrame({
        "arm": speed["arm"], "baseline": speed["baseline"], "measure": speed["measure"].map(MEASURE_WORDS),
        "ratio (baseline / arm)": speed["ratio"], "interval low": speed["ci_low"], "interval high": speed["ci_high"],
        "status": speed["status"], "p (uncorrected)": [fmt(p, 2) for p in speed["p_value"]],
        "smallest attainable p": [fmt(smallest_pvalue(int(n[a]), int(n[b])), 2)
                                  for a, b in zip(speed["arm"], speed["baseline"], strict=True)],
    })


def mastery_speedup_line(per_bin: pd.DataFrame, arm: str, opts: ReportOptions) -> list[str]:
    """One arm's per-bin mastery speedups in one indented line (none without per-bin rows)."""
    b = per_bin[per_bin["arm"] == arm]
    if not len(b):
        return []
    est = b[b["status"] == "estimate"]
    counts = b["status"].value_counts()
    text = (f"  Per-bin mastery speedups: {plural(len(est), 'bin')} estimable"
            + (f" (median ratio ×{fmt(float(np.median(est['ratio'])))})" if len(est) else ""))
    for status, word in (("lower_bound", "lower bound"), ("upper_bound", "upper bound"),
                         ("not_estimable", "not estimable")):
        if counts.get(status, 0):  # "not estimable" is an adjective: never pluralised
            n = int(counts[status])
            text += f", {n} not estimable" if status == "not_estimable" else f", {plural(n, word)}"
    sig = b[b["p_value"] < opts.alpha]
    faster, slower = int((sig["ratio"] > 1).sum()), int((sig["ratio"] < 1).sum())
    text += (f"; p < {opts.alpha:g} in {plural(len(sig), 'bin')} of {len(b)} "
             f"({faster} faster, {slower} slower; uncorrected for {plural(len(b), 'test')}).")
    return [text]


def evaluation_notes(eval_df: pd.DataFrame, bins: pd.DataFrame) -> list[str]:
    """Notes on old-accounting tables and horizon-truncated bins (empty when there are none)."""
    lines = []
    if "visits" not in eval_df.columns or eval_df["visits"].isna().any():
        lines.append("- Some runs' eval.parquet predates per-visit accounting: there `failure_rate` is the failure "
                     "rate of the episodes that *started* in a bin (a failure was charged to the start bin), and "
                     "bins whose episodes run out of clip before the horizon are not flagged.")
    truncated = bins.loc[bins[HORIZON_TRUNCATED], BIN].tolist()
    if truncated:
        one = len(truncated) == 1
        its, they = ("its", "it is") if one else ("their", "they are")
        lines.append(f"- Horizon-truncated {'bin' if one else 'bins'} {', '.join(map(str, truncated))}: {its} "
                     f"episodes reach the end of the clip before the evaluation horizon, so {they} hatched in the "
                     f"figures and count{'s' if one else ''} as mastered only when an episode tracked all of "
                     f"{its} frames after entering from an earlier bin.")
    return lines + ([""] if lines else [])


def budget_section(budget: pd.DataFrame, opts: ReportOptions, kinds: pd.Series | None = None,
                   machines: str = "") -> list[str]:
    """The report's budget table (completed iterations, env steps, wall time per machine kind) and its
    warnings. ``kinds``: the machine kind of each run (analysis.machines); ``machines``: the sentence
    saying why wall times are not compared (empty when every run trained on one kind)."""
    if not len(budget):
        return []
    budget = budget.assign(machine=budget["run_dir"].map(kinds) if kinds is not None else "")
    g = budget.groupby(["arm", "machine"], sort=True)
    view = pd.DataFrame({
        "arm": [a for a, _ in g.groups],
        "iterations": [span(x) for _, x in g["iterations"]],
        "env steps": [span(x) for _, x in g[ENV_STEPS]],
        "wall time (s)": [span(x) for _, x in g[WALL_TIME_S]],
    })
    if kinds is not None:
        view.insert(1, "machine (provenance.json)", [k for _, k in g.groups])
        view.insert(2, "runs", g.size().to_numpy())
    note = (f" {machines}" if machines else " Every run trained on one machine kind, so wall-time speedups are "
            "printed; runs that shared a GPU (CUDA MPS) are slower than alone, which provenance.json does not record.")
    lines = ["## Budget", "", "Completed per run (min–max over seeds, per arm and machine kind). Arms are compared "
             "at equal iterations and env steps." + note, "", md_table(view)]
    warning = tables.budget_warning(budget, opts)
    if warning:
        lines += [warning, ""]
    return lines


def span(x: pd.Series) -> str:
    """min-max of a column as text (one value when they agree)."""
    lo, hi = float(x.min()), float(x.max())
    return fmt(lo) if lo == hi else f"{fmt(lo)}–{fmt(hi)}"


def runs_section(runs: pd.DataFrame) -> list[str]:
    """The runs per arm and status, the running ones included and the ones left out, with why."""
    counts = runs.groupby(["arm", "status"]).size().unstack(fill_value=0).reset_index()
    lines = ["## Runs", "", md_table(counts), ""]
    running = runs[runs["included"] & runs["status"].isin(["running", "interrupted"])]
    if len(running):
        lines += ["Still running or interrupted (to be resumed), included with their partial tables:", ""]
        lines += [f"- `{r.arm}` seed {r.seed}: up to iteration {r.iteration} (`{r.run_dir}`)" for r in running.itertuples()]
        lines.append("")
    excluded = runs[~runs["included"]]
    if len(excluded):
        lines += ["Not included (failed, missing or without usable tables):", ""]
        lines += [f"- `{r.arm}` seed {r.seed}: {r.status} — {r.problem} (`{r.run_dir}`)" for r in excluded.itertuples()]
        lines.append("")
    return lines


def time_cell(time_df: pd.DataFrame, arm: str, measure: str) -> str:
    """An arm's median time to threshold in `measure`, with the seeds that got there and their times."""
    r = time_df[(time_df["arm"] == arm) & (time_df["measure"] == measure)]
    if not len(r):
        return "–"
    r = r.iloc[0]
    head = fmt(r["median"]) if not is_nan(r["median"]) else f"not reached (> {fmt(r['follow_up'])})"
    seeds = ", ".join(fmt(float(v)) if not v.startswith(">") else f">{fmt(float(v[1:]))}"
                      for v in str(r["per_seed"]).split(";"))
    return f"{head} ({int(r['n_reached'])}/{int(r['n_seeds'])} seeds; {seeds})"


FAILURE_UNIT = "failed / started episodes"
"""The unit of every overall, clip and segment failure in the report (per-bin rates are per visit)."""


def arms_view(summary: pd.DataFrame, time_df: pd.DataFrame, per_run: dict, at: str,
              measures=("iteration", ENV_STEPS, WALL_TIME_S)) -> pd.DataFrame:
    """The Arms table: per arm its final failure, bins mastered and times to threshold (``measures``:
    wall time only where it compares)."""
    arms = sorted(set(summary["arm"]))
    view = {"arm": arms, "seeds": [int(summary.loc[summary["arm"] == a, "n_seeds"].max()) for a in arms],
            f"final failure ({FAILURE_UNIT}; {at.split(',')[0]})": [cell(summary, a, "final_failure") for a in arms]}
    if "final_failure_equal_env_steps" in per_run:
        view[f"final failure ({FAILURE_UNIT}; equal env steps)"] = [
            cell(summary, a, "final_failure_equal_env_steps") for a in arms]
    if "final_failure_robust" in per_run:
        view[f"final failure, robust eval ({FAILURE_UNIT})"] = [cell(summary, a, "final_failure_robust") for a in arms]
    view["bins mastered (count)"] = [cell(summary, a, "bins_mastered") for a in arms]
    for m in measures:
        view[f"{MEASURE_WORDS[m]} to threshold (KM median)"] = [time_cell(time_df, a, m) for a in arms]
    return pd.DataFrame(view)


NOT_RECORDED = "not recorded"
"""A cell of a quantity the arm's evaluation tables do not have (runs from before it was recorded)."""


def tracking_view(summary: pd.DataFrame, metrics: dict[str, str], seeds: dict[str, int] | None = None) -> pd.DataFrame:
    """Per arm (rows) the summary metric of every ``metrics`` key (metric -> column label): "not
    recorded" where the arm has no value, and "recorded by k of n seeds" where only some runs had it
    (``seeds``: the arm's included runs)."""
    arms = sorted(set(summary["arm"]) | set(seeds or {}))
    view = {"arm": arms}
    for metric, label in metrics.items():
        cells = []
        for a in arms:
            r = summary_row(summary, a, metric)
            if r is None:
                cells.append(NOT_RECORDED)
                continue
            text = cell(summary, a, metric)
            n = (seeds or {}).get(a)
            cells.append(text + (f"; recorded by {int(r['n_seeds'])} of {n} seeds" if n and r["n_seeds"] < n else ""))
        view[label] = cells
    return pd.DataFrame(view)


def segment_view(seg: pd.DataFrame) -> pd.DataFrame:
    """The Segments table: one row per segment and arm, every column named with its unit."""
    return pd.DataFrame({
        "segment": seg["segment"], "difficulty": seg["difficulty"], "arm": seg["arm"],
        f"final failure ({FAILURE_UNIT}, by start segment)": [estimate_cell(p, lo, hi, m, n) for p, lo, hi, m, n in zip(
            seg["final_failure"], seg["final_failure_low"], seg["final_failure_high"], seg["ci_method"],
            seg["n_seeds"], strict=True)],
        "bins not mastered / bins": [f"{nm}/{b}" for nm, b in zip(seg["bins_not_mastered"], seg["num_bins"],
                                                                  strict=True)],
    })


def mastery_view(mastery_df: pd.DataFrame) -> pd.DataFrame:
    """The per-bin mastery table: median mastery iteration per bin (rows) and arm (columns)."""
    cells = mastery_df.assign(cell=[f"{fmt(m)} ({k}/{n})" for m, k, n in zip(
        mastery_df["mastery_iteration"], mastery_df["n_mastered"], mastery_df["n_seeds"], strict=True)])
    view = cells.pivot(index=BIN, columns="arm", values="cell").reset_index()
    meta = mastery_df.drop_duplicates(BIN)[[BIN, "segment", HORIZON_TRUNCATED]]
    meta = meta.assign(**{BIN: [f"{b}†" if t else str(b) for b, t in zip(meta[BIN], meta[HORIZON_TRUNCATED], strict=True)]},
                       _key=meta[BIN])
    view = meta.merge(view.rename(columns={BIN: "_key"}), on="_key").drop(columns=["_key", HORIZON_TRUNCATED])
    return view
