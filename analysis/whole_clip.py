"""Whole-clip evaluations in a report (the runs' whole_clip tables, eval.whole_clip): success against
iterations per arm and condition, each run's survival curve at its last whole-clip evaluation, and the
final numbers with start transients apart from later failures, and where in the clips the rollouts
fail. `compute` returns None when no run has the tables, and the report then says nothing about whole
clips."""

from __future__ import annotations

import operator
from dataclasses import dataclass
from functools import partial

import numpy as np
import pandas as pd

from analysis.load import load_table
from analysis.markdown import fmt, md_table, row_cell
from analysis.tables import (
    ReportOptions,
    count_per_seed,
    learning_curves,
    per_seed_text,
    seeds_text,
    summary_rows,
    use_bootstrap,
)
from bmimic.runs.schema import (
    CLIP_TIME_S,
    CONDITION,
    ITERATION,
    MPKPE_REL_MM,
    START_TRANSIENT_S,
    whole_clip_survival,
)

COUNTS = ["rollouts", "completed", "transient_failures", "later_failures"]
KAPLAN_MEIER_NOTE = (" The clips differ in length, so the survival figure pools them as a Kaplan-Meier curve: a "
                     "rollout that reaches its clip's last frame leaves those at risk there without failing.")
FAILURE_PLACES = 3
"""The clip seconds listed per arm and condition in "where they fail" (the most failures first)."""
TRACKED_S = "tracked_s"
"""Seconds of clip a rollout tracked before it failed (its clip's duration when it completed), mean over the
rollouts of an evaluation: the area under its survival curve, which tells apart policies that all fail."""


@dataclass
class WholeClipReport:
    """The report's whole-clip tables."""

    per_seed: pd.DataFrame
    """``arm, run_dir, seed, metric`` (the condition), ``iteration, value`` (success over every clip's rollouts)."""
    curves: pd.DataFrame
    """tables.learning_curves of ``per_seed``: the point over seeds with its band, per condition."""
    final: pd.DataFrame
    """Per arm and condition at each run's last whole-clip evaluation: success over seeds, failures per seed."""
    survival: pd.DataFrame
    """``arm, condition, time_s, n_seeds, tracking_frac, low, high``: the clips' rollouts still tracking at
    each second of each run's last whole-clip evaluation (clips pooled), mean and range over seeds."""
    places: pd.DataFrame
    """``arm, condition, clip_name, second, failures, share, arm_failures``: at each run's last whole-clip
    evaluation, the failed rollouts of the arm's seeds pooled and counted per whole second of clip time
    (``second`` s to ``second + 1`` s), ``share`` of the arm's failures in that condition; the
    FAILURE_PLACES largest per arm and condition (empty without failures tables). Seconds, not bins: arms
    of other bin sizes fail at comparable places."""
    survival_kaplan_meier: bool = False
    """Whether `survival` pooled clips of different lengths as Kaplan-Meier curves (pooled_survival)."""
    per_clip: pd.DataFrame | None = None
    """Libraries only (None for one clip): per_clip_rows, each clip's success per arm and condition."""


