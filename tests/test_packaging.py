"""A regular install works from any directory: the wheel carries the config tree and the sweeps.

The wheel is built from a clean copy of the checkout and installed, without its dependencies, into a
fresh virtual environment in a temporary folder; the dependencies come from this environment's
site-packages through a .pth file (paths only: this environment's own .pth hooks, such as an
editable install of bmimic, are not run), so torch is not installed again.
"""

from __future__ import annotations

import os
import shutil
import site
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from tests.conftest import REPO

pytestmark = pytest.mark.slow

NOT_SOURCE = ("build", "dist", "*.egg-info", ".git", "outputs", "__pycache__", ".pytest_cache", ".ruff_cache",
              ".hypothesis", ".venv", "venv")


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, Path]:
    """(python of a fresh venv with the wheel installed, an empty folder to run it in)."""
    root = tmp_path_factory.mktemp("wheel")
    src = root / "src"
    shutil.copytree(REPO, src, symlinks=True, ignore=shutil.ignore_patterns(*NOT_SOURCE))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(root / "dist"),
                            str(src)], capture_output=True, text=True, timeout=600, env=env)
    assert built.returncode == 0, built.stderr[-3000:]
    (wheel,) = (root / "dist").glob("bmimic-*.whl")

    venv = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=300)
    python = venv / "bin" / "python"
    purelib = subprocess.run([str(python), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    inst = subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--no-index", "-q", "--target",
                           purelib, str(wheel)], capture_output=True, text=True, timeout=600, env=env)
    assert inst.returncode == 0, inst.stderr[-3000:]
    Path(purelib, "_bmimic_test_deps.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    elsewhere = root / "elsewhere"
    elsewhere.mkdir()
    return python, elsewhere


def run(installed, *args: str) -> subprocess.CompletedProcess:
    python, cwd = installed
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    out = subprocess.run([str(python), *args], cwd=cwd, capture_output=True, text=True, timeout=600, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    return out


def test_the_wheel_is_what_runs(installed):
    where = run(installed, "-c", "import bmimic; print(bmimic.__file__); print(bmimic.CONF_DIR)").stdout.split()
    venv = installed[0].parent.parent
    assert all(Path(p).is_relative_to(venv) for p in where), where  # not the checkout
    conf = Path(where[1])
    assert (conf / "train.yaml").is_file() and not conf.is_symlink()
    assert sorted(p.name for p in (conf / "sweep").glob("*.yaml")) == sorted(p.name for p in (REPO / "sweeps").glob("*.yaml"))


def test_cfg_job_from_any_directory(installed):
    cfg = OmegaConf.create(run(installed, "-m", "bmimic.train", "--cfg", "job", "sampler=uniform").stdout)
    assert cfg.sampler.name == "uniform" and cfg.motion.name == "graded"


def test_help_from_any_directory(installed):
    text = run(installed, "-m", "bmimic.train", "--help").stdout
    assert "motion: builtin_library, default*, easy_only, file, lafan_dance1" in text and "_schema" not in text


def test_a_sweep_composes_from_any_directory(installed):
    out = run(installed, "-m", "bmimic.train", "-m", "+sweep=sampler_ablation", "--cfg", "job").stdout
    assert out.startswith("# -m: 10 jobs")
    cfg = OmegaConf.create(out)
    assert cfg.sweep_name == "sampler_ablation" and cfg.max_iterations == 10000 and cfg.sampler.name == "uniform"


def test_console_scripts_are_installed_and_not_shadowed_by_the_working_directory(installed):
    """pip's launchers import their target with the script's folder, not the working directory, first
    on sys.path (`python -I` runs the same way); a user's `analysis/` folder there shadows nothing."""
    (installed[1] / "analysis").mkdir(exist_ok=True)
    (installed[1] / "analysis" / "__init__.py").write_text("raise SystemExit('the user folder was imported')\n")
    names = run(installed, "-I", "-c", "from importlib.metadata import entry_points; "
                "print(*sorted(e.name for e in entry_points(group='console_scripts') if e.name.startswith('bmimic-')))")
    assert {"bmimic-train", "bmimic-report", "bmimic-eval", "bmimic-launch"} <= set(names.stdout.split())
    for argv in (["bmimic-train", "--cfg", "job", "sampler=uniform"], ["bmimic-report", "--help"]):
        code = ("import sys; from importlib.metadata import entry_points; "
                f"ep = entry_points(group='console_scripts')[{argv[0]!r}]; sys.argv = {argv!r}; sys.exit(ep.load()())")
        out = run(installed, "-I", "-c", code)
        assert ("name: uniform" in out.stdout) if argv[0] == "bmimic-train" else ("usage:" in out.stdout)
