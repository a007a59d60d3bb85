"""Run folders -> tidy pandas frames.

A *run folder* holds ``status.json`` and/or ``.hydra/config.yaml`` (see docs/architecture.md,
"Run folder contents"). Sweeps put each job at ``<sweep>/<override_dirname>/seed=<seed>/``;
single runs live at ``outputs/runs/<run_name>/<timestamp>/``. An *arm* is a job's overrides
without the seed: the folder name above ``seed=*`` for sweep jobs, and ``sampler.name`` plus the
overrides that differ between runs of that sampler for single runs.

Loading is lenient per run and strict per table: a run that failed, never wrote ``status.json``
or lacks a table is kept in the runs frame with ``included=False`` and a ``problem`` saying why
(the report lists it), while a table that cannot be read once a run is included is an error.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import pandas as pd

from analysis import AnalysisError
from analysis.inputs import MIXED_FLAG, check_comparable, collapse_duplicate_seeds, mark_copies
from analysis.run_files import (
    NEEDED_TABLES,
    REQUIRED_COLUMNS,
    config_value,
    find_run_dirs,
    missing_columns,
    parse_value,
    read_config,
    read_json,
    read_overrides,
    read_sweep_file,
    seed_from_name,
    table_problem,
)
from analysis.table_checks import check_table
from bmimic.runs import safe_read
from bmimic.runs.folder import (
    EVAL_DIR,
    EVALUATION_TABLES,
    MOTION_SEGMENTS,
    STATUS,
    SWEEP_INDEX,
    TABLES,
    WHOLE_CLIP_DIR,
    WHOLE_CLIP_FILES,
    read_resolved_config,
    table_path,
)
from bmimic.runs.schema import CONDITION, ENV_STEPS, ITERATION

log = logging.getLogger("analysis")

RUN_COLUMNS = [
    "run_dir", "sweep_dir", "arm", "seed", "status", "error", ITERATION, "sampler",
    "overrides", "included", "problem",
]
"""The fixed columns of the runs frame; ``param.<key>`` columns follow (see load_runs)."""

def _read_run(run_dir: Path, root: Path) -> dict:
    """One row of the runs frame (without the arm of single runs, filled in later)."""
    row: dict[str, Any] = {"run_dir": str(run_dir), "error": None, ITERATION: None, "problem": None}
    problems = []
    try:
        cfg = read_config(run_dir)
        overrides = read_overrides(run_dir)
    except AnalysisError as e:
        cfg, overrides = {}, {}
        problems.append(str(e))
    try:
        status = read_json(run_dir / STATUS)
    except AnalysisError as e:
        status = None
        problems.append(str(e))
    if isinstance(status, dict):
        row["status"] = str(status.get("status", "unknown"))
        row["error"] = status.get("error")
        row[ITERATION] = _whole(status.get(ITERATION))
    else:
        row["status"] = "unknown"
        problems.append("no status.json")

    seed = cfg.get("seed", seed_from_name(run_dir))
    whole = (isinstance(seed, int) and not isinstance(seed, bool)) or (isinstance(seed, float) and seed.is_integer())
    row["seed"] = int(seed) if whole and seed is not None else None
    if row["seed"] is None:
        problems.append(f"its seed {seed!r} is not a whole number (.hydra/config.yaml)")
    row["sampler"] = config_value(cfg, "sampler.name")
    row["overrides"] = ",".join(f"{k}={v}" for k, v in sorted(overrides.items()))
    row["_overrides"] = overrides
    row["_sweep_file"] = read_sweep_file(run_dir)
    row["_cfg"] = cfg
    row["_resolved"] = read_resolved_config(run_dir)  # the budget as trained (analysis.inputs)

    # Sweep jobs: the arm is the override_dirname folder (relative to the sweep, in case a value
    # held a '/'); a sweep without overrides puts seed=* at its root and falls back to the sampler.
    if seed_from_name(run_dir) is not None:
        arm_dir = run_dir.parent
        if root in arm_dir.parents or (arm_dir == root and "=" not in root.name):
            sweep_dir = root
        else:  # the path given was the arm folder itself
            sweep_dir = arm_dir.parent
        row["sweep_dir"] = str(sweep_dir)
        row["arm"] = arm_dir.relative_to(sweep_dir).as_posix() if arm_dir != sweep_dir else None
    else:
        row["sweep_dir"] = None
        row["arm"] = None

    if row["status"] == "failed":
        problems.append(f"failed: {row['error']}" if row["error"] else "failed")
    elif row["status"] not in ("done", "running", "interrupted") and row["status"] != "unknown":
        problems.append(f"status {row['status']!r}")
    problems += [p for p in (table_problem(run_dir, t) for t in NEEDED_TABLES) if p]
    row["problem"] = "; ".join(problems) if problems else None
    row["included"] = not problems
    return row


def _whole(value: Any) -> int | None:
    """status.json's iteration as a whole number >= 0, else None (NaN, Infinity or 1e30 in a damaged record
    would fail the runs frame's integer column)."""
    try:
        number = float(value) if not isinstance(value, bool) else math.nan
    except (TypeError, ValueError, OverflowError):
        return None
    return int(number) if math.isfinite(number) and number.is_integer() and 0 <= number <= 2**53 else None


