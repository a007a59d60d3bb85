"""`RunRecord`: the tables a training run writes into its folder, held in memory between flushes, and
`write_evaluation`: the files of one evaluation of a saved policy (`bmimic.eval`, sim2sim). This module
is the one writer of run-folder tables (tests/test_architecture.py holds it so).

Rows are appended as they are made (a dict per training iteration; a frame per evaluation, sampler
snapshot or round of clip rollouts), `flush` writes each table atomically (rank 0 only: a record
made with `enabled=False` never writes), and on resume `truncate` reads the folder's tables back and
keeps the rows of the iterations the checkpoint had completed; a table made whole at once
(eval_robust) is written by `write_table`. `metrics` assembles metrics.json in the run schema's
order. Names are `bmimic.runs.folder`'s (files) and `bmimic.runs.schema`'s (columns and keys).
Torch-free.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping

import pandas as pd

from bmimic import BmimicError
from bmimic.runs import safe_read
from bmimic.runs.folder import (
    EVAL_TABLES,
    EVALUATION_TABLES,
    SIM2SIM_GAP,
    WHOLE_CLIP_FILES,
    atomic_write_csv,
    atomic_write_json,
    atomic_write_parquet,
    make_folder,
    table_path,
)
from bmimic.runs.schema import FINAL_METRICS, ITERATION, RUN_METRICS

TRAINING_TABLES = ("train_metrics", "sampler", "eval", "clip_eval", "whole_clip", "whole_clip_survival",
                   "whole_clip_failures")
"""The tables training writes (runs.folder.TABLES names); eval_robust is written once, at the end."""
ROW_TABLES = ("train_metrics",)
"""Tables kept as one dict per row (the others as frames)."""


class RunRecordError(BmimicError):
    """A run folder's table cannot be read back (a resume stops; moving the table aside resumes without it)."""


class RunRecord:
    """The training tables of one run folder: rows in memory, truncation on resume, atomic flushes."""

    def __init__(self, run_dir: str | os.PathLike, enabled: bool = True) -> None:
        self.run_dir = Path(run_dir)
        self.enabled = enabled
        """False (the other ranks under torchrun): rows are kept, nothing is written."""
        self._rows: dict[str, list] = {name: [] for name in TRAINING_TABLES}

    def append(self, name: str, rows: dict | pd.DataFrame) -> None:
        """One row (a dict, ROW_TABLES) or a frame of rows (the other tables) of table `name`."""
        self._rows[name].append(rows)

    def rows(self, name: str) -> list:
        """The rows of table `name` so far (dicts or frames, as appended); the caller must not change them."""
        return self._rows[name]

    def last_iteration(self, name: str) -> int | None:
        """The largest iteration among the last rows appended to `name` (None: no rows)."""
        rows = self._rows[name]
        if not rows:
            return None
        last = rows[-1]
        return int(last[ITERATION] if isinstance(last, dict) else last[ITERATION].max())

    def truncate(self, iteration: int) -> None:
        """Resume: read the folder's tables and keep the rows of iterations the checkpoint had completed
        (training rows before `iteration`, evaluation rows up to and including it)."""
        for name, rows in self._rows.items():
            path = table_path(self.run_dir, name)
            if not path.exists():
                continue
            try:
                df = pd.read_parquet(safe_read.regular_file(path, self.run_dir))  # a FIFO or device would hang
            except Exception as e:  # noqa: BLE001 - any reader error: the table is damaged
                raise RunRecordError(f"{path}: cannot be read ({type(e).__name__}: {(str(e).strip() or '-').splitlines()[0][:160]}); move it aside to "
                                     "resume without its rows") from None
            if ITERATION not in df:
                raise RunRecordError(f"{path}: has no {ITERATION} column; move it aside to resume without its rows")
            df = df[df[ITERATION] <= iteration] if name in EVALUATION_TABLES else df[df[ITERATION] < iteration]
            if name in ROW_TABLES:
                rows.extend(df.to_dict("records"))
            else:
                rows.append(df)

    def flush(self) -> None:
        """Write every table that has rows (atomically; nothing when not `enabled`)."""
        if not self.enabled:
            return
        for name, rows in self._rows.items():
            if rows:
                table = pd.DataFrame(rows) if name in ROW_TABLES else pd.concat(rows, ignore_index=True)
                atomic_write_parquet(table_path(self.run_dir, name), table)

    def write_table(self, name: str, table: pd.DataFrame) -> None:
        """Write table `name` whole, now (atomically; nothing when not `enabled`): for a table made at
        once rather than row by row (eval_robust, after the last iteration). A table held as rows is
        refused: its next flush would overwrite what this wrote."""
        if name in self._rows:
            raise RunRecordError(f"{name}: is written from its rows by flush, not whole")
        if self.enabled:
            atomic_write_parquet(table_path(self.run_dir, name), table)


