"""The printed report of one evaluation: per segment, per bin (the worst ones for long motions), overall."""

from __future__ import annotations

import math

import pandas as pd

from bmimic.evaluation.tables import EvalResult
from bmimic.runs.schema import BIN, HORIZON_TRUNCATED, ITERATION, MPKPE_MM, TRACKING_ERRORS

_SHOWN = {
    "visits": ("visits", "{:d}"),
    "failures": ("failures", "{:d}"),
    "success_rate": ("success", "{:.3f}"),
    **{c.name: (c.title or c.name, "{:.1f}" if c.unit == "mm" else "{:.2f}" if c.unit == "rad/s" else "{:.3f}")
       for c in TRACKING_ERRORS},
}
MAX_BINS_SHOWN = 30


def _format_rows(df: pd.DataFrame, label_cols: dict[str, str], titles: dict[str, str] | None = None) -> str:
    shown = pd.DataFrame({title: df[col].astype(str) for col, title in label_cols.items()})
    for col, (title, fmt) in _SHOWN.items():
        title = (titles or {}).get(col, title)
        shown[title] = [fmt.format(int(v) if fmt == "{:d}" else float(v)) for v in df[col]]
    return shown.to_string(index=False)


def format_report(result: EvalResult) -> str:
    """A readable summary: per segment, per bin (the worst ones for long motions), overall."""
    s = result.summary
    lines = [
        f"{s['checkpoint']} (iteration {s[ITERATION]}), {s['device']}: {s['num_bins']} bins x "
        f"{s['episodes_per_bin']} episodes, horizon {s['horizon_s']:g} s, deterministic policy",
        "",
    ]
    if s.get("trained_on_motion") is False:
        clips = s.get("motion_clips") or []
        lines[-1:-1] = [f"motion {s.get('motion')}{f' ({len(clips)} clips)' if len(clips) > 1 else ''}: not the "
                        "motion this policy was trained on (generalisation)"]
    seg = result.segments.assign(
        segment=[n or "(none)" for n in result.segments["segment"]],
        span=[f"{a:.1f}-{b:.1f}" if math.isfinite(a) else "" for a, b in zip(result.segments["start_s"],
                                                                             result.segments["end_s"])],
    )
    lines += ["per segment:", _format_rows(seg, {"segment": "segment", "difficulty": "difficulty", "span": "t_s"}), ""]
    bins = result.bins.assign(span=[f"{a:.1f}-{b:.1f}" + ("*" if t else "") for a, b, t in zip(
        result.bins["bin_start_s"], result.bins["bin_end_s"], result.bins[HORIZON_TRUNCATED])])
    title = "per bin:"
    if len(bins) > MAX_BINS_SHOWN:
        bins = bins.sort_values(["success_rate", MPKPE_MM], ascending=[True, False]).head(MAX_BINS_SHOWN // 3)
        title = f"worst {len(bins)} of {len(result.bins)} bins:"
    lines += [title, _format_rows(bins, {BIN: "bin", "span": "t_s", "segment": "segment"}), ""]
    overall = pd.DataFrame([{"visits": s["episodes"], "failures": s["failures"], "success_rate": s["eval_success_rate"],
                             **{c: s[f"eval_{c}"] for c in _SHOWN if f"eval_{c}" in s}}])
    lines += ["overall:", _format_rows(overall, {}, titles={"visits": "episodes"}),
              f"bins mastered (failure rate < 0.1; a horizon-truncated bin only when tracked through): "
              f"{s['eval_bins_mastered_frac']:.2f}",
              "failures are charged to the bin (segment) where they happened, per visit; "
              "* = horizon-truncated (its episodes reach the clip end before the horizon)",
              "(bmimic-report's Segments table counts otherwise, failed / started episodes by the segment an episode "
              "started in, and reads training's evaluations: its segment figures differ from these)"]
    if result.out_dir is not None:
        lines.append(f"tables: {result.out_dir}")
    return "\n".join(lines)


