"""What a newcomer sees: a quiet console with one start-up summary, one-line GL errors."""

from __future__ import annotations

import re
import subprocess
import sys

import pytest

from bmimic import render
from tests.conftest import TINY, cli_env


def _run(*args: str, env: dict | None = None, cwd=None, merge: bool = False) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=not merge, text=True, timeout=900, cwd=cwd,
                          env={**cli_env(), **(env or {})},
                          **({"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT} if merge else {}))


# --------------------------------------------------------------------------------------------- console
@pytest.mark.slow
def test_console_is_one_summary_then_the_progress_bar(tmp_path):
    args = [a for a in TINY if a != "progress_bar=false"] + ["logger=none"]
    quiet = _run("-m", "bmimic.train", *args, f"hydra.run.dir={tmp_path / 'quiet'}", cwd=tmp_path, merge=True)
    assert quiet.returncode == 0, quiet.stdout[-3000:]
    text = quiet.stdout
    for noise in ("Module ", "Warp ", "Actor Model", "MLPModel", "Resolved observation sets", "[INFO]", "found in sys"):
        assert noise not in text, noise
    assert text.count("\n  run folder  ") == 1
    for row in ("device      cpu (requested cpu)", "envs        2", "iterations  2 of 8 steps per env",
                "motion      easy_only: built-in easy_only; 10.0 s at 50 Hz", "bins        10 of 1 s",
                "sampler     adaptive", f"run folder  {tmp_path / 'quiet'}"):
        assert f"\n  {row}\n" in text, row
    assert text.index("run folder") < text.index("train:") < text.index("done: 2 iterations")  # then the bar
    # train.log keeps the timestamps the console leaves out
    assert re.match(r"\[\d{4}-\d\d-\d\d ", (tmp_path / "quiet" / "train.log").read_text())

    loud = _run("-m", "bmimic.train", *TINY, "logger=none", "verbose=true", f"hydra.run.dir={tmp_path / 'loud'}",
                cwd=tmp_path, merge=True)
    assert loud.returncode == 0, loud.stdout[-3000:]
    assert "Actor Model" in loud.stdout and "Warp " in loud.stdout


def test_module_entry_points_run_without_a_runpy_warning():
    out = _run("-m", "bmimic.motion.convert", "--help")
    assert out.returncode == 0 and "found in sys.modules" not in out.stderr, out.stderr


def test_missing_gl_library_is_one_line_naming_what_to_install(tmp_path):
    if render.probe_gl_backend("osmesa") is None:
        pytest.skip("OSMesa works on this machine; the message is for machines without it")
    for command in (["-m", "bmimic.train", "--cfg", "job"], ["-m", "bmimic.play", str(tmp_path)]):
        out = _run(*command, env={"MUJOCO_GL": "osmesa"})
        assert out.returncode == 2, out.stderr[-2000:]
        assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
        assert out.stderr.startswith("error: MUJOCO_GL=osmesa: ") and "apt install libosmesa6" in out.stderr
