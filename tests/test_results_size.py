"""The repository stays small: every study under docs/results keeps to its size budget
(analysis.compact), and committed runs hold only what a report reads."""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest

from analysis.compact import STUDY_BUDGET_MB, STUDY_BUDGETS_MB
from analysis.run_files import REPORT_COLUMNS, find_run_dirs
from bmimic.runs.folder import table_path
from tests.conftest import REPO

RESULTS = REPO / "docs" / "results"
STUDIES = sorted(p for p in RESULTS.iterdir() if p.is_dir())


def tracked_size_mb(folder) -> float:
    """Size of the files git keeps, as .gitignore says: the report's CSVs are ignored (docs/results/**/*.csv),
    the runs' whole-clip evaluations (runs/**/eval/*/whole_clip/*.csv) are kept."""
    def kept(f) -> bool:
        return f.suffix != ".csv" or ("runs" in f.relative_to(folder).parts and f.parent.name == "whole_clip")
    return sum(f.stat().st_size for f in folder.rglob("*") if f.is_file() and kept(f)) / 1e6


@pytest.mark.parametrize("study", STUDIES, ids=lambda p: p.name)
def test_study_keeps_to_its_budget(study):
    budget = STUDY_BUDGETS_MB.get(study.name, STUDY_BUDGET_MB)
    assert tracked_size_mb(study) <= budget, f"{study.name}: over its {budget} MB budget (python -m analysis.compact)"


def test_budgets_name_real_studies():
    assert set(STUDY_BUDGETS_MB) <= {p.name for p in STUDIES} | {"sensitivity_dance1"}


@pytest.mark.parametrize("study", [s for s in STUDIES if (s / "runs").is_dir()], ids=lambda p: p.name)
def test_committed_runs_hold_only_report_columns(study):
    for run in find_run_dirs(study / "runs"):
        for name, keep in REPORT_COLUMNS.items():
            path = table_path(run, name)
            if keep is not None and path.is_file():
                extra = set(pq.read_schema(path).names) - set(keep)
                assert not extra, f"{path}: columns no report reads {sorted(extra)} (python -m analysis.compact)"


def _strings(value):
    if isinstance(value, dict):
        for v in value.values():
            yield from _strings(v)
    elif isinstance(value, list):
        for v in value:
            yield from _strings(v)
    elif isinstance(value, str):
        yield value


@pytest.mark.parametrize("study", [s for s in STUDIES if (s / "runs").is_dir()], ids=lambda p: p.name)
def test_committed_records_hold_no_path_of_the_machine_they_ran_on(study):
    import json

    for run in find_run_dirs(study / "runs"):
        assert not (run / ".hydra" / "hydra.yaml").exists(), f"{run}: hydra.yaml (python -m analysis.compact)"
        for path in run.rglob("*.json"):
            absolute = [s for s in _strings(json.loads(path.read_text())) if s.startswith("/")]
            assert not absolute, f"{path}: absolute paths {absolute[:2]} (python -m analysis.compact)"
