"""The whole-clip evaluation of a saved policy (`python -m bmimic.eval --whole-clip`): its tables, summary
and printed report. The rollouts are bmimic.training.whole_clip's, built through bmimic.task."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import pandas as pd

from bmimic.evaluation.saved_run import LoadedRun, evaluation_record, load_run_checkpoint
from bmimic.runs.folder import WHOLE_CLIP_FILES
from bmimic.runs.record import write_whole_clip
from bmimic.runs.schema import (
    BIN,
    CONDITION,
    ITERATION,
    MPKPE_MM,
    MPKPE_REL_MM,
    START_TRANSIENT_S,
    WHOLE_CLIP_SUCCESS,
    whole_clip_key,
)

log = logging.getLogger("bmimic.eval")


@dataclass
class WholeClipEval:
    """What `evaluate_whole_clip` produced, and where it was written."""

    clips: pd.DataFrame
    survival: pd.DataFrame
    failures: pd.DataFrame
    summary: dict
    """whole_clip_<condition>_* numbers and provenance (whole_clip_summary.json)."""
    out_dir: Path | None = None


def evaluate_whole_clip(run: LoadedRun, overrides: Sequence[str] = ()) -> WholeClipEval:
    """Whole-clip rollouts of `run.checkpoint` under eval.whole_clip's conditions (bmimic.training.whole_clip)."""
    import time

    from bmimic.runtime import seed_everything
    from bmimic.task import build_whole_clip
    from bmimic.training.clip_rollouts import clip_bounds
    from bmimic.training.policy import build_policy

    task = run.task
    cfg, device, layout = task.cfg, task.device, task.layout
    whole = build_whole_clip(task)  # refuses a clip it cannot hold, before the checkpoint is read
    state = load_run_checkpoint(run)
    seed_everything(cfg.seed)
    iteration = int(state.get("iter", -1))
    try:
        policy = build_policy(state, whole.evaluator(whole.conditions[0]).env, cfg.ppo, device, run.checkpoint)
        log.info("whole clips of %s (iteration %d) on %s: %d clip(s) of up to %d steps, conditions %s, %d rollouts "
                 "per clip when perturbed", run.checkpoint, iteration, device, len(clip_bounds(layout)[0]),
                 whole.steps(), ",".join(whole.conditions), whole.rollouts)
        t0 = time.perf_counter()
        result = whole.evaluate(policy)
        wall = time.perf_counter() - t0
    finally:
        whole.close()
    summary = {
        **result.summary,
        "conditions": list(whole.conditions),
        "rollouts_per_clip": {c: whole.per_clip(c) for c in whole.conditions},
        "start_transient_s": START_TRANSIENT_S,
        "max_mpkpe_rel_mm": cfg.eval.max_mpkpe_rel_mm,
        "eval_wall_time_s": wall,
        "clips": int(len(result.clips) // max(len(whole.conditions), 1)),
        **evaluation_record(run, state, overrides),
    }
    return WholeClipEval(result.clips, result.survival, result.failures, summary)


def write_whole_clip_tables(result: WholeClipEval, out_dir: Path) -> Path:
    """Write runs.folder.WHOLE_CLIP_FILES through the run record (atomically, the summary last)."""
    if (out_dir / WHOLE_CLIP_FILES[-1]).exists():
        log.warning("replacing the earlier whole-clip evaluation in %s", out_dir)
    result.out_dir = write_whole_clip(out_dir, result.clips, result.survival, result.failures, result.summary)
    return result.out_dir


def _bins_text(failures: pd.DataFrame) -> str:
    """`bin 20 (2), bin 31 (1)`: the bins failures fell in, most first."""
    if not len(failures):
        return "none"
    counts = failures[BIN].value_counts()
    counts = counts.sort_index().sort_values(ascending=False, kind="stable")
    return ", ".join(f"{int(b)} ({int(n)})" for b, n in counts.head(12).items()) + (" ..." if len(counts) > 12 else "")


def format_whole_clip(result: WholeClipEval) -> str:
    """One block per condition: each clip's completed rollouts, start transients and later failures, the
    bins of the failures and the tracking errors over the completed rollouts; then the overall line."""
    s = result.summary
    lines = [f"{s['checkpoint']} (iteration {s[ITERATION]}), {s['device']}: whole clips from their first frame to "
             f"their last, deterministic policy", ""]
    for condition in s["conditions"]:
        clips = result.clips[result.clips[CONDITION] == condition]
        fails = result.failures[result.failures[CONDITION] == condition]
        lines.append(f"{condition} ({s['rollouts_per_clip'][condition]} rollout(s) per clip):")
        for row in clips.itertuples(index=False):
            r = row._asdict()
            mine = fails[fails["clip"] == r["clip"]]
            errors = (f"; completed: MPKPE {r[MPKPE_MM]:.1f} mm, root-relative {r[MPKPE_REL_MM]:.1f} mm"
                      if r["completed"] and math.isfinite(r[MPKPE_MM]) else "")
            lines.append(f"  {r['clip_name']} ({r['clip_duration_s']:.1f} s): {r['completed']}/{r['rollouts']} completed "
                         f"(success {r[WHOLE_CLIP_SUCCESS]:.3f}); failures: {r['transient_failures']} within "
                         f"{START_TRANSIENT_S:g} s of the start, {r['later_failures']} later, in bins "
                         f"{_bins_text(mine)}{errors}")
        lines.append(f"  overall: success {s[whole_clip_key(condition, 'success_rate')]:.3f} "
                     f"({s[whole_clip_key(condition, 'completed')]}/{s[whole_clip_key(condition, 'rollouts')]})")
        lines.append("")
    if result.out_dir is not None:
        lines.append(f"tables: {result.out_dir}")
    return "\n".join(lines)


__all__ = ["WholeClipEval", "evaluate_whole_clip", "format_whole_clip", "write_whole_clip_tables"]
