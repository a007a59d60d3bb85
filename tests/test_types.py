"""The type checker over bmimic/ and analysis/ (settings: pyproject.toml [tool.mypy]) finds nothing."""

from __future__ import annotations

import subprocess
import sys

from tests.conftest import REPO


def test_mypy_finds_no_error_in_the_package_and_the_analysis():
    out = subprocess.run([sys.executable, "-m", "mypy"], cwd=REPO, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stdout[-6000:] + out.stderr[-2000:]
    assert out.stdout.strip().startswith("Success: no issues found"), out.stdout[-2000:]


def test_the_placed_config_is_read_through_its_schema(tmp_path):
    # What train, eval and bench build from (bmimic.config.placed): the values resolve_runtime filled
    # in read as ints, and a key the schema lacks is a type error before anything runs.
    code = tmp_path / "reads_the_config.py"
    code.write_text(
        "from bmimic.config import placed\n\n\n"
        "def f(cfg) -> None:\n"
        "    run = placed(cfg)\n"
        "    envs: int = run.num_envs\n"
        "    rollouts: int = run.eval.whole_clip.rollouts\n"
        "    print(envs, rollouts, run.sim.max_abs_qvl)\n", encoding="utf-8")
    out = subprocess.run([sys.executable, "-m", "mypy", "--cache-dir", str(tmp_path / "cache"), str(code)],
                         cwd=REPO, capture_output=True, text=True, timeout=900)
    assert out.returncode == 1, out.stdout[-2000:] + out.stderr[-2000:]
    assert '8: error: "SimConfig" has no attribute "max_abs_qvl"' in out.stdout, out.stdout[-2000:]
    assert "Found 1 error in 1 file" in out.stdout, out.stdout[-2000:]
