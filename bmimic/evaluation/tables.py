"""The tables of one evaluation of a saved policy: one row per episode, per time bin and per motion
segment, with the MuJoCo-Warp evaluator's accounting (bmimic.training.evaluator.aggregate); they are
written by bmimic.runs.record.write_evaluation. sim2sim builds the same tables from native-MuJoCo episodes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from bmimic.runs.record import write_evaluation
from bmimic.runs.schema import BIN, ERROR_COLUMNS, FAILURE_RATE, HORIZON_TRUNCATED, ITERATION


def segment_at(segments, t_s: np.ndarray) -> tuple[list[str], list[str]]:
    """(segment name, difficulty) covering each time ('' where no segment does)."""
    names, levels = [], []
    for t in np.asarray(t_s, dtype=float):
        hit = next((s for s in segments if s.start_s <= t < s.end_s), None)
        names.append(hit.name if hit else "")
        levels.append(hit.difficulty if hit else "")
    return names, levels


def episode_table(raw: pd.DataFrame, layout, motion, step_dt: float, iteration: int) -> pd.DataFrame:
    """One row per episode: where it started and ended, whether and where it failed, how long it lived,
    and its mean errors (raw: Rollouts.episodes of Evaluator.run_episodes or another evaluator;
    layout: the BinLayout it was run with)."""
    edges = layout.edges_s.cpu().numpy()
    start_s = raw["start_frame"].to_numpy() / motion.fps
    segment, difficulty = segment_at(motion.segments, start_s)
    bins = raw[BIN].to_numpy()
    failed = raw["failed"].to_numpy().astype(bool)
    failure_frame = raw["failure_frame"].to_numpy().astype(int)
    fail_bin = layout.frame_to_bin.cpu().numpy()[np.where(failed, failure_frame, 0)]
    return pd.DataFrame({
        ITERATION: int(iteration),
        "episode": np.arange(len(raw)),
        BIN: bins.astype(int),
        "bin_start_s": edges[bins],
        "bin_end_s": edges[bins + 1],
        "segment": segment,
        "difficulty": difficulty,
        "start_frame": raw["start_frame"].to_numpy().astype(int),
        "start_s": start_s,
        "end_frame": raw["end_frame"].to_numpy().astype(int),
        "failed": failed,
        "success": ~failed,
        "terminated": raw["terminated"].to_numpy().astype(bool),
        "error_failed": raw["error_failed"].to_numpy().astype(bool),
        "broken": raw["broken"].to_numpy().astype(bool) if "broken" in raw else np.zeros(len(raw), dtype=bool),
        "failure_frame": failure_frame,
        "failure_bin": np.where(failed, fail_bin, -1),
        HORIZON_TRUNCATED: raw[HORIZON_TRUNCATED].to_numpy().astype(bool),
        "steps": raw["steps"].to_numpy().astype(int),
        "survival_s": raw["steps"].to_numpy() * step_dt,
        **{c: raw[c].to_numpy(dtype=float) for c in ERROR_COLUMNS},
    })


def _with_rates(table: pd.DataFrame, survival_s: np.ndarray) -> pd.DataFrame:
    """success_rate (1 - failure_rate) and `mean_survival_s` (of the episodes started in each row's group)."""
    table.insert(table.columns.get_loc(FAILURE_RATE) + 1, "success_rate", 1.0 - table[FAILURE_RATE])
    table.insert(table.columns.get_loc("start_failures") + 1, "mean_survival_s", survival_s)
    return table


def bin_table(rollouts, episodes: pd.DataFrame, layout, segments) -> pd.DataFrame:
    """One row per time bin of `layout`: failures where they happened per visit (training's eval.parquet
    columns), the start-bin counts, and the mean survival of the episodes started in it."""
    from bmimic.training.evaluator import bin_table as labelled_bins

    per_bin = labelled_bins(rollouts, layout, segments)
    per_bin.insert(0, ITERATION, int(episodes[ITERATION].iloc[0]))
    survival = episodes.groupby(BIN)["survival_s"].mean().reindex(per_bin[BIN]).to_numpy(dtype=float)
    return _with_rates(per_bin, survival)


def segment_table(rollouts, episodes: pd.DataFrame, motion) -> pd.DataFrame:
    """One row per stretch of the motion covered by one segment ('' = no segment), in time order, with
    the same per-visit accounting as the bins: visits, failures where they happened, start counts."""
    from bmimic.training.evaluator import aggregate

    labels, levels = segment_at(motion.segments, np.arange(motion.num_frames) / motion.fps)
    names = np.asarray(labels, dtype=object)
    stretch = np.r_[0, np.cumsum(names[1:] != names[:-1])]  # contiguous frames of one label
    per_seg = aggregate(rollouts.episodes, stretch, rollouts.frame_errors)
    ids = per_seg.pop(BIN).to_numpy()
    first = np.searchsorted(stretch, ids)
    last = np.searchsorted(stretch, ids, side="right") - 1
    per_seg.insert(0, "segment", names[first])
    per_seg.insert(1, "difficulty", np.asarray(levels, dtype=object)[first])
    per_seg.insert(2, "start_s", first / motion.fps)
    per_seg.insert(3, "end_s", (last + 1) / motion.fps)
    started = stretch[episodes["start_frame"].to_numpy()]
    survival = episodes.groupby(started)["survival_s"].mean().reindex(ids).to_numpy(dtype=float)
    return _with_rates(per_seg, survival)


@dataclass
class EvalResult:
    """What `evaluate` produced, and where it was written."""

    episodes: pd.DataFrame
    """One row per episode."""
    bins: pd.DataFrame
    """One row per time bin."""
    segments: pd.DataFrame
    """One row per motion segment."""
    summary: dict
    """Overall numbers and provenance (eval_summary.json)."""
    out_dir: Path | None = None
    """Folder the tables were written to (None until written)."""



def write_tables(result: EvalResult, out_dir: Path, gap: pd.DataFrame | None = None,
                 tables: dict[str, pd.DataFrame] | None = None) -> Path:
    """Write the four tables (runs.folder.EVAL_TABLES), sim2sim's `gap` and other `tables` (CSVs by file
    name), if any, through the run record (bmimic.runs.record.write_evaluation: atomically, the summary
    last)."""
    result.out_dir = write_evaluation(out_dir, result.episodes, result.bins, result.segments,
                                      result.summary, gap, tables)
    return result.out_dir