def _single_run_arms(rows: list[dict]) -> None:
    """Name single runs (and seed-only sweeps) ``sampler.name`` plus the overrides that differ
    between runs of the same sampler (never the seed or the ``sampler`` group choice itself)."""
    pending = [r for r in rows if r["arm"] is None]
    by_sampler: dict[str, list[dict]] = {}
    for r in pending:
        by_sampler.setdefault(str(r["sampler"]), []).append(r)
    for sampler, group in by_sampler.items():
        keys = sorted({k for r in group for k in r["_overrides"] if k != "sampler"})
        differing = [k for k in keys if len({r["_overrides"].get(k) for r in group}) > 1]
        for r in group:
            extra = [f"{k}={r['_overrides'][k]}" for k in differing if k in r["_overrides"]]
            r["arm"] = ",".join([sampler, *extra])


def _missing_jobs(rows: list[dict]) -> list[dict]:
    """Rows for sweep jobs absent from disk: every (arm, seed) of a sweep's grid with no folder,
    plus jobs listed in the sweep's index.csv whose folder is gone.

    A grid is the arms launched from one sweeps/ file (their ``+sweep=`` override) times the seeds seen
    among them: a study whose files share one folder with different seed lists (5 seeds for its
    baselines, 3 per knob level) expects each file's own seeds, not the union over the folder."""
    missing = []
    sweeps: dict[str, list[dict]] = {}
    for r in rows:
        if r["sweep_dir"] is not None:
            sweeps.setdefault(r["sweep_dir"], []).append(r)
    for sweep_dir, group in sweeps.items():
        present = {r["run_dir"] for r in group}
        expected: dict[str, tuple[str, int]] = {}
        grids: dict[str | None, list[dict]] = {}
        for r in group:
            grids.setdefault(r.get("_sweep_file"), []).append(r)
        for members in grids.values():
            arm_dirs = {r["arm"]: Path(r["run_dir"]).parent for r in members}
            seeds = sorted(s for s in {seed_from_name(Path(r["run_dir"])) for r in members} if s is not None)
            expected.update({
                str(arm_dir / f"seed={seed}"): (arm, seed) for arm, arm_dir in arm_dirs.items() for seed in seeds
            })
        index = Path(sweep_dir) / SWEEP_INDEX
        if index.is_file():
            try:
                listed = pd.read_csv(index)
            except (OSError, ValueError, pd.errors.ParserError):
                listed = pd.DataFrame()  # a broken index is rebuilt by analysis.index; the grid still applies
            if {"job", "arm", "seed"} <= set(listed.columns):
                for job, arm, seed in zip(listed["job"], listed["arm"], listed["seed"], strict=True):
                    if pd.notna(job) and pd.notna(seed):
                        expected[str(Path(sweep_dir) / str(job))] = (str(arm), int(seed))
        siblings = {r["arm"]: r for r in group}  # a missing job shares its arm's config
        for run_dir, (arm, seed) in sorted(expected.items()):
            if run_dir in present:
                continue
            missing.append({
                "run_dir": run_dir, "sweep_dir": sweep_dir, "arm": arm, "seed": seed,
                "status": "missing", "error": None, ITERATION: None,
                "sampler": siblings[arm]["sampler"] if arm in siblings else None,
                "overrides": siblings[arm]["overrides"] if arm in siblings else arm,
                "included": False, "problem": "job folder missing",
                "_overrides": siblings[arm]["_overrides"] if arm in siblings else {},
                "_cfg": siblings[arm]["_cfg"] if arm in siblings else {},
            })
    return missing


