"""The MuJoCo-Warp evaluation of the same checkpoint and sim2sim's gap to it, compared like with like."""

from __future__ import annotations

import contextlib
import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bmimic.runs.folder import (
    EVAL_DIR,
    EVAL_SUMMARY,
    EVAL_TABLES,
    SIM2SIM_GAP,
    read_resolved_config,
    table_path,
)
from bmimic.runs.schema import BIN, FAILURE_RATE, HORIZON_TRUNCATED, ITERATION, MPKPE_REL_MM

if TYPE_CHECKING:
    import pandas as pd
from bmimic.runs import safe_read
from bmimic.sim2sim.spec import Sim2SimError

log = logging.getLogger("bmimic.sim2sim")

GAP_FILE = SIM2SIM_GAP
"""The gap table's file name (bmimic.runs.folder spells it)."""
SETTINGS = ("episodes_per_bin", "horizon_s", "max_mpkpe_rel_mm")
"""Evaluation settings two evaluations must share to be compared bin by bin."""


@dataclass
class WarpEval:
    """The MuJoCo-Warp evaluation of the same checkpoint, for the gap."""

    source: str
    """Where it was read."""
    bins: pd.DataFrame
    """pandas DataFrame: bin, visits, failures, success_rate (1 - failures / visits), mpkpe_rel_mm, and
    where the table has them start_episodes and eval_steps."""
    success_rate: float
    """Overall success rate (episodes that did not fail / episodes)."""
    mpkpe_rel_mm: float
    """Overall anchor-relative MPKPE (mean over the evaluation steps)."""
    settings: dict
    """The SETTINGS it ran with, as far as known (a missing key: unknown; max_mpkpe_rel_mm None: not set)."""


def warp_eval(run_dir: Path | None, label: str, iteration: int | None) -> WarpEval | None:
    """RUN/eval/<label>/ (bmimic.eval) if present, else the training-time rows of RUN/eval.parquet."""
    import pandas as pd

    from bmimic.training.evaluator import summarize

    if run_dir is None:
        return None
    columns = [BIN, "visits", "failures", "success_rate", MPKPE_REL_MM]
    extra = ["start_episodes", "eval_steps"]  # for restrict(); tables written before them lack them
    folder = run_dir / EVAL_DIR / label
    summary_file, bins_file = folder / EVAL_SUMMARY, folder / EVAL_TABLES[1]
    if summary_file.is_file() and bins_file.is_file():
        with readable(summary_file, run_dir):
            s = safe_read.read_json(summary_file)
            success, mpkpe = (math.nan if s[k] is None else float(s[k]) for k in ("eval_success_rate", "eval_mpkpe_rel_mm"))
        with readable(bins_file, run_dir):
            bins = pd.read_parquet(bins_file)
        if "visits" in bins:
            with readable(bins_file, run_dir):
                return WarpEval(str(folder), bins[columns + [c for c in extra if c in bins]], success, mpkpe,
                                {k: s[k] for k in SETTINGS if k in s})
        log.warning("%s: tables of the old start-bin accounting, not compared (evaluate again with python -m "
                    "bmimic.eval)", folder)
    table = table_path(run_dir, "eval")
    if iteration is None or not table.is_file():
        return None
    with readable(table, run_dir):
        rows = pd.read_parquet(table)
        rows = rows[rows[ITERATION] == iteration].reset_index(drop=True)
    if rows.empty:
        return None
    if "visits" not in rows:
        log.warning("%s: rows of the old start-bin accounting, not compared (run python -m bmimic.eval %s)",
                    table, run_dir)
        return None
    with readable(table, run_dir):
        overall = summarize(rows)
        settings = {"episodes_per_bin": int(rows["start_episodes"].max())}
        config = _run_eval_config(run_dir)
        settings |= {k: config[k] for k in SETTINGS[1:] if k in config}
        return WarpEval(f"{table} (iteration {iteration})",
                        rows.assign(success_rate=1.0 - rows[FAILURE_RATE])[columns + [c for c in extra if c in rows]],
                        overall["eval_success_rate"], overall["eval_mpkpe_rel_mm"], settings)


@contextlib.contextmanager
def readable(path: Path, run_dir: Path | None = None):
    """A file of the MuJoCo-Warp evaluation that cannot be read (damaged, or lacking a column) is one
    line naming it, not a traceback from the reader; one that is not a regular file of `run_dir` (a FIFO,
    a device, a link out of the run) is refused before a reader opens it (it would block or read forever)."""
    try:
        safe_read.regular_file(path, run_dir)
        yield
    except Exception as e:  # noqa: BLE001 - JSON, pyarrow and pandas raise many types for a damaged file
        text = str(e).strip()
        raise Sim2SimError(f"{path}: cannot be read ({type(e).__name__}: {text.splitlines()[0][:120] if text else ''}); "
                           "move it aside, or evaluate the checkpoint again with python -m bmimic.eval") from None


def _run_eval_config(run_dir: Path | None) -> dict:
    """The run's resolved `eval` settings (resolved_config.json), or {} when unknown."""
    section = (read_resolved_config(run_dir) or {}).get("eval") if run_dir is not None else None
    return section if isinstance(section, dict) else {}


