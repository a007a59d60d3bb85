"""`RunRecord`: the tables a training run writes into its folder, held in memory between flushes.

Rows are appended as they are made (a dict per training iteration; a frame per evaluation, sampler
snapshot or round of clip rollouts), `flush` writes each table atomically (rank 0 only: a record
made with `enabled=False` never writes), and on resume `truncate` reads the folder's tables back and
keeps the rows of the iterations the checkpoint had completed. `metrics` assembles metrics.json in
the run schema's order. Names are `bmimic.run_folder`'s (files) and `bmimic.run_schema`'s (columns
and keys). Torch-free.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import pandas as pd

from bmimic import BmimicError
from bmimic.run_folder import atomic_write_parquet, table_path
from bmimic.run_schema import FINAL_METRICS, ITERATION, RUN_METRICS

TRAINING_TABLES = ("train_metrics", "sampler", "eval", "clip_eval")
"""The tables training writes (run_folder.TABLES names); eval_robust is written once, at the end."""
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
                df = pd.read_parquet(path)
            except Exception as e:  # noqa: BLE001 - any reader error: the table is damaged
                raise RunRecordError(f"{path}: cannot be read ({type(e).__name__}); move it aside to resume without "
                                     "its rows") from None
            if ITERATION not in df:
                raise RunRecordError(f"{path}: has no {ITERATION} column; move it aside to resume without its rows")
            df = df[df[ITERATION] <= iteration] if "eval" in name else df[df[ITERATION] < iteration]
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


def metrics(final: dict[str, Any], robust: dict[str, Any], run: dict[str, Any]) -> dict[str, Any]:
    """metrics.json: the final evaluation's FINAL_METRICS (from its summary, `eval_*` keys), the robust
    evaluation's `final_robust_eval_*` (if any), then the run's RUN_METRICS (every one required)."""
    missing = [k for k in RUN_METRICS if k not in run]
    if missing:
        raise RunRecordError(f"metrics.json: the run's {', '.join(missing)} missing")
    return {**{name: final[name.removeprefix("final_")] for name in FINAL_METRICS}, **robust,
            **{k: run[k] for k in RUN_METRICS}}


__all__ = ["ROW_TABLES", "TRAINING_TABLES", "RunRecord", "RunRecordError", "metrics"]