def arm_items(arm: str) -> dict[str, str]:
    """An arm's (or an overrides string's) ``key=value`` items as {key: value}."""
    return dict(i.split("=", 1) for i in str(arm).split(",") if "=" in i)


def short_arm_labels(arms) -> tuple[dict[str, str], list[str]]:
    """Name arms by the overrides that differ between them: ``({arm: label}, shared items)``.

    ``a=1,b=2,c=3`` and ``a=1,b=2,c=4`` become ``c=3`` and ``c=4`` (shared: ``a=1``, ``b=2``); an arm
    left with nothing is ``base``. Falls back to the full names if shortening would merge two arms.
    """
    arms = sorted({a for a in arms if isinstance(a, str)})
    if len(arms) < 2:
        return {a: a for a in arms}, []
    items = {a: a.split(",") for a in arms}
    shared = [i for i in items[arms[0]] if all(i in items[a] for a in arms[1:])]
    labels = {a: ",".join(i for i in items[a] if i not in shared) or "base" for a in arms}
    if len(set(labels.values())) != len(arms):
        return {a: a for a in arms}, []
    return labels, shared


def load_runs(paths, allow_mixed: bool = False, compare: bool = True) -> pd.DataFrame:
    """Find and describe every run under ``paths`` (sweep folders, run folders, or parents of runs).

    Returns one row per job with columns:

    - ``run_dir`` (str): the run folder; ``sweep_dir`` (str | None): the sweep it belongs to.
    - ``arm`` (str): the job's overrides without the seed (see the module docstring).
    - ``seed`` (Int64): from the config's ``seed`` (else the ``seed=<s>`` folder name).
    - ``status`` (str): ``done``/``running``/``failed`` from status.json, ``unknown`` when it is
      absent, ``missing`` for a sweep job with no folder; ``error`` (str | None);
      ``iteration`` (Int64): the last iteration status.json reports.
    - ``sampler`` (str): ``sampler.name`` from ``.hydra/config.yaml``.
    - ``overrides`` (str): the job's overrides, ``key=value`` joined by ``,``, sorted, without seed.
    - ``included`` (bool): status is done or running and train_metrics/eval are readable with the
      needed columns; ``problem`` (str | None): why not.
    - ``param.<key>`` for every override key of any run: the value in that run's config when the key
      is a config value there (so an arm that kept a default still gets it), else the override's
      value (e.g. a config-group choice such as ``param.sampler``), else missing.

    Raises AnalysisError when a path does not exist or no run folder is found under any path, and
    (analysis.inputs) when included runs differ in motion, bin layout or budget unless ``allow_mixed``, or when
    a run's tables are byte-identical to another's but its config differs (a copy with its seed edited); a
    run whose tables and config are byte-identical to another's is left out (``problem`` says so), and so is every
    run but one of a seed that appears more than once in an arm (analysis.inputs.collapse_duplicate_seeds).
    ``compare=False`` skips the motion, bin-layout and budget check, for a listing that compares nothing
    (the sweep index: a study may hold a bin-size knob's runs beside the others).
    """
    if isinstance(paths, str | Path):
        paths = [paths]
    rows = []
    seen = set()
    for path in paths:
        root = Path(path).resolve()
        run_dirs = find_run_dirs(root)
        for run_dir in run_dirs:
            if run_dir in seen:
                continue
            seen.add(run_dir)
            rows.append(_read_run(run_dir, root if root != run_dir else run_dir.parent.parent))
    if not rows:
        raise AnalysisError(f"no run folders (with status.json or .hydra/config.yaml) under {list(map(str, paths))}")
    mark_copies(rows, refuse=compare)  # a report refuses a copy with an edited seed; the index lists it
    for note in check_comparable(rows, allow_mixed) if compare else ():
        log.warning("%s (%s)", note, MIXED_FLAG)
    _single_run_arms(rows)
    for note in collapse_duplicate_seeds(rows):
        log.warning("warning: %s", note)
    rows += _missing_jobs(rows)

    keys = sorted({k for r in rows for k in r["_overrides"]})
    for r in rows:
        for k in keys:
            value = config_value(r["_cfg"], k)
            if value is None or isinstance(value, dict | list):
                raw = r["_overrides"].get(k)
                value = parse_value(raw) if raw is not None else None
            r[f"param.{k}"] = value
    df = pd.DataFrame([{k: v for k, v in r.items() if not k.startswith("_")} for r in rows])
    df = df[RUN_COLUMNS + [f"param.{k}" for k in keys]]
    df["seed"] = df["seed"].astype("Int64")
    df[ITERATION] = pd.to_numeric(df[ITERATION], errors="coerce").astype("Int64")
    df["included"] = df["included"].astype(bool)
    return df.sort_values(["arm", "seed", "run_dir"], na_position="last").reset_index(drop=True)


