"""A run or sweep that would train for days on a CPU is refused before it starts: one line with the
estimate and the overrides that make it a smoke run or accept it; nothing is written."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from types import SimpleNamespace

import pytest

from bmimic.config.budget import (
    CPU_S_PER_ENV_STEP,
    CPU_S_PER_STEP,
    BudgetError,
    check_cpu_budget,
    check_sweep,
    cpu_training_s,
)
from tests.cli.test_sweeps import hydra_config_restored  # noqa: F401  (a fixture)
from tests.conftest import REPO, TINY, run_train


def _cfg(num_envs=8, steps=24, iterations=10000, time_limit_s=None):
    return SimpleNamespace(num_envs=num_envs, max_iterations=iterations, time_limit_s=time_limit_s,
                           ppo=SimpleNamespace(num_steps_per_env=steps))


def test_the_estimate_is_steps_at_the_measured_cpu_costs():
    step_s = CPU_S_PER_STEP + 8 * CPU_S_PER_ENV_STEP
    assert cpu_training_s(_cfg()) == pytest.approx(10000 * 24 * step_s)
    assert cpu_training_s(_cfg(), done_iterations=9000) == pytest.approx(1000 * 24 * step_s)
    assert cpu_training_s(_cfg(num_envs=64)) > 4 * cpu_training_s(_cfg())  # per-env cost dominates
    assert cpu_training_s(_cfg(), done_iterations=20000) == 0.0
    assert cpu_training_s(_cfg(time_limit_s=60.0)) == 60.0  # training stops there


def test_the_refusal_gives_the_estimate_and_both_ways_on():
    seconds = 29.6 * 3600
    with pytest.raises(BudgetError) as e:
        check_cpu_budget([seconds], 1.0, "10000 iterations x 8 envs x 24 steps")
    msg = str(e.value)
    assert "\n" not in msg and "about 30 h" in msg and "max_iterations=4" in msg and "max_cpu_hours=30" in msg
    check_cpu_budget([seconds], 30.0, "")  # what the message offers is accepted
    check_cpu_budget([seconds], None, "")  # null: no limit
    with pytest.raises(BudgetError, match="this sweep's 10 jobs, one after another, would train for about 6.0 h.*max_cpu_hours=6 "):
        check_cpu_budget([2160.0] * 10, 1.0, "")  # 36 min each: the sum counts


def _cli(tmp_path, *args):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "bmimic.train", *args], cwd=tmp_path, env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.mark.parametrize("args", [["max_iterations=10000"], ["-m", "+sweep=sampler_ablation", "seed=0"]],
                         ids=["run", "sweep"])
def test_a_study_on_a_cpu_is_refused_before_anything_is_written(tmp_path, args):
    out = _cli(tmp_path, *args, "device=cpu")
    assert out.returncode == 2, out.stderr[-3000:]
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "on this CPU" in lines[0], out.stderr[-3000:]
    assert "max_iterations=4" in lines[0] and "max_cpu_hours=" in lines[0]
    assert list(tmp_path.iterdir()) == []


def _jobs(*overrides):
    from bmimic.sweeping.jobs import list_jobs

    return list_jobs(["+sweep=sampler_ablation", "seed=0", *overrides])[1]


def test_a_gpu_sweep_is_not_limited(monkeypatch, hydra_config_restored):  # noqa: F811
    import bmimic.runtime

    jobs = _jobs()
    monkeypatch.setattr(bmimic.runtime, "resolve_device", lambda device: "cuda:0")
    check_sweep(jobs)  # 2 jobs of 10000 iterations: a GPU study, no refusal


def test_a_sweep_within_the_limit_starts(monkeypatch, hydra_config_restored):  # noqa: F811
    import bmimic.runtime

    monkeypatch.setattr(bmimic.runtime, "resolve_device", lambda device: "cpu")
    check_sweep(_jobs("max_iterations=4"))  # the README's CPU smoke sweep
    with pytest.raises(BudgetError, match="this sweep's 2 jobs"):
        check_sweep(_jobs("max_iterations=5000"))  # 2 x 51 min
    done = [dataclasses.replace(j, status="done") for j in _jobs("max_iterations=5000")]
    check_sweep(done)  # jobs already done train nothing


def test_a_time_limit_caps_the_estimate_and_the_run_trains(tmp_path):
    code, out = run_train(*TINY, "max_iterations=100000", "time_limit_s=1", "logger=none",
                          f"hydra.run.dir={tmp_path / 'run'}")
    assert code == 0, out[-3000:]
    assert (tmp_path / "run" / "metrics.json").exists()


def test_the_dry_runs_device_guess_is_cpu_where_no_gpu_shows(monkeypatch):
    """launch list's torch-free guess: what it names stays, auto is the CPU where every GPU is hidden."""
    from bmimic.runtime import guess_device

    assert guess_device("cpu") == "cpu" and guess_device("cuda:1") == "cuda:1"
    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "")
    assert guess_device("auto") == "cpu"
