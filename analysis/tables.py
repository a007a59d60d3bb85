"""The report's tables, computed from the tidy frames of ``analysis.load``.

Each function takes the loaded tables and returns one tidy frame that is written as a CSV and
drawn by ``analysis.plots``. The statistics follow ``analysis.stats`` (IQM from 4 seeds, bootstrap
intervals only when every arm has 5 seeds, else the range of the seeds; permutation p-values) and
the metric definitions ``analysis.metrics``. Fixed RNG seeds: the same runs always give the same report.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pandas as pd

from analysis import AnalysisError
from analysis.metrics import (
    ERROR_METRICS,
    SMOOTHNESS_METRICS,
    at_budget,
    overall_failure,
)
from analysis.stats import (
    DEFAULT_RESAMPLES,
    MIN_SEEDS_BOOTSTRAP,
    MIN_SEEDS_IQM,
    curve_intervals,
    iqm,
    seed_interval,
)
from bmimic.runs.schema import ENV_STEPS, FAILURE_RATE, ITERATION, MPKPE_REL_MM, WALL_TIME_S, summary_key


@dataclass(frozen=True)
class ReportOptions:
    """Thresholds and statistics settings of a report."""

    mastery_threshold: float = 0.1
    """A bin counts as mastered at an evaluation where its failure rate is below this."""

    mastery_persist: int = 2
    """Mastery (and time to threshold) needs this many consecutive evaluations, or the rest of the run."""

    success_threshold: float = 0.9
    """Overall evaluated success (1 - mean failure over bins) an arm must reach for time to threshold."""

    baseline: str | None = None
    """Arm the speedups are measured against; None picks the arm whose sampler.name is "uniform"."""

    n_resamples: int = DEFAULT_RESAMPLES
    """Bootstrap resamples per interval."""

    confidence: float = 0.95
    """Coverage of the bootstrap intervals."""

    alpha: float = 0.05
    """A difference is claimed when its permutation-test p-value is below this."""

    n_permutations: int = 9999
    """Random relabellings of a permutation test too large to enumerate (stats.EXACT_PERMUTATIONS)."""

    bootstrap_seed: int = 0
    """RNG seed of every bootstrap and permutation test, for reproducible reports."""

    budget_tolerance: float = 0.05
    """The report warns when the runs compared completed iteration counts differing by more than this
    fraction of the largest."""

    max_iteration: int | None = None
    """Read every run only up to this many iterations (a common budget): evaluations at iterations <= it,
    training and sampler rows of the iterations before it, so a longer run is read as if it had stopped
    there. None: every run to its end."""

    max_curve_points: int = 200
    """Training curves are drawn at most at this many evenly spaced iterations (plus the last)."""


CURVE_METRICS = {
    "mean_episode_length": ("train_metrics", "mean episode length (steps)"),
    "mean_reward": ("train_metrics", "mean reward"),
    "eval_failure_rate": ("eval", "evaluated overall failure rate"),
    "eval_mpkpe_rel_mm": ("errors", "evaluated root-relative MPKPE (mm)"),
}
"""Learning-curve metric -> (source table, axis label); ``errors`` is metrics.tracking_errors."""

SUMMARY_COLUMNS = ["arm", "n_seeds", "metric", "mean", "iqm", "ci_low", "ci_high", "ci_method", "per_seed"]
"""Columns of summary.csv: one row per arm and metric."""

SPEEDUP_COLUMNS = ["arm", "baseline", "measure", "ratio", "ci_low", "ci_high", "status", "p_value"]
"""Columns of speedup.csv: one row per arm and measure."""


def choose_baseline(runs: pd.DataFrame, baseline: str | None) -> tuple[str | None, list[str]]:
    """The baseline arm (`baseline` when given, else the first arm whose sampler is uniform; None without
    either) and the uniform arms it was chosen among (empty when given)."""
    arms = runs.loc[runs["included"], ["arm", "sampler"]].drop_duplicates()
    if baseline is not None:
        if baseline not in set(arms["arm"]):
            raise AnalysisError(f"--baseline {baseline!r}: not an arm with usable runs; arms: {sorted(arms['arm'])}")
        return baseline, []
    uniform = sorted(arms.loc[arms["sampler"] == "uniform", "arm"])
    return (uniform[0] if uniform else None), uniform


def seeds_per_arm(runs: pd.DataFrame) -> pd.Series:
    """Included runs per arm (the seeds every statistic is over)."""
    inc = runs[runs["included"]]
    return inc.groupby("arm")["run_dir"].nunique()


def use_bootstrap(runs: pd.DataFrame) -> bool:
    """Bootstrap intervals only when every arm with usable runs has MIN_SEEDS_BOOTSTRAP seeds."""
    n = seeds_per_arm(runs)
    return bool(len(n)) and int(n.min()) >= MIN_SEEDS_BOOTSTRAP


def interval_label(runs: pd.DataFrame, opts: ReportOptions) -> str:
    """How the report's intervals are made, in words."""
    n = seeds_per_arm(runs)
    if use_bootstrap(runs):
        return (f"{opts.confidence:.0%} bootstrap intervals over seeds (BCa where defined, else percentile; "
                f"{opts.n_resamples} resamples, RNG seed {opts.bootstrap_seed})")
    fewest = int(n.min()) if len(n) else 0
    return (f"no bootstrap intervals: an arm has {fewest} seed{'s' if fewest != 1 else ''} (< {MIN_SEEDS_BOOTSTRAP}); "
            "brackets give the range of the seeds (\"range of n seeds\")")


