"""What a newcomer sees: `--help`, a quiet console with one start-up summary, one-line GL errors."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys

import pytest

from bmimic import render
from bmimic.cli.help_text import field_docs
from bmimic.config import TrainConfig
from tests.conftest import TINY, cli_env

GROUPS = ("robot", "motion", "sampler", "ppo", "sim", "env", "eval")


def _run(*args: str, env: dict | None = None, cwd=None, merge: bool = False) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, *args], capture_output=not merge, text=True, timeout=900, cwd=cwd,
                          env={**cli_env(), **(env or {})},
                          **({"stdout": subprocess.PIPE, "stderr": subprocess.STDOUT} if merge else {}))


# --------------------------------------------------------------------------------------------- --help
@dataclasses.dataclass
class _Documented:
    speed_mps: float = 1.0
    """How fast, in metres
    per second."""
    undocumented: int = 0
    name: str = "x"
    """A name."""


def test_field_docs_known_answer():
    assert field_docs(_Documented) == {"speed_mps": "How fast, in metres per second.", "name": "A name."}


@pytest.mark.slow
def test_help_lists_options_and_documented_keys():
    # The option lists wrap at the terminal's width (60-110 columns; COLUMNS under pytest-xdist is the
    # worker's): at the widest, each group's options a reader looks for share a line.
    out = _run("-m", "bmimic.train", "--help", "sampler=uniform", env={"COLUMNS": "110"})
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout
    assert "_schema" not in text and "== Config ==" not in text  # no schemas, no config dump
    lines = text.splitlines()
    for group in GROUPS:
        options = [line for line in lines if line.startswith(f"{group}: ")]
        assert len(options) == 1, group
    assert "uniform*" in text and "adaptive," in text  # the current choice is starred
    assert re.search(r"^motion: .*lafan_dance1, lafan_dance1_full", text, flags=re.M)
    assert re.search(r"^\+sweep: [^=]*sampler_ablation", text, flags=re.M)  # the list may wrap
    docs = field_docs(TrainConfig)
    keys = [f.name for f in dataclasses.fields(TrainConfig) if f.name not in (*GROUPS, "defaults", "data")]
    for key in keys:
        (i,) = [n for n, line in enumerate(lines) if line.startswith(f"{key}=")]
        assert lines[i + 1].strip() and lines[i + 1].split()[0] == docs[key].split()[0], key  # its doc follows
    assert "seed=0" in lines and "    Derives every random stream: torch, numpy, python, warp and the motion" in text
    assert any(line.startswith("data.lafan_dir=") for line in lines) and "BMIMIC_LAFAN_DIR" in text


# --------------------------------------------------------------------------------------------- console
@pytest.mark.slow
def test_console_is_one_summary_then_iteration_lines_off_a_terminal(tmp_path):
    args = [a for a in TINY if a != "progress_bar=false"] + ["logger=none"]
    quiet = _run("-m", "bmimic.train", *args, f"hydra.run.dir={tmp_path / 'quiet'}", cwd=tmp_path, merge=True)
    assert quiet.returncode == 0, quiet.stdout[-3000:]
    text = quiet.stdout
    for noise in ("Module ", "Warp ", "Actor Model", "MLPModel", "Resolved observation sets", "[INFO]", "found in sys"):
        assert noise not in text, noise
    assert text.count("\n  run folder  ") == 1
    for row in ("device      cpu (requested cpu)", "envs        2", "iterations  2 of 8 steps per env",
                "motion      easy_only: built-in easy_only; 10.0 s at 50 Hz", "bins        10 time bins of 1 s over 10 s",
                "sampler     adaptive", f"run folder  {tmp_path / 'quiet'}"):
        assert f"\n  {row}\n" in text, row
    # Captured output is no terminal: lines, not tqdm's carriage-return frames (test_output: the bar on a tty).
    assert text.index("run folder") < text.index("iteration 1/2: ") < text.index("iteration 2/2: ")
    assert text.index("iteration 2/2: ") < text.index("done: 2 iterations") and "\r" not in text
    # train.log keeps the timestamps the console leaves out
    assert re.match(r"\[\d{4}-\d\d-\d\d ", (tmp_path / "quiet" / "train.log").read_text())

    loud = _run("-m", "bmimic.train", *TINY, "logger=none", "verbose=true", f"hydra.run.dir={tmp_path / 'loud'}",
                cwd=tmp_path, merge=True)
    assert loud.returncode == 0, loud.stdout[-3000:]
    assert "Actor Model" in loud.stdout and "Warp " in loud.stdout


@pytest.mark.slow
def test_module_entry_points_run_without_a_runpy_warning():
    out = _run("-m", "bmimic.motion.convert", "--help")
    assert out.returncode == 0 and "found in sys.modules" not in out.stderr, out.stderr


@pytest.mark.slow
def test_missing_gl_library_is_one_line_naming_what_to_install(tmp_path):
    if render.probe_gl_backend("osmesa") is None:
        pytest.skip("OSMesa works on this machine; the message is for machines without it")
    for command in (["-m", "bmimic.train", "--cfg", "job"], ["-m", "bmimic.play", str(tmp_path)]):
        out = _run(*command, env={"MUJOCO_GL": "osmesa"})
        assert out.returncode == 2, out.stderr[-2000:]
        assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1, out.stderr
        assert out.stderr.startswith("error: MUJOCO_GL=osmesa: ") and "apt install libosmesa6" in out.stderr
