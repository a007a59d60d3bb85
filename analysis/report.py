"""``python -m analysis.report PATH [PATH ...]``: figures, CSV tables and report.md for a sweep.

PATH is a sweep folder, a run folder, or any folder holding run folders (e.g. a study's committed
``docs/results/<study>/runs/``). The report goes to ``--out``, else ``<PATH>/report/`` for one
PATH, else ``report/`` in the folder the paths share. Failed, missing and unfinished jobs are
listed, never fatal; running jobs with tables are included and marked. See analysis.metrics for the
definitions and analysis.stats for the statistics the report uses.

Machine-readable outputs: ``summary.csv`` (tables.SUMMARY_COLUMNS), ``speedup.csv``
(tables.SPEEDUP_COLUMNS), ``speedup_curve.csv`` and ``iso_failure.csv`` (analysis.speedup_curve),
``baseline_comparisons.csv`` (with Holm's adjusted p), ``sampling_support.csv`` (analysis.adaptation),
plus per-seed and per-bin tables beside them.
"""

from bmimic.cli.startup import leave_working_directory

leave_working_directory(__spec__.name)  # first: under `python -m` (bmimic.cli.startup); no MuJoCo here

import argparse
import os
import sys
from pathlib import Path

from analysis import REFUSED, AnalysisError, error_line, tables
from analysis.files import write_csv, write_text
from analysis.inputs import MIXED_FLAG, check_options
from analysis.report_compute import compute, read_runs
from analysis.report_files import write_files
from analysis.report_views import REPORT_TITLE, body, header, schedule_section
from analysis.tables import ReportOptions
from bmimic.cli.common import path_arg
from bmimic.runs import safe_read
from bmimic.runs.atomic_io import staged_folder


def default_out(paths: list[Path]) -> Path:
    """Where the report goes without --out: beside the runs (``<sweep>/report``)."""
    if len(paths) == 1:
        return paths[0] / "report"
    return Path(os.path.commonpath([str(p.resolve()) for p in paths])) / "report"


def build_report(paths, out: str | Path | None = None, opts: ReportOptions | None = None,
                 allow_mixed: bool = False) -> Path:
    """Load the runs under ``paths``, write every figure, table and report.md to ``out``; return ``out``.
    ``allow_mixed``: compare runs of different motions, bin layouts or budgets (else refused). The numbers are
    analysis.report_compute's, the files analysis.report_files', the words analysis.report_views'."""
    opts = opts or ReportOptions()
    paths = [Path(p) for p in ([paths] if isinstance(paths, str | Path) else paths)]
    out = Path(out) if out is not None else default_out(paths)
    if out.exists() and not out.is_dir():
        raise AnalysisError(f"--out {out}: is a file, not a folder")
    for name, ours in (("report.md", REPORT_TITLE), ("runs.csv", "run_dir,")):  # never a user's file of that name
        if (out / name).exists() or (out / name).is_symlink():
            try:
                text = safe_read.read_text(out / name)
            except (OSError, ValueError):
                text = ""
            if not text.startswith(ours):
                raise AnalysisError(f"--out {out}: its {name} is not a bmimic report's; choose another folder")
    r = read_runs(paths, opts, allow_mixed)
    # Every table is read (and checked) before the first file is written: a refused report writes nothing.
    data = compute(r.runs, r.opts) if r.runs["included"].any() else None
    with staged_folder(out) as stage:  # a write that fails (a full disk) leaves `out` as it was
        write_csv(stage / "runs.csv", r.runs)
        md = header(paths, r)
        if data is None:
            md += ["No run has usable tables yet; nothing else to report."]
        else:
            md += schedule_section(r.runs, data.inputs.final_iteration) + body(data, write_files(data, stage), r.coverage)
        write_text(stage / "report.md", "\n".join(md) + "\n")
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m analysis.report", description=__doc__.splitlines()[0])
    parser.add_argument("paths", nargs="+", type=path_arg, help="sweep folder, run folder(s), or folders holding runs")
    parser.add_argument("--out", type=path_arg, default=None, help="report folder (default: <PATH>/report)")
    parser.add_argument("--mastery-threshold", type=float, default=0.1, help="bin mastered when failure < this")
    parser.add_argument("--mastery-persist", type=int, default=2,
                        help="consecutive evaluations a bin must stay mastered (or to the end of the run)")
    parser.add_argument("--success-threshold", type=float, default=0.9, help="overall success for time to threshold")
    parser.add_argument("--baseline", default=None, help="baseline arm (default: the arm whose sampler is uniform)")
    parser.add_argument("--resamples", type=int, default=tables.DEFAULT_RESAMPLES, help="bootstrap resamples")
    parser.add_argument("--max-iteration", type=int, default=None,
                        help="read every run only up to this many iterations (a common budget for runs that went "
                             "further)")
    parser.add_argument(MIXED_FLAG, action="store_true",
                        help="compare runs trained on different motions, bin layouts or budgets (max_iterations, "
                             "num_envs, time_limit_s; refused without it: per-bin tables match bins by number, "
                             "and a smoke run is not a study's seed)")
    args = parser.parse_args(argv)
    try:
        check_options(args.mastery_threshold, args.success_threshold, args.resamples, args.mastery_persist)
        if args.max_iteration is not None and args.max_iteration < 1:
            raise AnalysisError(f"--max-iteration must be >= 1, got {args.max_iteration}")
        opts = ReportOptions(mastery_threshold=args.mastery_threshold, mastery_persist=args.mastery_persist,
                             success_threshold=args.success_threshold, baseline=args.baseline,
                             n_resamples=args.resamples, max_iteration=args.max_iteration)
        out = build_report(args.paths, args.out, opts, allow_mixed=args.allow_mixed)
    except REFUSED as e:
        print(error_line(e), file=sys.stderr)
        return 2
    print(f"report written to {out / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
