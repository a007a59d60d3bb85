"""The command line answers before the heavy libraries load: composing a config, `--help`, `--cfg job`
and the sweep dry run import neither torch nor Warp (nor MuJoCo-Warp, nor MuJoCo for the config
alone); the dry run, which validates every job's env terms and sampler checks as the job will, reads
their modules with torch deferred (bmimic.cli.deferred), and never runs it. Their start-up times are a
benchmark (docs/benchmarks.md), not a test; what a test can hold is that the slow imports stay out."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from tests.conftest import REPO

HEAVY = ("torch", "warp", "mujoco_warp", "mujoco", "pandas")


def _run(code: str, cwd) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=300)


def _loaded(out: subprocess.CompletedProcess) -> list[str]:
    assert out.returncode == 0, out.stderr[-3000:]
    return [line.split(" ", 1)[1] for line in out.stdout.splitlines() if line.startswith("LOADED ")]


# A module deferred by bmimic.cli.deferred sits in sys.modules without having run: not loaded.
LOADED = f"[m for m in {HEAVY!r} if m in sys.modules and type(sys.modules[m]).__name__ != 'DeferredModule']"
REPORT = f"import sys; print(*('LOADED ' + m for m in {LOADED}), sep='\\n')"


def test_composing_a_config_imports_neither_torch_nor_warp(tmp_path):
    code = f"""
from hydra import compose, initialize_config_dir
import bmimic, bmimic.config
from bmimic.config.checks import check_composed
for sampler in ("adaptive", "egm", "phc", "uniform"):
    with initialize_config_dir(config_dir=str(bmimic.CONF_DIR), version_base="1.3"):
        cfg = compose("train", overrides=[f"sampler={{sampler}}", "sampler.bin_size_seconds=0.5"])
    check_composed(cfg)
    assert cfg.sampler.kind == sampler and cfg.sampler.bin_size_seconds == 0.5
{REPORT}
"""
    assert _loaded(_run(code, tmp_path)) == []


@pytest.mark.parametrize("argv", [["bmimic.train", "--help"], ["bmimic.train", "--cfg", "job", "sampler=gmt"],
                                  ["bmimic.train", "-m", "+sweep=sampler_ablation", "--cfg", "job"],
                                  ["bmimic.launch", "list", "+sweep=gamma", "seed=0"]])
def test_help_cfg_and_the_dry_run_import_neither_torch_nor_warp(tmp_path, argv):
    # The command runs as `python -m` would run it; what it imported is read at interpreter exit.
    code = f"""
import atexit, runpy, sys
atexit.register(lambda: print(*('LOADED ' + m for m in {LOADED}), sep='\\n'))
sys.argv = {argv!r}
runpy.run_module("{argv[0]}", run_name="__main__", alter_sys=True)
"""
    out = _run(code, tmp_path)
    assert "sampler" in out.stdout or "jobs" in out.stdout, out.stdout[-2000:]
    # The dry run validates every job as the job will, its env terms included (their modules import
    # torch and mujoco, deferred there and never run); the simulator it never needs.
    assert _loaded(out) == []
    assert not (tmp_path / "outputs").exists()  # nothing written by a look at the config


def test_the_sampler_classes_still_register_on_first_use(tmp_path):
    code = f"""
import bmimic.sampling as s
{REPORT}
from bmimic.sampling.config import make_sampler, load_variant
sampler = make_sampler(load_variant("egm"), 4)
assert type(sampler).__name__ == "EGMSampler", type(sampler)
assert set(s.SAMPLERS) >= {{"uniform", "adaptive", "beyondmimic", "egm", "gmt", "phc", "protomotions"}}
print("BUILT", type(s.AdaptiveSampler(3)).__name__)
"""
    out = _run(code, tmp_path)
    assert _loaded(out) == [] and "BUILT AdaptiveSampler" in out.stdout


def test_a_deferred_module_runs_on_first_use_and_is_then_the_module_itself(tmp_path):
    code = """
import sys, types
from bmimic.cli.deferred import defer, is_deferred
defer("colorsys"); defer("email"); defer("no_such_module_anywhere")
import colorsys, email                                  # an import statement binds the stand-in
assert is_deferred("colorsys") and is_deferred("email") and "no_such_module_anywhere" not in sys.modules
assert colorsys.rgb_to_hsv(1.0, 0.0, 0.0) == (0.0, 1.0, 1.0)   # the first use runs it
assert not is_deferred("colorsys") and type(sys.modules["colorsys"]) is types.ModuleType
import email.utils                                      # a submodule of a deferred package
assert email.utils.parseaddr("a <b@c.d>") == ("a", "b@c.d") and sys.modules["email"] is email
print("OK")
"""
    out = _run(code, tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == "OK", out.stderr[-2000:]


def test_a_global_bound_on_first_use_becomes_the_module_itself(tmp_path):
    code = """
import sys, json
from bmimic.cli.deferred import import_on_first_use
ns = {}
ns["colorsys"] = import_on_first_use("colorsys", ns)
assert "colorsys" not in sys.modules                    # bound, not imported
assert ns["colorsys"].rgb_to_hsv(1.0, 0.0, 0.0) == (0.0, 1.0, 1.0)   # the first read imports it
assert ns["colorsys"] is sys.modules["colorsys"]        # and the global is the module from then on
assert import_on_first_use("json", {}) is json          # imported already: the module itself
print("OK")
"""
    out = _run(code, tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == "OK", out.stderr[-2000:]


def test_a_sampler_module_imports_without_torch_and_holds_torch_once_a_sampler_is_built(tmp_path):
    # The schema and the class of a sampler share one module; composing a config imports it, so its torch
    # is bound on first use, and by the time a step could be compiled the globals are torch itself.
    code = """
import sys, types
import bmimic.sampling.base as base, bmimic.sampling.samplers as samplers, bmimic.sampling.peer_errors as peer
assert "torch" not in sys.modules and not isinstance(samplers.torch, types.ModuleType)
from bmimic.sampling.config import make_sampler, load_variant
for kind in ("adaptive", "egm"):
    make_sampler(load_variant(kind), 4).sample(3)
import torch
assert base.torch is torch and samplers.torch is torch and peer.torch is torch
print("OK")
"""
    out = _run(code, tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == "OK", out.stderr[-2000:]