def _per_run(clips: pd.DataFrame, failures: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per run, condition and evaluation: the clips' counts summed, success = completed / rollouts, the
    root-relative MPKPE over the completed rollouts (weighted by completed rollouts x clip duration) and,
    with the failures table, the seconds of clip tracked per rollout (TRACKED_S)."""
    clips = clips.assign(_w=clips["completed"] * clips["clip_duration_s"])
    has_error = MPKPE_REL_MM in clips
    if has_error:
        clips = clips.assign(_e=clips[MPKPE_REL_MM].fillna(0.0) * clips["_w"])
    keys = ["arm", "run_dir", "seed", CONDITION, ITERATION]
    out = clips.groupby(keys, sort=True)[[*COUNTS, "_w", *(["_e"] if has_error else [])]].sum().reset_index()
    out["success"] = out["completed"] / out["rollouts"].where(out["rollouts"] > 0)
    out[MPKPE_REL_MM] = out["_e"] / out["_w"].where(out["_w"] > 0) if has_error else np.nan
    out[TRACKED_S] = np.nan
    if failures is not None and len(failures):
        # seconds tracked per rollout: a completed rollout tracked its clip's duration (_w), a failed one up to
        # its failure; only where the failures table accounts for every failed rollout of the evaluation
        failed = failures.groupby(["run_dir", CONDITION, ITERATION])["failure_time_s"].agg(["sum", "count"])
        key = pd.MultiIndex.from_frame(out[["run_dir", CONDITION, ITERATION]])
        fail_s, n = failed["sum"].reindex(key).to_numpy(), failed["count"].reindex(key).fillna(0).to_numpy()
        known = n == (out["rollouts"] - out["completed"]).to_numpy()
        tracked = (np.nan_to_num(fail_s) + out["_w"].to_numpy()) / out["rollouts"].where(out["rollouts"] > 0).to_numpy()
        out[TRACKED_S] = np.where(known, tracked, np.nan)
    return out.drop(columns=[c for c in ("_w", "_e") if c in out])


def _final_rows(last: pd.DataFrame, runs: pd.DataFrame, opts: ReportOptions) -> pd.DataFrame:
    boot = use_bootstrap(runs)
    rows = []
    for (arm, condition), g in last.groupby(["arm", CONDITION], sort=True):
        row = summary_rows(arm, "whole_clip_success", g.assign(value=g["success"]), "value", boot, opts)
        row.update({CONDITION: condition, "iterations": ";".join(str(int(i)) for i in g.sort_values("seed")[ITERATION]),
                    "rollouts_per_seed": float(g["rollouts"].mean()),
                    "transient_failures_per_seed": float(g["transient_failures"].mean()),
                    "later_failures_per_seed": float(g["later_failures"].mean()),
                    MPKPE_REL_MM: float(g[MPKPE_REL_MM].mean())})
        tracked = summary_rows(arm, TRACKED_S, g.assign(value=g[TRACKED_S]), "value", boot, opts)
        row.update({f"{TRACKED_S}_{k}": tracked[k] for k in ("mean", "iqm", "ci_low", "ci_high", "ci_method",
                                                             "n_seeds", "per_seed")})
        rows.append(row)
    return pd.DataFrame(rows)


def failure_places(failures: pd.DataFrame, last: pd.DataFrame, top: int = FAILURE_PLACES) -> pd.DataFrame:
    """WholeClipReport.places from the failures table and each run's last evaluation (``run_dir,
    condition, iteration``)."""
    columns = ["arm", CONDITION, "clip_name", "second", "failures", "share", "arm_failures"]
    if failures is None or not len(failures):
        return pd.DataFrame(columns=columns)
    f = failures.merge(last[["run_dir", CONDITION, ITERATION]].drop_duplicates(), on=["run_dir", CONDITION, ITERATION])
    if not len(f):
        return pd.DataFrame(columns=columns)
    f = f.assign(second=np.floor(f["failure_time_s"].to_numpy(float)).astype(int),
                 clip_name=f["clip_name"] if "clip_name" in f else f["clip"].astype(str))
    counts = f.groupby(["arm", CONDITION, "clip_name", "second"], sort=True).size().rename("failures").reset_index()
    counts["arm_failures"] = counts.groupby(["arm", CONDITION])["failures"].transform("sum")
    counts["share"] = counts["failures"] / counts["arm_failures"]
    counts = counts.sort_values(["arm", CONDITION, "failures", "clip_name", "second"],
                                ascending=[True, True, False, True, True], kind="stable")
    return counts.groupby(["arm", CONDITION], sort=False).head(top)[columns].reset_index(drop=True)


def compute(runs: pd.DataFrame, opts: ReportOptions) -> WholeClipReport | None:
    """The whole-clip tables of `runs` (None when no included run has whole_clip.parquet)."""
    clips = load_table(runs, "whole_clip", opts.max_iteration)
    if not len(clips):
        return None
    failures = load_table(runs, "whole_clip_failures", opts.max_iteration)
    per_run = _per_run(clips, failures)
    per_seed = per_run[["arm", "run_dir", "seed", CONDITION, ITERATION, "success"]].rename(
        columns={CONDITION: "metric", "success": "value"})
    last_it = per_run.groupby(["run_dir", CONDITION])[ITERATION].transform("max")
    last = per_run[per_run[ITERATION] == last_it]
    # the survival curves are a view of the clips and failures tables (one rule: runs.schema), not read from disk
    at_last = last[["run_dir", CONDITION, ITERATION]]
    survival = whole_clip_survival(clips.merge(at_last, on=["run_dir", CONDITION, ITERATION]),
                                   failures.merge(at_last, on=["run_dir", CONDITION, ITERATION]),
                                   keys=("arm", "run_dir", ITERATION))
    kaplan_meier = False
    if len(survival):
        pooled = pooled_survival(survival)
        kaplan_meier = bool(pooled["kaplan_meier"].any())
        survival = pooled.groupby(["arm", CONDITION, CLIP_TIME_S], sort=True)["frac"].agg(
            n_seeds="count", tracking_frac="mean", low="min", high="max").reset_index()
    return WholeClipReport(per_seed, learning_curves(per_seed, runs, opts), _final_rows(last, runs, opts), survival,
                           failure_places(failures, last), kaplan_meier, per_clip_rows(clips, last))


CLIP_SUCCESS_LINES = (0.9, 0.95)
"""Whole-clip success a library's clips are counted at (the library issue's targets: robust >= 0.90)."""


def per_clip_rows(clips: pd.DataFrame, last: pd.DataFrame) -> pd.DataFrame | None:
    """``arm, condition, clip, clip_name, n_seeds, success, low, high, seeds, per_seed, rollouts, mpkpe_rel_mm``:
    each clip's whole-clip success at each run's last whole-clip evaluation (the mean over seeds, their range,
    and each seed's in ``per_seed``, in the order of ``seeds``), its rollouts (fewest over seeds), and the
    root-relative MPKPE of its completed rollouts (mean over seeds that completed any); None for one clip."""
    if clips["clip"].nunique() < 2:
        return None
    c = clips.merge(last[["run_dir", CONDITION, ITERATION]], on=["run_dir", CONDITION, ITERATION])
    c = c.assign(success=c["completed"] / c["rollouts"].where(c["rollouts"] > 0),
                 clip_name=c["clip_name"] if "clip_name" in c else c["clip"].astype(str))
    if MPKPE_REL_MM not in c:
        c[MPKPE_REL_MM] = np.nan
    out = c.sort_values("seed", kind="stable").groupby(["arm", CONDITION, "clip", "clip_name"], sort=True).agg(
        n_seeds=("success", "count"), success=("success", "mean"), low=("success", "min"), high=("success", "max"),
        seeds=("seed", seeds_text), per_seed=("success", per_seed_text),
        rollouts=("rollouts", "min"), **{MPKPE_REL_MM: (MPKPE_REL_MM, "mean")})
    return out.reset_index()


def per_clip_resolution(per_clip: pd.DataFrame) -> str:
    """How finely one evaluation resolves a clip's success, per condition: R rollouts of a clip are R
    Bernoulli draws, so a success p read from them has the binomial standard error sqrt(p (1 - p) / R),
    largest at p = 0.5 (0.5 / sqrt(R)); a deterministic condition has one rollout per clip, 0 or 1."""
    parts = []
    for condition, g in per_clip.groupby(CONDITION, sort=True):
        r = int(g["rollouts"].min())
        parts.append(f"{condition}: one rollout per clip (0 or 1)" if r <= 1 else
                     f"{condition}: {r} rollouts per clip, a binomial standard error of up to {fmt(0.5 / np.sqrt(r))} "
                     f"(at success 0.5)")
    return ("One evaluation's resolution per clip (seed by seed, before any spread over seeds): "
            + "; ".join(parts) + ".")


def _counts_by_seed(g: pd.DataFrame) -> list[tuple[int, ...]]:
    """``(seed, clips at each of CLIP_SUCCESS_LINES)`` for every seed of one arm and condition's per-clip rows."""
    per_line = [count_per_seed(g["seeds"], g["per_seed"], partial(operator.le, line)) for line in CLIP_SUCCESS_LINES]
    return [(s, *(counts[s] for counts in per_line)) for s in per_line[0]]


def _per_clip_section(per_clip: pd.DataFrame) -> list[str]:
    """The per-clip table of a library and how many of its clips reach each of CLIP_SUCCESS_LINES."""
    view = per_clip.assign(cell=[f"{fmt(r['success'])} ({fmt(r['low'])}–{fmt(r['high'])})" if r["n_seeds"] > 1
                                 else f"{fmt(r['success'])} (1 seed)" for r in per_clip.to_dict("records")])
    table = view.pivot_table(index=["clip", "clip_name"], columns=["arm", CONDITION], values="cell", aggfunc="first")
    table.columns = [f"{arm}, {condition}" for arm, condition in table.columns]
    table = table.reset_index(level="clip", drop=True).rename_axis("clip").reset_index()
    md = ["Per clip: whole-clip success at each run's last whole-clip evaluation (mean over seeds; brackets: "
          "range of the seeds).", "", md_table(table), "", per_clip_resolution(per_clip), ""]
    n_clips = per_clip["clip"].nunique()
    for (arm, condition), g in per_clip.groupby(["arm", CONDITION], sort=True):
        counts = ", ".join(f">= {line:g}: {int((g['success'] >= line).sum())}" for line in CLIP_SUCCESS_LINES)
        per_seed = ""
        if int(g["n_seeds"].max()) > 1:  # the mean's count, then what each seed's policy does on its own
            per_seed = " by the mean over seeds (per seed: " + "; ".join(
                f"seed {s} " + ", ".join(f">= {line:g}: {n}" for line, n in zip(CLIP_SUCCESS_LINES, ns, strict=True))
                for s, *ns in _counts_by_seed(g)) + ")"
        md.append(f"- `{arm}`, {condition}: clips at whole-clip success {counts} of {n_clips}{per_seed}; root-relative MPKPE "
                  f"of completed rollouts {fmt(g[MPKPE_REL_MM].min())}–{fmt(g[MPKPE_REL_MM].max())} mm over the "
                  f"clips with any.")
    return md + [""]


def pooled_survival(survival: pd.DataFrame) -> pd.DataFrame:
    """``arm, run_dir, condition, time_s, frac, kaplan_meier``: the rollouts of every clip still tracking at
    each time, and whether they pooled as a Kaplan-Meier curve.

    Clips of one length (a single clip, or a library's equal ones) pool as the tracking count over the
    rollouts. Clips of different lengths pool as a Kaplan-Meier curve: a rollout that reaches its clip's
    last frame leaves those at risk there, uncounted as a failure, so the curve falls only where rollouts
    fail; the plain fraction would drop to the failures of the few clips still running and jump as clips
    end. A clip's failures between two of its times count at the later one, its rollouts at risk there being
    its count at the earlier one (other clips' times may lie between)."""
    keys = ["arm", "run_dir", CONDITION]
    out = []
    for key, df in survival.groupby(keys, sort=True):
        ends = df.groupby("clip")[CLIP_TIME_S].max()
        if ends.nunique() == 1:
            per_t = df.groupby(CLIP_TIME_S, sort=True)[["tracking", "rollouts"]].sum()
            frac = per_t["tracking"] / per_t["rollouts"]
        else:
            tracking = df.pivot_table(index=CLIP_TIME_S, columns="clip", values="tracking", aggfunc="sum").sort_index()
            rollouts = df.groupby("clip")["rollouts"].max()
            # at risk at t: each clip's count at its last time before t, while t is within the clip
            at_risk = tracking.ffill().shift(1).fillna(rollouts).where(tracking.index.to_numpy()[:, None] <= ends.to_numpy())
            failed = (at_risk - tracking).where(tracking.notna(), 0.0)
            n, d = at_risk.sum(axis=1), failed.sum(axis=1)
            frac = (1.0 - (d / n).where(n > 0, 0.0)).cumprod()
        out.append(pd.DataFrame({**dict(zip(keys, key, strict=True)), CLIP_TIME_S: frac.index, "frac": frac.to_numpy(),
                                 "kaplan_meier": ends.nunique() > 1}))
    return pd.concat(out, ignore_index=True)


def section(w: WholeClipReport) -> list[str]:
    """The report's "Whole clips" section."""
    f = w.final
    view = pd.DataFrame({
        "arm": f["arm"], "condition": f[CONDITION], "last whole-clip evaluation (iteration per seed)": f["iterations"],
        "whole-clip success": [row_cell(r) for r in f.to_dict("records")],
        "rollouts per seed": f["rollouts_per_seed"].map(fmt),
        f"start transients (< {START_TRANSIENT_S:g} s) per seed": f["transient_failures_per_seed"].map(fmt),
        "later failures per seed": f["later_failures_per_seed"].map(fmt),
        "seconds tracked per rollout": [row_cell(r, f"{TRACKED_S}_") for r in f.to_dict("records")],
        "root-relative MPKPE of completed rollouts (mm)": f[MPKPE_REL_MM].map(fmt),
    })
    return ["## Whole clips", "", "Rollouts from each clip's first frame to its last (eval.whole_clip): `nominal` "
            "as the window evaluation (deterministic, one per clip), `robust` with training's domain randomisation, "
            "observation noise and pushes (each rollout its own draw). Success: rollouts that tracked their clip to "
            "its last frame / rollouts, over every clip; at each run's last whole-clip evaluation. Failures within "
            f"{START_TRANSIENT_S:g} s of the start are start transients; the others are later failures. Seconds "
            "tracked per rollout: the clip time a rollout tracked before it failed (its clip's length when it "
            "completed), mean over rollouts: the area under the survival curve, which separates policies that "
            "all fail somewhere." + (KAPLAN_MEIER_NOTE if w.survival_kaplan_meier else ""), "", md_table(view), ""] + (
            _per_clip_section(w.per_clip) if w.per_clip is not None else []) + _places_section(w.places)


def _places_section(places: pd.DataFrame) -> list[str]:
    if not len(places):
        return []
    several = places["clip_name"].nunique() > 1
    rows = []
    for (arm, condition), g in places.groupby(["arm", CONDITION], sort=True):
        cells = [f"{f'{c} ' if several else ''}{s}–{s + 1} s ({100 * share:.0f}%)"
                 for c, s, share in zip(g["clip_name"], g["second"], g["share"], strict=True)]
        rows.append({"arm": arm, "condition": condition, "failed rollouts (seeds pooled)": int(g["arm_failures"].iloc[0]),
                     "where most failed (share of the failures)": ", ".join(cells)})
    return ["Where they fail: the seconds of clip time holding the most failures at each run's last whole-clip "
            f"evaluation, seeds pooled (up to {FAILURE_PLACES} per arm and condition).", "",
            md_table(pd.DataFrame(rows)), ""]


__all__ = ["WholeClipReport", "compute", "section"]
