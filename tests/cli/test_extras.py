"""Every optional extra, when missing, is one line that names it and how to install it (exit status 2,
nothing written), never a traceback; logger=wandb works once wandb is there. A missing package is
played by `sys.modules[name] = None`, which makes its import fail as if it were not installed."""

from __future__ import annotations

import importlib.machinery
import logging
import os
import subprocess
import sys
import tomllib
import types
from pathlib import Path

import pytest

from bmimic.cli.extras import EXTRAS, LAUNCHER_EXTRAS, MissingExtraError, require_extra
from tests.conftest import REPO

CASES = [
    ("bmimic.sim2sim", ["outputs/runs/default/x"], "onnxruntime", "sim2sim"),
    ("bmimic.train", ["-m", "+sweep=gamma", "hydra/launcher=joblib_gpus"], "hydra_plugins.hydra_joblib_launcher",
     "parallel"),
    ("bmimic.train", ["-m", "+sweep=gamma", "hydra/launcher=slurm"], "hydra_plugins.hydra_submitit_launcher", "slurm"),
    ("bmimic.launch", ["list", "+sweep=gamma", "hydra/launcher=slurm"], "hydra_plugins.hydra_submitit_launcher",
     "slurm"),
    ("bmimic.train", ["logger=wandb", "device=cpu"], "wandb", "wandb"),
]


@pytest.mark.parametrize(("module", "args", "blocked", "extra"), CASES, ids=[f"{c[0]}-{c[3]}" for c in CASES])
def test_a_missing_extra_is_one_line_naming_it(tmp_path, module, args, blocked, extra):
    code = (f"import runpy, sys; sys.modules[{blocked!r}] = None; sys.argv = [{module!r}, *{args!r}]; "
            f"runpy.run_module({module!r}, run_name='__main__', alter_sys=True)")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 2, out.stderr[-3000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), out.stderr[-3000:]
    assert f'pip install -e ".[{extra}]"' in lines[0] and "Traceback" not in out.stderr
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_the_extras_are_pyprojects():
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    for extra, pairs in EXTRAS.items():
        names = {d.split(">")[0].split("=")[0].split("<")[0].strip() for d in declared[extra]}
        assert names == {package for _, package in pairs}, extra
    assert set(LAUNCHER_EXTRAS.values()) <= set(EXTRAS)
    launchers = {p.stem for p in (REPO / "conf" / "hydra" / "launcher").glob("*.yaml")}
    assert launchers <= set(LAUNCHER_EXTRAS)


def test_without_the_video_extra_a_video_is_a_gif_and_the_warning_names_the_extra(monkeypatch, caplog):
    from bmimic.render import video_path

    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with caplog.at_level(logging.WARNING, logger="bmimic.render"):
        assert video_path(Path("play.mp4")) == Path("play.gif")
    assert 'pip install -e ".[video]"' in caplog.text and "imageio-ffmpeg not installed" in caplog.text


def test_logger_wandb_logs_through_wandb_once_installed(monkeypatch, tmp_path):
    """With the wandb extra (here a module that records what it is given) the logger's scalars go to a
    W&B run in the run folder, and the run is finished on close."""
    from bmimic.training.logger import RunLogger

    calls = []

    class Run:
        def log(self, values, step):
            calls.append(("log", values, step))

        def finish(self):
            calls.append(("finish",))

    wandb = types.ModuleType("wandb")
    wandb.__spec__ = importlib.machinery.ModuleSpec("wandb", None)
    wandb.init = lambda **kw: calls.append(("init", kw)) or Run()
    monkeypatch.setitem(sys.modules, "wandb", wandb)
    logger = RunLogger("wandb", tmp_path, "my_run", wandb_project="proj", progress_bar=False)
    logger.open()
    logger.writer.add_scalar("Train/mean_reward", 1.5, 7)
    logger.writer.close()
    assert calls == [("init", {"project": "proj", "name": "my_run", "dir": str(tmp_path)}),
                     ("log", {"Train/mean_reward": 1.5}, 7), ("finish",)]


def test_require_extra_names_every_missing_package(monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio", None)
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(MissingExtraError, match=r"play needs the video extra \(imageio, imageio-ffmpeg not installed or not importable\)"):
        require_extra("video", "play")
