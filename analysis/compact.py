"""``python -m analysis.compact PATH [PATH ...]``: shrink run folders to what a report reads.

A study's committed runs (docs/results/<study>/runs/) exist so that anyone can rebuild its report;
training writes much more (losses, per-term rewards, timings) for the person watching the run. This
rewrites each run's tables in place, atomically, keeping only REPORT_COLUMNS (the columns the analysis
reads, analysis.run_files) and storing floating-point columns with Parquet's byte-stream-split encoding
under zstd level 19: lossless, so a report rebuilt from the compacted runs is byte-identical, and
about half the size. Rows are never dropped or thinned here (thinning sampler.parquet would change the
sampling figures). Survival tables of whole-clip evaluations go (drop_survival_views): they are a view
of the clips and failures tables, which the analysis derives again, and they are dropped only where that
derivation gives them back exactly. It also makes the run's records portable (portable_records: no path of
the machine it ran on). Run it before committing a study's runs; ``--check`` only prints what it would do.

STUDY_BUDGET_MB is the size a study's folder may take in the repository; STUDY_BUDGETS_MB records the
studies allowed more, each with its reason. tests/test_results_size.py holds every folder of
docs/results to its budget.
"""

from bmimic.cli.startup import leave_working_directory

leave_working_directory(__spec__.name)  # first: under `python -m` (bmimic.cli.startup); no MuJoCo here

import argparse
import io
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import yaml

from analysis import AnalysisError
from analysis.run_files import REPORT_COLUMNS, find_run_dirs
from bmimic.runs import safe_read
from bmimic.runs.atomic_io import atomic_write_bytes
from bmimic.runs.folder import (
    DATA_FOLDER_NAME,
    EVAL_DIR,
    HYDRA_DIR,
    RESOLVED_CONFIG,
    WHOLE_CLIP_DIR,
    WHOLE_CLIP_FILES,
    table_path,
)
from bmimic.runs.schema import (
    CLIP_TIME_S,
    CONDITION,
    ITERATION,
    WHOLE_CLIP_SURVIVAL_COLUMNS,
    whole_clip_survival,
)

STUDY_BUDGET_MB = 10.0
"""Largest size of one study's folder under docs/results (runs, report.md, figures; not the report's CSVs,
which git ignores), in MB."""

STUDY_BUDGETS_MB = {
    "peer_samplers": 16.0,  # 40 runs of 627 bins, committed (and thinned) before compaction existed: 15.1 MB
    "design_choices_dance1": 17.5,  # 30 runs of 132 bins evaluated every 50 iterations: 16.9 MB compacted
    "sensitivity_dance1": 22.5,  # 67 runs (18.4 MB compacted: the 0.25/0.5 s bins carry 4x/2x the bins) + 33 figures (3.4 MB)
    "lafan36_library": 42.5,  # 8 runs of 8,018 bins (eval.parquet ~0.46 MB per evaluation: 2.3-2.9 MB at 2038 iterations,
    # 5.0-5.5 MB for the four jobs continued to 4,604; whole-clip clips and failures CSVs ~0.07 MB per evaluation,
    # their survival views dropped) + the continued jobs' report (1.0 MB): 41.9 MB
    "lafan36_whole": 16.0,  # issue 73's states (4.6 MB per job, the issue allows 10) + each job's record, which grows
    # ~0.5 MB per 500 iterations (one window evaluation of 8,018 bins): 12.2 MB for one job at 4,749 iterations;
    # its history grows by about the new rows per sitting (ROW_GROUP_ITERATIONS)
}
"""Studies allowed more than STUDY_BUDGET_MB, in MB, with why."""

ZSTD_LEVEL = 19
"""zstd level of compacted tables (slow to write, as fast to read as the default)."""

ROW_GROUP_ITERATIONS = 500
"""A table with an iteration column is written in row groups of this many iterations (rows of iterations
[0, 500), [500, 1000), ...). A run continued across sittings (docs/results/lafan36_whole) commits its grown
tables each sitting; its earlier row groups then come out byte-identical, so git stores the new version as
a delta of the old one (the new rows and the last group) instead of another whole file."""


def compact_table(table: pa.Table, keep: tuple[str, ...] | None) -> bytes:
    """``table`` with only the columns of ``keep`` (all when None; absent ones are skipped), as Parquet
    bytes: floats byte-stream-split, everything zstd ``ZSTD_LEVEL``; values unchanged."""
    if keep is not None:
        table = table.select([c for c in table.column_names if c in keep])
    table = table.replace_schema_metadata(None)  # pandas' index metadata: the readers never use it
    floats = [f.name for f in table.schema if pa.types.is_floating(f.type)]
    buf = io.BytesIO()
    with pq.ParquetWriter(buf, table.schema, compression="zstd", compression_level=ZSTD_LEVEL,
                          use_byte_stream_split=floats or False,
                          use_dictionary=[c for c in table.column_names if c not in floats] or False) as writer:
        for start, length in row_groups(table):
            writer.write_table(table.slice(start, length), row_group_size=max(length, 1))
    return buf.getvalue()