def thin_iterations(iterations, max_points: int) -> np.ndarray:
    """At most ``max_points`` evenly spaced values of the sorted unique ``iterations``, plus the last."""
    its = np.unique(np.asarray(iterations))
    if len(its) <= max_points:
        return its
    keep = np.unique(np.r_[np.linspace(0, len(its) - 1, max_points).round().astype(int), len(its) - 1])
    return its[keep]


def seed_curves(train: pd.DataFrame, overall: pd.DataFrame, opts: ReportOptions,
                errors: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per-run curves ``arm, run_dir, seed, metric, iteration, value`` for every CURVE_METRICS entry
    (training metrics at most ``max_curve_points`` iterations): the thin lines of the figures."""
    frames = []
    sources = {"train_metrics": train, "eval": overall.rename(columns={FAILURE_RATE: "eval_failure_rate"}),
               "errors": (errors if errors is not None else pd.DataFrame()).rename(
                   columns={MPKPE_REL_MM: summary_key(MPKPE_REL_MM)})}
    for metric, (source, _) in CURVE_METRICS.items():
        df = sources[source]
        if not len(df) or metric not in df:
            continue
        if source == "train_metrics":
            df = df[df[ITERATION].isin(thin_iterations(df[ITERATION], opts.max_curve_points))]
        frames.append(df[["arm", "run_dir", "seed", ITERATION, metric]].rename(columns={metric: "value"})
                      .assign(metric=metric).dropna(subset=["value"]))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def learning_curves(per_seed: pd.DataFrame, runs: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """``arm, metric, iteration, n_seeds, point, point_label, mean, iqm, ci_low, ci_high, ci_method`` over
    the seeds of ``per_seed`` (seed_curves)."""
    boot = use_bootstrap(runs)
    frames = []
    for (metric, arm), g in (per_seed.groupby(["metric", "arm"], sort=True) if len(per_seed) else ()):
        wide = g.pivot_table(index="run_dir", columns=ITERATION, values="value", aggfunc="mean")
        m = wide.to_numpy(dtype=float)
        p, low, high, method = curve_intervals(m, boot, opts.n_resamples, opts.confidence, opts.bootstrap_seed)
        n = (~np.isnan(m)).sum(axis=0)
        with np.errstate(all="ignore"):
            mean = np.nanmean(m, axis=0)
        q = np.where(n >= MIN_SEEDS_IQM, iqm(m, axis=0), np.nan)
        frames.append(pd.DataFrame({
            "arm": arm, "metric": metric, ITERATION: wide.columns.to_numpy(), "n_seeds": n, "point": p,
            "point_label": np.where(n >= MIN_SEEDS_IQM, "iqm", "mean"), "mean": mean, "iqm": q,
            "ci_low": low, "ci_high": high, "ci_method": method,
        }))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def budgets(runs: pd.DataFrame, train: pd.DataFrame) -> pd.DataFrame:
    """Per included run: completed ``iterations``, ``env_steps`` and ``wall_time_s`` (training's last row)."""
    if not len(train):
        return pd.DataFrame(columns=["run_dir", "arm", "seed", "iterations", ENV_STEPS, WALL_TIME_S])
    last = train.sort_values(ITERATION).groupby("run_dir").tail(1)
    out = last[["run_dir", "arm", "seed"]].copy()
    out["iterations"] = last[ITERATION].to_numpy() + 1  # rows are numbered from iteration 0
    out[ENV_STEPS] = last[ENV_STEPS].to_numpy()
    out[WALL_TIME_S] = last[WALL_TIME_S].to_numpy()
    return out.sort_values(["arm", "seed"]).reset_index(drop=True)


def budget_warning(budget: pd.DataFrame, opts: ReportOptions) -> str | None:
    """A sentence when the runs completed iteration counts that differ by more than the tolerance."""
    if len(budget) < 2:
        return None
    lo, hi = budget["iterations"].min(), budget["iterations"].max()
    if hi <= 0 or (hi - lo) / hi <= opts.budget_tolerance:
        return None
    per_arm = budget.groupby("arm")["iterations"].agg(["min", "max"])
    detail = "; ".join(f"`{a}` {int(r['min'])}" + (f"-{int(r['max'])}" if r["max"] != r["min"] else "")
                       for a, r in per_arm.iterrows())
    return (f"**Warning: unequal budgets.** The runs completed {int(lo)}-{int(hi)} iterations "
            f"({(hi - lo) / hi:.0%} apart; {detail}). Final numbers are compared at the last evaluation every "
            "run has; time-to-threshold of the shorter runs is censored earlier. Runs stopped by wall time "
            "(`time_limit_s`) while sharing a GPU get unequal work: compare arms with `max_iterations`.")


def common_budget(overall: pd.DataFrame) -> dict[str, float]:
    """Per measure, the largest value every run's evaluations reach (the equal-budget comparison point)."""
    return {m: float(overall.groupby("run_dir")[m].max().min()) for m in ("iteration", ENV_STEPS)}


def final_overall(overall: pd.DataFrame, measure: str = "iteration") -> pd.DataFrame:
    """Each run's evaluation at the common budget in ``measure`` (metrics.at_budget)."""
    return at_budget(overall, measure, common_budget(overall)[measure])


def per_seed_text(values: pd.Series) -> str:
    """Per-seed values as the `per_seed` column writes them: `;`-separated, 6 significant digits."""
    return ";".join(f"{float(v):.6g}" for v in values)


def seeds_text(seeds: pd.Series) -> str:
    """The seeds of a `per_seed` column, in its order, as a `seeds` column writes them: `;`-separated."""
    return ";".join(str(int(s)) for s in seeds)


def count_per_seed(seeds: pd.Series, per_seed: pd.Series, hit: Callable[[float], bool]) -> dict[int, int]:
    """Per seed: how many rows (clips) have a value for which ``hit(value)`` holds, from the ``seeds`` and
    ``per_seed`` columns (seeds_text, per_seed_text) of a table with one row per clip; seeds in order."""
    counts: dict[int, int] = {}
    for ss, vs in zip(seeds, per_seed, strict=True):
        for s, v in zip(str(ss).split(";"), str(vs).split(";"), strict=True):
            if s != "":
                counts[int(s)] = counts.get(int(s), 0) + bool(hit(float(v)))
    return dict(sorted(counts.items()))


def summary_rows(arm: str, metric: str, per_run: pd.DataFrame, value: str, boot: bool, opts: ReportOptions) -> dict:
    """One summary.csv row from a frame with one row per run (``seed`` and ``value``)."""
    per_run = per_run.sort_values("seed")
    v = per_run[value].to_numpy(dtype=float)
    v = v[~np.isnan(v)]
    _, low, high, method = seed_interval(v, boot, opts.n_resamples, opts.confidence, opts.bootstrap_seed)
    return {
        "arm": arm, "n_seeds": len(v), "metric": metric,
        "mean": float(np.mean(v)) if len(v) else math.nan,
        "iqm": iqm(v) if len(v) >= MIN_SEEDS_IQM else math.nan,
        "ci_low": low, "ci_high": high, "ci_method": method, "per_seed": per_seed_text(v),
    }


def per_run_metrics(runs, overall, robust_overall, mastery_seeds, budget, errors=None,
                    broken=None) -> dict[str, pd.DataFrame]:
    """metric -> one row per run (``run_dir, arm, seed, value``): the per-seed numbers summary.csv is over.

    - ``final_failure``: overall failure at the last evaluation iteration every run has;
    - ``final_failure_equal_env_steps``: the same at equal env steps (only when runs differ in env
      steps per iteration);
    - ``final_failure_robust``: the last robust evaluation (eval_robust.parquet), where present;
    - ``bins_mastered``: bins the run mastered (persistent, counts_as_mastered);
    - ``iterations``, ``env_steps``, ``wall_time_s``: what the run completed;
    - ``final_<column>`` for each metrics.ERROR_METRICS and metrics.SMOOTHNESS_METRICS column of
      ``errors`` (metrics.tracking_errors): the step-weighted value at the same evaluation as
      ``final_failure``, for the runs that recorded it;
    - ``broken_episodes``: episodes whose world broke, summed over every evaluation of the run
      (``broken``: metrics.broken_episodes), for the runs that recorded it.
    """
    out = {}
    keep = ["run_dir", "arm", "seed"]
    if len(overall):
        f = final_overall(overall, "iteration")
        out["final_failure"] = f[keep].assign(value=f[FAILURE_RATE].to_numpy())
        steps_per_it = overall[overall[ITERATION] > 0].eval("env_steps / iteration").round(6)
        if steps_per_it.nunique() > 1:
            f = final_overall(overall, ENV_STEPS)
            out["final_failure_equal_env_steps"] = f[keep].assign(value=f[FAILURE_RATE].to_numpy())
    if robust_overall is not None and len(robust_overall):
        f = robust_overall.sort_values(ITERATION).groupby("run_dir").tail(1)
        out["final_failure_robust"] = f[keep].assign(value=f[FAILURE_RATE].to_numpy())
    if len(mastery_seeds):
        m = mastery_seeds.groupby(keep, dropna=False)["mastered"].sum().reset_index()
        out["bins_mastered"] = m[keep].assign(value=m["mastered"].astype(float).to_numpy())
    if errors is not None and len(errors) and len(overall):
        f = at_budget(errors, "iteration", common_budget(overall)[ITERATION])
        for col in (*ERROR_METRICS, *SMOOTHNESS_METRICS):
            if col in f and f[col].notna().any():
                out[f"final_{col}"] = f[keep].assign(value=f[col].to_numpy(dtype=float)).dropna(subset=["value"])
    if broken is not None and len(broken):
        out["broken_episodes"] = broken[keep].assign(value=broken["broken"].astype(float).to_numpy())
    for col in ("iterations", ENV_STEPS, WALL_TIME_S):
        if len(budget):
            out[col] = budget[keep].assign(value=budget[col].astype(float).to_numpy())
    return out


def summary(per_run: dict[str, pd.DataFrame], runs: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    """summary.csv: SUMMARY_COLUMNS, one row per arm and metric of ``per_run``."""
    boot = use_bootstrap(runs)
    rows = []
    for metric, df in per_run.items():
        for arm, g in df.groupby("arm", sort=True):
            rows.append(summary_rows(arm, metric, g, "value", boot, opts))
    return pd.DataFrame(rows, columns=SUMMARY_COLUMNS)


def arm_overview(summary_df: pd.DataFrame, time_df: pd.DataFrame) -> pd.DataFrame:
    """One row per arm, wide: ``<metric>`` point, ``<metric>_low``/``_high``, ``<metric>_method`` for every
    summary metric, and ``time_<measure>`` (Kaplan-Meier median) with ``n_reached``."""
    rows: dict[str, dict] = {}
    for r in summary_df.itertuples(index=False):
        row = rows.setdefault(r.arm, {"arm": r.arm, "n_seeds": r.n_seeds})
        row[r.metric] = r.iqm if not (isinstance(r.iqm, float) and math.isnan(r.iqm)) else r.mean
        row[f"{r.metric}_low"], row[f"{r.metric}_high"], row[f"{r.metric}_method"] = r.ci_low, r.ci_high, r.ci_method
    for r in time_df.itertuples(index=False):
        row = rows.setdefault(r.arm, {"arm": r.arm, "n_seeds": r.n_seeds})
        row[f"time_{r.measure}"] = r.median
        row["n_reached"] = r.n_reached
    return pd.DataFrame(list(rows.values()))


def swept_keys(runs: pd.DataFrame) -> list[str]:
    """Override keys with numeric values that take at least two values across included arms."""
    inc = runs[runs["included"]].drop_duplicates("arm")
    keys = []
    for col in (c for c in runs.columns if c.startswith("param.")):
        values = inc[col].dropna()
        numeric = values.map(lambda v: isinstance(v, int | float | np.number) and not isinstance(v, bool))
        if len(values) and numeric.all() and values.nunique() > 1:
            keys.append(col.removeprefix("param."))
    return keys


def _explicit_keys(overrides: str) -> set[str]:
    return {item.split("=", 1)[0].lstrip("+") for item in str(overrides).split(",") if "=" in item}


SENSITIVITY_METRICS = {
    "final_failure": ("final_failure", "final_failure_low", "final_failure_high"),
    "bins_mastered": ("bins_mastered", "bins_mastered_low", "bins_mastered_high"),
    "time_iteration": ("time_iteration", None, None),
}
"""Sensitivity metric -> (point, low, high) columns of arm_overview (no interval for censored medians)."""


def sensitivity(runs: pd.DataFrame, overview: pd.DataFrame) -> pd.DataFrame:
    """Final failure, bins mastered and iterations to threshold against each swept key.

    For key ``k`` the arms compared are those whose sampler is one that some arm sets ``k`` for
    explicitly (a uniform arm also carries an unused ``gamma`` default, which must not become a
    point); ``series`` names the arm's other overrides, so a grid over two keys gives one line per
    value of the other. Returns ``key, value, series, arm, metric, point, ci_low, ci_high``.
    """
    arms = runs[runs["included"]].drop_duplicates("arm").set_index("arm")
    s = overview.set_index("arm")
    rows = []
    for key in swept_keys(runs):
        setters = {a for a in arms.index if key in _explicit_keys(arms.loc[a, "overrides"])}
        samplers = set(arms.loc[sorted(setters), "sampler"])
        for arm in sorted(a for a in arms.index if arms.loc[a, "sampler"] in samplers):
            value = arms.loc[arm, f"param.{key}"]
            if pd.isna(value) or arm not in s.index:
                continue
            others = [i for i in str(arms.loc[arm, "overrides"]).split(",") if i.split("=", 1)[0] != key]
            series = ",".join(others)
            for metric, (col, lo, hi) in SENSITIVITY_METRICS.items():
                if col not in s.columns:
                    continue
                p = s.loc[arm, col]
                rows.append((key, float(value), series, arm, metric, p,
                             s.loc[arm, lo] if lo and lo in s.columns else p, s.loc[arm, hi] if hi and hi in s.columns else p))
    return pd.DataFrame(rows, columns=["key", "value", "series", "arm", "metric", "point", "ci_low", "ci_high"])


def overall(eval_df: pd.DataFrame) -> pd.DataFrame:
    """metrics.overall_failure of every run."""
    return overall_failure(eval_df, by=["run_dir", "arm", "seed"])
