"""The type checker over bmimic/ and analysis/ (settings: pyproject.toml [tool.mypy]) finds nothing."""

from __future__ import annotations

import subprocess
import sys

from tests.conftest import REPO


def test_mypy_finds_no_error_in_the_package_and_the_analysis():
    out = subprocess.run([sys.executable, "-m", "mypy"], cwd=REPO, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-2000:]
    assert out.stdout.strip().startswith("Success: no issues found"), out.stdout[-2000:]