def eval_settings(run_dir: Path | None, warp: WarpEval | None, episodes_per_bin: int | None,
                  horizon_s: float | None, max_mpkpe_rel_mm: float | None) -> dict:
    """The SETTINGS of this evaluation: given ones win, then the MuJoCo-Warp evaluation's (so the gap
    compares like with like), then the run's config, then bmimic's defaults on a CPU."""
    given = {"episodes_per_bin": episodes_per_bin, "horizon_s": horizon_s, "max_mpkpe_rel_mm": max_mpkpe_rel_mm}
    known = {"episodes_per_bin": 1, "horizon_s": 2.0, "max_mpkpe_rel_mm": None}
    config = _run_eval_config(run_dir)  # a null max_mpkpe_rel_mm is a setting ("not set"), other nulls are not
    known |= {k: config[k] for k in SETTINGS if k in config and (config[k] is not None or k == "max_mpkpe_rel_mm")}
    known |= warp.settings if warp is not None else {}
    out: dict[str, Any] = {k: given[k] if given[k] is not None else known[k] for k in SETTINGS}
    def positive(x) -> bool:
        return isinstance(x, (int, float)) and math.isfinite(x) and x > 0

    if out["episodes_per_bin"] < 1 or not positive(out["horizon_s"]) or not (out["max_mpkpe_rel_mm"] is None
                                                                            or positive(out["max_mpkpe_rel_mm"])):
        raise Sim2SimError(f"--episodes-per-bin {out['episodes_per_bin']} / --horizon-s {out['horizon_s']} / "
                           f"--max-mpkpe-rel-mm {out['max_mpkpe_rel_mm']}: need >= 1, finite > 0 and finite > 0")
    return {"episodes_per_bin": int(out["episodes_per_bin"]), "horizon_s": float(out["horizon_s"]),
            "max_mpkpe_rel_mm": None if out["max_mpkpe_rel_mm"] is None else float(out["max_mpkpe_rel_mm"])}


def setting_differences(ours: dict, warp: WarpEval) -> list[str]:
    """Each SETTING in which this evaluation differs from the MuJoCo-Warp one, or that is unknown there."""
    out = []
    for key in SETTINGS:
        if key not in warp.settings:
            out.append(f"{key}: {ours[key]} here, unknown there")
            continue
        a, b = ours[key], warp.settings[key]
        if (a is None) != (b is None) or (a is not None and not math.isclose(float(a), float(b))):
            out.append(f"{key}: {a} here, {b} there")
    return out


def restrict(warp: WarpEval, bins) -> WarpEval:
    """The MuJoCo-Warp evaluation over `bins` alone (sim2sim --clip): its overall success and MPKPE
    recomputed from those bins (failures / started episodes; MPKPE weighted by the steps taken)."""
    import numpy as np

    rows = warp.bins[warp.bins[BIN].isin(bins)].reset_index(drop=True)
    steps = rows["eval_steps"].to_numpy(dtype=float) if "eval_steps" in rows else np.zeros(len(rows))
    started = float(rows["start_episodes"].sum()) if "start_episodes" in rows else 0.0
    success = 1.0 - float(rows["failures"].sum()) / started if started else math.nan
    mpkpe = float(np.nansum(rows[MPKPE_REL_MM].to_numpy(dtype=float) * steps) / steps.sum()) if steps.sum() else math.nan
    return WarpEval(f"{warp.source}, {len(rows)} of its bins", rows, success, mpkpe, warp.settings)


def gap_table(bins, warp: WarpEval):
    """Per bin: MuJoCo-Warp and sim2sim visits, failures (where they happened), success rate per visit
    and anchor-relative MPKPE, and the differences."""
    ours = bins[[BIN, "bin_start_s", "bin_end_s", "segment", HORIZON_TRUNCATED, "visits", "failures",
                 "success_rate", MPKPE_REL_MM]]
    names = ["visits", "failures", "success_rate", MPKPE_REL_MM]
    out = ours.rename(columns={c: f"sim2sim_{c}" for c in names})
    out = out.merge(warp.bins[[BIN, *names]].rename(columns={c: f"warp_{c}" for c in names}), on=BIN, how="left")
    out["success_gap"] = out["sim2sim_success_rate"] - out["warp_success_rate"]
    out["mpkpe_rel_gap_mm"] = out["sim2sim_mpkpe_rel_mm"] - out["warp_mpkpe_rel_mm"]
    return out


def format_gap(result, warp: WarpEval | None, gap) -> str:
    s = result.summary
    if warp is None:
        return ("gap to MuJoCo-Warp: no evaluation of this checkpoint in the run folder "
                "(run python -m bmimic.eval RUN to get one)")
    lines = [f"gap to MuJoCo-Warp ({warp.source}); success = 1 - failures / visits per bin, "
             f"failures charged where they happen:",
             f"  success rate   warp {warp.success_rate:.3f}  sim2sim {s['eval_success_rate']:.3f}  "
             f"gap {s['eval_success_rate'] - warp.success_rate:+.3f}",
             f"  rel MPKPE mm   warp {warp.mpkpe_rel_mm:.1f}  sim2sim {s['eval_mpkpe_rel_mm']:.1f}  "
             f"gap {s['eval_mpkpe_rel_mm'] - warp.mpkpe_rel_mm:+.1f}"]
    if s["gap_setting_differences"]:
        lines.append("  note: not like with like, the evaluations differ in " + "; ".join(s["gap_setting_differences"]))
    shown = gap
    title = "per bin:"
    if len(gap) > 30:
        shown = gap.reindex(gap["success_gap"].abs().sort_values(ascending=False).index).head(10)
        title = f"the 10 bins of {len(gap)} with the largest success gap:"
    cols = [BIN, "segment", "warp_visits", "sim2sim_visits", "warp_success_rate", "sim2sim_success_rate",
            "success_gap", "warp_mpkpe_rel_mm", "sim2sim_mpkpe_rel_mm", "mpkpe_rel_gap_mm"]
    lines += [title, shown[cols].to_string(index=False, float_format=lambda v: f"{v:.3f}")]
    return "\n".join(lines)