def row_groups(table: pa.Table) -> list[tuple[int, int]]:
    """(first row, rows) of each row group: runs of consecutive rows in one ROW_GROUP_ITERATIONS block of
    the iteration column; the whole table in one group where there is no such column (or no rows)."""
    if ITERATION not in table.column_names or table.num_rows == 0:
        return [(0, table.num_rows)]
    block = np.asarray(table.column(ITERATION).to_numpy(zero_copy_only=False)) // ROW_GROUP_ITERATIONS
    starts = np.flatnonzero(np.r_[True, block[1:] != block[:-1]])
    return [(int(a), int(b - a)) for a, b in zip(starts, np.r_[starts[1:], len(block)])]


def compact_run(run_dir: Path, write: bool = True) -> tuple[int, int]:
    """Compact every table of ``run_dir`` that the analysis reads; returns (bytes before, after)."""
    before = after = 0
    for name, keep in REPORT_COLUMNS.items():
        path = table_path(run_dir, name)
        if not path.is_file():
            continue
        try:
            table = pq.read_table(safe_read.regular_file(path, run_dir))  # a FIFO or device would hang pyarrow
        except Exception as e:  # pyarrow raises several types for damaged files
            raise AnalysisError(f"{path}: unreadable parquet ({type(e).__name__}: {e})") from e
        data = compact_table(table, keep)
        if not pq.read_table(io.BytesIO(data)).equals(table.select([c for c in table.column_names
                                                                    if keep is None or c in keep])
                                                       .replace_schema_metadata(None)):
            raise AnalysisError(f"{path}: compacting would change its values; left as it was")
        before, after = before + path.stat().st_size, after + len(data)
        if write and len(data) < path.stat().st_size:
            atomic_write_bytes(path, data)
    return before, after


def _survival_sources(run_dir: Path) -> list[tuple[Path, Path, Path, tuple[str, ...]]]:
    """(survival, clips, failures, keys) of every whole-clip evaluation of ``run_dir`` that stored a survival
    table: training's parquet tables (keyed by iteration) and each checkpoint's eval/<label>/whole_clip/."""
    found: list[tuple[Path, Path, Path, tuple[str, ...]]] = []
    parquet = table_path(run_dir, "whole_clip_survival")
    if parquet.is_file():
        found.append((parquet, table_path(run_dir, "whole_clip"), table_path(run_dir, "whole_clip_failures"),
                      (ITERATION,)))
    for folder in sorted((run_dir / EVAL_DIR).glob(f"*/{WHOLE_CLIP_DIR}")):
        clips, survival, failures = (folder / name for name in WHOLE_CLIP_FILES[:3])
        if survival.is_file():
            found.append((survival, clips, failures, ()))
    return found


def _read(path: Path) -> pd.DataFrame:
    safe_read.regular_file(path)  # a FIFO or device would hang the reader
    return pd.read_csv(path) if path.suffix == ".csv" else pd.read_parquet(path)


def drop_survival_views(run_dir: Path, write: bool = True) -> tuple[int, int]:
    """Delete ``run_dir``'s stored whole-clip survival tables that bmimic.runs.schema.whole_clip_survival
    derives back exactly from the same evaluation's clips and failures tables (every column, every row);
    one that differs, or whose sources are missing or unreadable, stays. Returns (files, bytes) dropped
    (or that would be)."""
    files = size = 0
    for survival_path, clips_path, failures_path, keys in _survival_sources(run_dir):
        columns, order = [*keys, *WHOLE_CLIP_SURVIVAL_COLUMNS], [*keys, CONDITION, "clip", CLIP_TIME_S]
        try:
            stored = _read(survival_path)[columns]
            derived = whole_clip_survival(_read(clips_path), _read(failures_path), keys)[columns]
            pd.testing.assert_frame_equal(stored.sort_values(order, kind="stable").reset_index(drop=True),
                                          derived.sort_values(order, kind="stable").reset_index(drop=True),
                                          check_dtype=False, check_exact=True)
        except Exception:  # missing, damaged or different: the stored view stays, the only record of itself
            continue
        files, size = files + 1, size + survival_path.stat().st_size
        if write:
            survival_path.unlink()
    return files, size




def _data_folder(run_dir: Path) -> str | None:
    """The run's absolute data.lafan_dir from resolved_config.json (None when absent or relative)."""
    try:
        folder = json.loads((run_dir / RESOLVED_CONFIG).read_text()).get("data", {}).get("lafan_dir")
    except (OSError, ValueError, AttributeError):
        return None  # no record (or not one this can read): nothing of it to rewrite
    return folder.rstrip("/") if isinstance(folder, str) and folder.startswith("/") and folder != "/" else None