def load_table(runs: pd.DataFrame, name: str, max_iteration: int | None = None) -> pd.DataFrame:
    """One table of every included run, stacked: ``run_dir, arm, seed`` then the table's columns.

    ``max_iteration`` (ReportOptions.max_iteration) keeps the rows of a run that had trained at most that
    many iterations: evaluation rows (``iteration`` = iterations done) up to it, training and sampler rows
    (``iteration`` = the iteration's 0-based index) below it.

    ``name`` is a key of bmimic.runs.folder.TABLES (schemas in docs/architecture.md). Runs without the file are skipped
    (only possible for the optional tables); a file
    that is unreadable, lacks a needed column or breaks the run record's contract (analysis.table_checks:
    no rows, values out of range, bins the run does not have) raises AnalysisError naming it. With no rows, an
    empty frame with the needed columns is returned.
    """
    if name not in TABLES:
        raise AnalysisError(f"unknown table {name!r}; expected one of {sorted(TABLES)}")
    frames = []
    for run in runs[runs["included"]].itertuples(index=False):
        path = table_path(run.run_dir, name)
        table = None
        if path.is_file():
            try:
                table = pd.read_parquet(safe_read.regular_file(path, run.run_dir))  # never a FIFO, device, foreign link
            except Exception as e:  # pyarrow raises several types for truncated or foreign files
                raise AnalysisError(f"{path}: unreadable parquet ({type(e).__name__}: {e})") from e
            _check_read(path, name, table, run.run_dir)
        elif name in NEEDED_TABLES:
            raise AnalysisError(f"{path}: missing")
        if name in CHECKPOINT_WHOLE_CLIP_FILES:
            table = _with_checkpoint_whole_clips(Path(run.run_dir), name, table)
        if table is None:
            continue
        if max_iteration is not None and ITERATION in table.columns:
            done = table[ITERATION] if name in EVALUATION_TABLES else table[ITERATION] + 1
            table = table[done <= max_iteration]
        table = table.drop(columns=[c for c in ("run_dir", "arm", "seed") if c in table.columns])
        table.insert(0, "seed", run.seed)
        table.insert(0, "arm", run.arm)
        table.insert(0, "run_dir", run.run_dir)
        frames.append(table)
    if not frames:
        return pd.DataFrame(columns=["run_dir", "arm", "seed", *REQUIRED_COLUMNS[name]])
    return pd.concat(frames, ignore_index=True)


