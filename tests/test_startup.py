"""Importing bmimic changes nothing; its commands protect themselves (bmimic.cli.startup).

Importing the package root, the run-folder module or the analysis leaves sys.path as it was and imports
no MuJoCo, even inside another program's `python -m` start-up with a broken MUJOCO_GL (the root used
to take the working directory off sys.path and exit there). The commands themselves, whose first
statement is bmimic.cli.startup's, never import a module planted in the working directory, the
standard-library names that `python -m` has not loaded yet included (the ones tests/cli/test_entry_points.py
plants are third-party or `logging`)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bmimic.cli import startup
from tests.conftest import REPO


def _env(**extra: str) -> dict:
    # No empty PYTHONPATH entry: it would put the working directory on sys.path before site's .pth files
    # run (an editable install's imports `__future__`), before any code of bmimic's.
    path = [str(REPO), *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p)]
    return {**os.environ, "PYTHONPATH": os.pathsep.join(path), **extra}


def test_importing_bmimic_and_the_analysis_has_no_side_effect(tmp_path):
    # Another program's package imports them in its __init__ and is run with `python -m` from its folder.
    (tmp_path / "userpkg").mkdir()
    (tmp_path / "userpkg" / "__init__.py").write_text(
        "import sys\nBEFORE = list(sys.path)\nimport bmimic, bmimic.runs.folder, analysis  # noqa\n")
    (tmp_path / "userpkg" / "tool.py").write_text(
        "import sys\nfrom userpkg import BEFORE\n"
        "print('path unchanged' if sys.path == BEFORE else f'path changed: {BEFORE} -> {sys.path}')\n"
        "print('mujoco imported' if 'mujoco' in sys.modules else 'no mujoco')\n")
    out = subprocess.run([sys.executable, "-m", "userpkg.tool"], cwd=tmp_path, capture_output=True, text=True,
                         env=_env(MUJOCO_GL="no-such-backend"), timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split("\n")[:2] == ["path unchanged", "no mujoco"], out.stdout


@pytest.mark.parametrize("orig_argv, module", [
    (["python", "-m", "bmimic.train", "-m", "x"], "bmimic.train"),
    (["python", "-X", "dev", "-W", "ignore", "-mbmimic.eval", "."], "bmimic.eval"),
    (["python", "-Im", "analysis.report"], "analysis.report"),
    (["python", "--check-hash-based-pycs", "never", "-m", "bmimic.sim2sim"], "bmimic.sim2sim"),
    (["python", "-c", "import bmimic", "-m", "bmimic.train"], None),
    (["python", "script.py", "-m", "bmimic.train"], None),
    (["bmimic-train", "--help"], None),
])
def test_the_python_m_module_is_read_from_the_command_line(monkeypatch, orig_argv, module):
    monkeypatch.setattr(sys, "orig_argv", orig_argv)
    assert startup.python_m_module() == module


PLANTED = ("__future__", "typing", "pathlib", "yaml", "numpy")
"""Imported by the packages a `python -m` entry point lives in, or by the entry point, before anything else."""


@pytest.mark.parametrize("module", ["bmimic.motion.convert", "bmimic.sim2sim", "analysis.report", "bmimic.launch"])
def test_python_m_never_imports_a_planted_standard_module(tmp_path, module):
    for name in PLANTED:  # each would leave a marker file if it were imported
        (tmp_path / f"{name}.py").write_text(f"open({str(tmp_path / ('RAN_' + name))!r}, 'w').write('ran')\n")
    out = subprocess.run([sys.executable, "-m", module, "--help"], cwd=tmp_path, capture_output=True, text=True,
                         env=_env(), timeout=300)
    assert sorted(p.name for p in tmp_path.glob("RAN_*")) == []
    assert out.returncode == 0 and "usage" in out.stdout.lower(), out.stderr[-3000:]


def test_checkout_root_is_the_folder_that_holds_bmimic():
    assert startup.checkout_root() == os.path.realpath(REPO)
    assert os.path.isfile(os.path.join(startup.checkout_root(), "bmimic", "__init__.py"))


@pytest.mark.parametrize("in_checkout", [True, False])
def test_python_m_keeps_the_checkout_root_on_sys_path(monkeypatch, tmp_path, in_checkout):
    # On a machine where bmimic is not installed (a copy of the tree, PYTHONPATH at its root), a command
    # run from the checkout's root must still find the analysis package beside bmimic (the sweep index
    # callback): 5fca5e6 looked for the root one folder too deep and took it off sys.path.
    cwd = os.path.realpath(REPO) if in_checkout else os.path.realpath(tmp_path)
    monkeypatch.chdir(cwd)
    monkeypatch.setattr(sys, "orig_argv", ["python", "-m", "bmimic.train"])
    monkeypatch.setattr(sys, "path", [cwd, "/elsewhere", cwd])
    startup.leave_working_directory("bmimic.train")
    assert sys.path == ([cwd, "/elsewhere", cwd] if in_checkout else ["/elsewhere"])