def _yaml_value(name: str) -> Callable[[re.Match[str]], str]:
    """re.sub's replacement of a folder by `name` in `key: FOLDER[/below]` (the checkout's root: relative paths)."""
    def replace(m: re.Match[str]) -> str:
        return m.group(1) + ("" if name == "." and m.group(2) == "/" else name + m.group(2))
    return replace


def portable_records(run_dir: Path, write: bool = True) -> int:
    """Make ``run_dir``'s records machine-independent; returns how many files it changed (or would).

    Paths under the launch's working directory (Hydra's ``runtime.cwd`` in .hydra/hydra.yaml: the machine's
    copy of the repository) become relative to it in every JSON record (a whole-clip summary's checkpoint
    and run folder, the resolved config's data folder) and in Hydra's config.yaml (whole values); a data
    folder elsewhere (data.lafan_dir) becomes DATA_FOLDER_NAME; and hydra.yaml itself goes: no report reads it, and
    it holds the machine's paths and the launcher's internals. A run without hydra.yaml is left as it is.
    """
    hydra_yaml = run_dir / HYDRA_DIR / "hydra.yaml"
    if not hydra_yaml.is_file():
        return 0
    try:
        cwd = (yaml.safe_load(hydra_yaml.read_text()) or {}).get("hydra", {}).get("runtime", {}).get("cwd")
    except (yaml.YAMLError, AttributeError) as e:
        raise AnalysisError(f"{hydra_yaml}: unreadable ({type(e).__name__}: {e})") from e
    rewritten = {}  # every record read and checked before any is written: a bad one leaves the run as it was
    if isinstance(cwd, str) and cwd.startswith("/"):
        root = cwd.rstrip("/")
        # the clips' folder outside the checkout (data.lafan_dir, e.g. an unpacked archive) becomes the
        # variable that names it: where a reader keeps LAFAN1 is theirs
        data = _data_folder(run_dir)
        replace = [(root, "."), *([(data, DATA_FOLDER_NAME)] if data and not data.startswith(root + "/") else [])]
        for path in sorted(run_dir.rglob("*.json")):
            try:
                text = new = path.read_text()
                # Whole JSON strings only: the folder itself, or the folder and a path below it.
                for folder, name in replace:
                    new = new.replace(json.dumps(folder), json.dumps(name)).replace(
                        json.dumps(folder + "/")[:-1], json.dumps(name + "/")[:-1] if name != "." else '"')
                if new != text:
                    json.loads(new)  # still JSON
                    rewritten[path] = new
            except (OSError, ValueError) as e:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
                raise AnalysisError(f"{path}: unreadable JSON record ({type(e).__name__}); its run's records are left as they were") from e
        # Hydra's composed config holds the same folders as plain YAML scalars (motion.folder resolved)
        config_yaml = run_dir / HYDRA_DIR / "config.yaml"
        if config_yaml.is_file():
            text = new = config_yaml.read_text()
            for folder, name in replace:
                # a whole value only: `key: FOLDER` or `key: FOLDER/below`, never a folder that only starts alike
                new = re.sub(rf"(?m)(:[ \t]+){re.escape(folder)}(/|[ \t]*$)", _yaml_value(name), new)
            if new != text:
                try:
                    yaml.safe_load(new)  # still YAML
                except yaml.YAMLError as e:
                    raise AnalysisError(f"{config_yaml}: not YAML once its paths are rewritten ({type(e).__name__}); "
                                        "its run's records are left as they were") from e
                rewritten[config_yaml] = new
    if write:
        for path, new in rewritten.items():
            atomic_write_bytes(path, new.encode())
        hydra_yaml.unlink()
    return 1 + len(rewritten)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m analysis.compact", description=__doc__.split("\n\n")[0])
    p.add_argument("paths", nargs="+", type=Path, help="run folders, or folders holding them")
    p.add_argument("--check", action="store_true", help="print what it would save; write nothing")
    args = p.parse_args(argv)
    try:
        runs = [r for path in args.paths for r in find_run_dirs(path)]
        if not runs:
            raise AnalysisError(f"no run folders under {[str(x) for x in args.paths]}")
        before = after = records = views = 0
        for run in runs:
            b, a = compact_run(run, write=not args.check)
            n, dropped = drop_survival_views(run, write=not args.check)
            before, after, views = before + b + dropped, after + a, views + n
            records += portable_records(run, write=not args.check)
    except AnalysisError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    verb = "would shrink" if args.check else "shrank"
    print(f"{len(runs)} runs: tables {verb} from {before / 1e6:.2f} MB to {after / 1e6:.2f} MB "
          f"({views} survival views {'would be ' if args.check else ''}dropped: derived again from clips and failures); "
          f"{records} record files {'would be ' if args.check else ''}made free of the machine's paths")
    return 0


if __name__ == "__main__":
    sys.exit(main())