def load_segments(runs: pd.DataFrame) -> pd.DataFrame:
    """The motion segments ``name, start_s, end_s, difficulty`` from the first included run's
    ``motion_segments.json`` (runs of one report share a motion); empty when no run has the file."""
    for run_dir in runs.loc[runs["included"], "run_dir"]:
        path = Path(run_dir) / MOTION_SEGMENTS
        data = read_json(path)
        if data is None:
            continue
        if not isinstance(data, list) or not all(isinstance(s, dict) for s in data):
            raise AnalysisError(f"{path}: expected a list of {{name, start_s, end_s, difficulty}} objects")
        segments = pd.DataFrame(data)
        missing = [c for c in ("name", "start_s", "end_s") if c not in segments.columns]
        if missing:
            raise AnalysisError(f"{path}: segments lack fields {missing}")
        return segments
    return pd.DataFrame(columns=["name", "start_s", "end_s", "difficulty"])


CHECKPOINT_WHOLE_CLIP_FILES = {"whole_clip": WHOLE_CLIP_FILES[0], "whole_clip_failures": WHOLE_CLIP_FILES[2]}
"""The run tables the analysis reads that `python -m bmimic.eval RUN --whole-clip` also writes, per
checkpoint, as eval/<checkpoint label>/whole_clip/<file> (without the iteration, which its summary holds).
The survival file is a view of these two (bmimic.runs.schema.whole_clip_survival), derived again, never read."""


def _check_read(path: Path, name: str, table: pd.DataFrame, run_dir) -> None:
    missing = missing_columns(name, table.columns)
    if missing:
        raise AnalysisError(f"{path}: missing columns {missing}")
    check_table(path, name, table, run_dir)  # ranges, bins, rows: one line naming file and column


def _with_checkpoint_whole_clips(run_dir: Path, name: str, table: pd.DataFrame | None) -> pd.DataFrame | None:
    """`table` (training's whole-clip table, or None) with the rows of the run's checkpoint evaluations
    (`bmimic.eval --whole-clip`) whose iteration and condition training did not evaluate: a whole-clip
    evaluation of a checkpoint after training is the same measurement as one at that iteration during it.
    Only complete evaluations count (the summary, written last, names the iteration)."""
    extra = []
    for summary_path in sorted((run_dir / EVAL_DIR).glob(f"*/{WHOLE_CLIP_DIR}/{WHOLE_CLIP_FILES[-1]}")):
        path = summary_path.parent / CHECKPOINT_WHOLE_CLIP_FILES[name]
        summary = read_json(summary_path)
        iteration = summary.get(ITERATION) if isinstance(summary, dict) else None
        if not isinstance(iteration, int) or isinstance(iteration, bool) or iteration < 0:
            raise AnalysisError(f"{summary_path}: 'iteration' must be an integer >= 0, got {iteration!r}")
        if not path.is_file():
            raise AnalysisError(f"{path}: missing (its evaluation's summary exists)")
        try:
            rows = pd.read_csv(safe_read.regular_file(path, run_dir))
        except Exception as e:  # an unreadable or foreign file is one line naming it
            raise AnalysisError(f"{path}: unreadable csv ({type(e).__name__}: {e})") from e
        if rows.empty:  # a whole_clip_failures.csv of an evaluation where every rollout completed
            continue
        rows.insert(0, ITERATION, iteration)
        if isinstance(summary, dict) and isinstance(summary.get(ENV_STEPS), int):
            rows.insert(1, ENV_STEPS, summary[ENV_STEPS])
        _check_read(path, name, rows, run_dir)
        extra.append(rows)
    if not extra:
        return table
    rows = pd.concat(extra, ignore_index=True)
    if table is not None and len(table):
        done = set(zip(table[ITERATION], table[CONDITION]))
        rows = rows[[key not in done for key in zip(rows[ITERATION], rows[CONDITION])]]
        return pd.concat([table, rows], ignore_index=True)
    return rows