def metrics(final: dict[str, Any], robust: dict[str, Any], run: dict[str, Any]) -> dict[str, Any]:
    """metrics.json: the final evaluation's FINAL_METRICS (from its summary, `eval_*` keys), the robust
    evaluation's `final_robust_eval_*` and the final whole-clip evaluation's `final_whole_clip_*` (if
    any; both in `robust`), then the run's RUN_METRICS (every one required)."""
    missing = [k for k in RUN_METRICS if k not in run]
    if missing:
        raise RunRecordError(f"metrics.json: the run's {', '.join(missing)} missing")
    return {**{name: final[name.removeprefix("final_")] for name in FINAL_METRICS}, **robust,
            **{k: run[k] for k in RUN_METRICS}}


def write_evaluation(out_dir: str | os.PathLike, episodes: pd.DataFrame, bins: pd.DataFrame,
                     segments: pd.DataFrame, summary: dict[str, Any],
                     gap: pd.DataFrame | None = None, tables: Mapping[str, pd.DataFrame] | None = None) -> Path:
    """One finished evaluation of a saved policy into `out_dir` (eval/<label>/ for `bmimic.eval`,
    sim2sim/<model>/<label>/ for sim2sim, which adds its `gap` table; sim2sim's whole-clip rollouts add
    `tables`, CSVs by runs.folder file name): runs.folder.EVAL_TABLES, each atomically, the summary last
    so that its presence means a complete set (a reader, or sim2sim's gap, never takes a half-written
    evaluation). Returns `out_dir` as a Path."""
    episodes_file, bins_file, segments_file, summary_file = EVAL_TABLES
    out_dir = make_folder(out_dir)
    if gap is not None:
        atomic_write_csv(out_dir / SIM2SIM_GAP, gap)
    for name, table in (tables or {}).items():
        atomic_write_csv(out_dir / name, table)
    atomic_write_parquet(out_dir / episodes_file, episodes)
    atomic_write_parquet(out_dir / bins_file, bins)
    atomic_write_csv(out_dir / segments_file, segments)
    atomic_write_json(out_dir / summary_file, summary)
    return out_dir


def write_whole_clip(out_dir: str | os.PathLike, clips: pd.DataFrame, survival: pd.DataFrame,
                     failures: pd.DataFrame, summary: dict[str, Any]) -> Path:
    """One whole-clip evaluation of a saved policy into `out_dir` (eval/<label>/whole_clip/ for
    `bmimic.eval --whole-clip`): runs.folder.WHOLE_CLIP_FILES, each atomically, the summary last.
    Returns `out_dir` as a Path."""
    clips_file, survival_file, failures_file, summary_file = WHOLE_CLIP_FILES
    out_dir = make_folder(out_dir)
    atomic_write_csv(out_dir / clips_file, clips)
    atomic_write_csv(out_dir / survival_file, survival)
    atomic_write_csv(out_dir / failures_file, failures)
    atomic_write_json(out_dir / summary_file, summary)
    return out_dir


__all__ = ["ROW_TABLES", "TRAINING_TABLES", "RunRecord", "RunRecordError", "metrics", "write_evaluation",
           "write_whole_clip"]
