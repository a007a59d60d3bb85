"""bmimic's own (MuJoCo-Warp) whole-clip success of the checkpoint sim2sim's whole-clip rollouts ran,
read from the run folder (its whole-clip evaluation first), and the gap per condition and clip."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from bmimic.runs.folder import EVAL_DIR, EVAL_TABLES, WHOLE_CLIP_DIR, WHOLE_CLIP_FILES, table_path
from bmimic.runs.schema import BIN, CONDITION, HORIZON_TRUNCATED, ITERATION
from bmimic.sim2sim.gap import readable
from bmimic.sim2sim.spec import PolicySpec


def clip_spans(spec: PolicySpec) -> tuple[np.ndarray, np.ndarray]:
    """Each clip's first frame and exclusive end frame (bmimic.training.clip_rollouts.clip_bounds' rule)."""
    starts = np.asarray(spec.clip_starts, dtype=np.int64).reshape(-1)
    return starts, np.r_[starts[1:], spec.num_frames].astype(np.int64)


@dataclass
class WarpWholeClip:
    """bmimic's (MuJoCo-Warp) whole-clip outcome of the same checkpoint under one condition, per clip."""

    source: str
    """Where it was read, and what it is."""
    clips: pd.DataFrame
    """clip, rollouts, completed."""


def warp_whole_clip(run_dir: Path | None, label: str, iteration: int | None, spec: PolicySpec) -> dict[str, WarpWholeClip]:
    """bmimic's own whole-clip outcome of this checkpoint, by condition, from what the run folder holds
    (the first source that has it):

    1. bmimic's whole-clip evaluation (bmimic.training.whole_clip), every condition it ran: RUN/eval/<label>/
       whole_clip/ (`bmimic.eval --whole-clip`), else RUN/whole_clip.parquet at the checkpoint's iteration
       (eval.whole_clip during training);
    2. RUN/eval/<label>/ (`bmimic.eval`) whose horizon reaches each clip's end: its episodes that
       started in a clip's first bin and ran to the clip's end or failed, nominal (the stratified
       starts are a few frames after the clip's first frame);
    3. RUN/clip_eval.parquet (phc, protomotions) at the checkpoint's iteration: one rollout per clip
       from its first frame, nominal, where it was not cut short by `sampler.rollout_max_s`."""
    if run_dir is None:
        return {}
    starts, ends = clip_spans(spec)
    for source in (_from_whole_clip, _from_eval_episodes, _from_clip_eval):
        found = source(run_dir, label, iteration, starts, ends, spec)
        if found:
            return found
    return {}


def _from_whole_clip(run_dir: Path, label: str, iteration, starts, ends, spec) -> dict[str, WarpWholeClip]:
    folder = run_dir / EVAL_DIR / label / WHOLE_CLIP_DIR
    clips_file, summary_file = folder / WHOLE_CLIP_FILES[0], folder / WHOLE_CLIP_FILES[-1]
    if clips_file.is_file() and summary_file.is_file():
        with readable(clips_file, run_dir):
            table = pd.read_csv(clips_file)[[CONDITION, "clip", "rollouts", "completed"]]
        source = f"{folder} (bmimic.eval --whole-clip)"
    else:
        path = table_path(run_dir, "whole_clip")
        if iteration is None or not path.is_file():
            return {}
        with readable(path, run_dir):
            table = pd.read_parquet(path)[[ITERATION, CONDITION, "clip", "rollouts", "completed"]]
        table = table[table[ITERATION] == iteration]
        source = f"{path} (iteration {iteration})"
    return {str(condition): WarpWholeClip(f"{source}, {condition}", g[["clip", "rollouts", "completed"]].astype(
        np.int64).reset_index(drop=True)) for condition, g in table.groupby(CONDITION, sort=False) if len(g) == len(starts)}


def _from_eval_episodes(run_dir: Path, label: str, iteration, starts, ends, spec) -> dict[str, WarpWholeClip]:
    from bmimic.sampling.layouts import make_layout

    folder = run_dir / EVAL_DIR / label
    episodes_file, summary_file = folder / EVAL_TABLES[0], folder / EVAL_TABLES[-1]
    if not (episodes_file.is_file() and summary_file.is_file()):
        return {}
    with readable(episodes_file, run_dir):
        ep = pd.read_parquet(episodes_file)
        ep = ep[[BIN, "start_frame", "end_frame", "failed", HORIZON_TRUNCATED]]
    layout = make_layout(spec.bin_layout, spec.num_frames, spec.fps, spec.bin_size_s, clip_starts=spec.clip_starts)
    first_bins = layout.frame_to_bin.numpy()[starts]
    rows = []
    for c, (b, end) in enumerate(zip(first_bins, ends)):
        # started in the clip's first bin, with a horizon past the clip's end: it ran to the end or failed
        mine = ep[(ep[BIN] == b) & ep[HORIZON_TRUNCATED].astype(bool)]
        mine = mine[mine["failed"].astype(bool) | (mine["end_frame"] == end - 1)]
        if len(mine):
            rows.append((c, len(mine), int((~mine["failed"].astype(bool)).sum()), int(mine["start_frame"].max())))
    if len(rows) != len(starts):
        return {}
    clips = pd.DataFrame(rows, columns=["clip", "rollouts", "completed", "latest_start_frame"])
    return {"nominal": WarpWholeClip(f"{folder} (episodes started in each clip's first bin, up to frame "
                                     f"{int(clips['latest_start_frame'].max())} after it, that ran to its end or failed)",
                                     clips.drop(columns=["latest_start_frame"]))}


def _from_clip_eval(run_dir: Path, label: str, iteration, starts, ends, spec) -> dict[str, WarpWholeClip]:
    table = table_path(run_dir, "clip_eval")
    if iteration is None or not table.is_file():
        return {}
    with readable(table, run_dir):
        rows = pd.read_parquet(table)
        rows = rows[rows[ITERATION] == iteration]
        whole = rows[rows["failed"].astype(bool) | rows["reached_end"].astype(bool)]
    if whole.empty or len(whole) != len(starts):
        return {}
    clips = pd.DataFrame({"clip": whole["clip"].to_numpy(dtype=np.int64), "rollouts": 1,
                          "completed": whole["reached_end"].to_numpy(dtype=np.int64)})
    return {"nominal": WarpWholeClip(f"{table} (iteration {iteration}: one rollout per clip from its first frame)",
                                     clips)}


def gap_table(rollouts: pd.DataFrame, warp: dict[str, WarpWholeClip]) -> pd.DataFrame:
    """Per condition and clip: native rollouts, completed and success, bmimic's (where known) and the gap."""
    native = rollouts.groupby(["condition", "clip", "clip_name"], sort=False).agg(
        sim2sim_rollouts=("completed", "size"), sim2sim_completed=("completed", "sum")).reset_index()
    native["sim2sim_success_rate"] = native["sim2sim_completed"] / native["sim2sim_rollouts"]
    theirs = [w.clips.assign(condition=c, warp_source=w.source) for c, w in warp.items()]
    other = (pd.concat(theirs, ignore_index=True) if theirs else
             pd.DataFrame(columns=["condition", "clip", "rollouts", "completed", "warp_source"]))
    other = other.rename(columns={"rollouts": "warp_rollouts", "completed": "warp_completed"})
    out = native.merge(other, on=["condition", "clip"], how="left")
    out["warp_success_rate"] = out["warp_completed"].astype(float) / out["warp_rollouts"].astype(float)
    out["success_gap"] = out["sim2sim_success_rate"] - out["warp_success_rate"]
    return out


__all__ = ["WarpWholeClip", "clip_spans", "gap_table", "warp_whole_clip"]
