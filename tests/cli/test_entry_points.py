"""The commands' two forms: console scripts (`bmimic-train`, ...; pyproject's [project.scripts]) for
every `python -m` entry point, and neither form imports from the working directory: a run folder
holding a planted module (yaml.py, logging.py, numpy.py) is read, never executed."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import tomllib

import pytest

from tests.conftest import REPO
from tests.test_architecture import ENTRY_POINTS

SCRIPTS = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
PLANTED = ("yaml", "logging", "numpy", "pandas", "omegaconf")
"""Modules every command imports (or its libraries do); planted in the working directory."""


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}


def test_every_entry_point_has_a_console_script():
    modules = {target.split(":")[0] for target in SCRIPTS.values()}
    # A package entry point (sim2sim) is served by one of its modules.
    assert {next((e for e in ENTRY_POINTS if m == e or m.startswith(e + ".")), m) for m in modules} == set(ENTRY_POINTS)
    assert all(name.startswith("bmimic-") for name in SCRIPTS)
    for name, target in SCRIPTS.items():
        module, _, func = target.partition(":")
        assert callable(getattr(importlib.import_module(module), func)), name


def _plant(folder) -> None:
    for name in PLANTED:  # each would leave a marker file, and break the command, if it were imported
        (folder / f"{name}.py").write_text(f"open({str(folder / ('RAN_' + name))!r}, 'w').write('ran')\n")


@pytest.mark.parametrize("argv", [["bmimic.eval", "."], ["analysis.report", "."], ["bmimic.train", "--cfg", "job"],
                                  ["bmimic.launch", "list", "+sweep=gamma", "seed=0"]])
def test_python_m_never_imports_a_module_planted_in_the_working_directory(tmp_path, argv):
    run = tmp_path / "run"
    run.mkdir()
    _plant(run)
    out = subprocess.run([sys.executable, "-m", *argv], cwd=run, env=_env(), capture_output=True, text=True,
                         timeout=300)
    assert sorted(p.name for p in run.glob("RAN_*")) == []
    assert "Traceback" not in out.stderr, out.stderr[-3000:]
    assert out.returncode in (0, 2)  # done, or a one-line refusal: "." is not a run folder


def _console_script(tmp_path, name: str):
    """The launcher pip writes for `name` (an import of its target, then a call), in a bin/ folder:
    run as a file, its own folder is sys.path[0], not the working directory."""
    module, _, func = SCRIPTS[name].partition(":")
    script = tmp_path / "bin" / name
    script.parent.mkdir(exist_ok=True)
    script.write_text(f"import sys\nfrom {module} import {func}\nif __name__ == '__main__':\n    sys.exit({func}())\n")
    return script


def test_the_console_script_runs_where_an_analysis_folder_shadows_python_m(tmp_path):
    work = tmp_path / "work"
    (work / "analysis").mkdir(parents=True)  # the user's own folder of that name
    (work / "analysis" / "__init__.py").write_text("")
    shadowed = subprocess.run([sys.executable, "-m", "analysis.report", "--help"], cwd=work, env=_env(),
                              capture_output=True, text=True, timeout=300)
    assert shadowed.returncode != 0  # python -m finds the user's analysis/ first: why the scripts exist
    script = _console_script(tmp_path, "bmimic-report")
    out = subprocess.run([sys.executable, str(script), "--help"], cwd=work, env=_env(), capture_output=True,
                         text=True, timeout=300)
    assert out.returncode == 0 and "usage:" in out.stdout, out.stderr[-2000:]


def test_bmimic_train_console_script_composes_like_python_m(tmp_path):
    script = _console_script(tmp_path, "bmimic-train")
    forms = [[sys.executable, str(script)], [sys.executable, "-m", "bmimic.train"]]
    outs = [subprocess.run([*form, "--cfg", "job", "sampler=uniform"], cwd=tmp_path, env=_env(),
                           capture_output=True, text=True, timeout=300) for form in forms]
    assert [o.returncode for o in outs] == [0, 0], outs[0].stderr[-2000:]
    assert outs[0].stdout == outs[1].stdout and "name: uniform" in outs[0].stdout
