"""sweeps/lafan36_library_job.sh, one job of the 36-clip library study (issue 45) trained sitting by sitting:
its command composes to the study's job, a job with a checkpoint continues for TRAIN_S more seconds of
training, and bad input is one line with exit status 2 that starts nothing."""

from __future__ import annotations

import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.conftest import REPO, compose

JOB = REPO / "sweeps" / "lafan36_library_job.sh"


def _job(*args: str, **env: str) -> subprocess.CompletedProcess:
    path = f"{Path(sys.executable).parent}:/usr/bin:/bin"  # the python of this environment (torch) first
    return subprocess.run(["bash", str(JOB), *args], capture_output=True, text=True, timeout=120,
                          env={"PATH": path, **env})


def _command(done: subprocess.CompletedProcess) -> list[str]:
    assert done.returncode == 0, done.stderr
    return shlex.split(done.stdout.strip().splitlines()[-1])


def test_a_new_job_is_the_studys_job_for_its_arm_and_seed(tmp_path):
    command = _command(_job("uniform", "1", "--dry-run", RUNS_ROOT=str(tmp_path)))
    assert command[:3] == ["python", "-m", "bmimic.train"]
    overrides = command[3:]
    assert "resume=true" not in overrides and "time_limit_s=1000" in overrides
    run_dir = next(o for o in overrides if o.startswith("hydra.run.dir="))
    assert run_dir == f"hydra.run.dir='{tmp_path}/motion=lafan_folder,sampler=uniform/seed=1'"  # quoted for Hydra
    cfg = compose([o for o in overrides if not o.startswith("hydra.")])
    assert (cfg.motion.name, cfg.sampler.name, cfg.seed, cfg.num_envs, cfg.max_iterations) == (
        "lafan_folder", "uniform", 1, 8192, 8400)
    assert cfg.sampler.clip_balance == "bins" and cfg.time_limit_s == 1000


def test_a_job_with_a_checkpoint_continues_for_train_s_more_seconds(tmp_path):
    ckpt = tmp_path / "motion=lafan_folder,sampler=adaptive/seed=0" / "checkpoints" / "latest.pt"
    ckpt.parent.mkdir(parents=True)
    torch.save({"progress": {"wall_time_s": 720.4, "iteration": 2038}}, ckpt)
    command = _command(_job("adaptive", "0", "--dry-run", RUNS_ROOT=str(tmp_path), TRAIN_S="600", NPROC="2"))
    assert command[:4] == ["torchrun", "--standalone", "--nproc_per_node", "2"]
    assert "resume=true" in command and "time_limit_s=1320" in command


def test_iters_pauses_a_job_at_another_arms_iterations_and_keeps_its_budget(tmp_path):
    command = _command(_job("adaptive", "0", "--dry-run", RUNS_ROOT=str(tmp_path), ITERS="2038", TRAIN_S="900"))
    cfg = compose([o for o in command[3:] if not o.startswith("hydra.")])
    assert (cfg.stop_at_iteration, cfg.max_iterations, cfg.time_limit_s, cfg.sampler.name) == (
        2038, 8400, 900, "adaptive")


def test_egm_anneals_over_the_studys_budget_whatever_a_sitting_stops_at(tmp_path):
    """EGM's schedule spans the study's 8400 iterations in every call, paused by ITERS or not."""
    for env in ({"ITERS": "2038"}, {}):
        command = _command(_job("egm", "0", "--dry-run", RUNS_ROOT=str(tmp_path), **env))
        cfg = compose([o for o in command[3:] if not o.startswith("hydra.")])
        assert (cfg.sampler.name, cfg.sampler.schedule_iterations) == ("egm", 8400)
        assert cfg.max_iterations == 8400 and cfg.stop_at_iteration == (2038 if env else None)
    gmt = _command(_job("gmt", "0", "--dry-run", RUNS_ROOT=str(tmp_path), ITERS="2038"))
    assert not any(o.startswith("sampler.schedule_iterations") for o in gmt)  # no schedule to pin


@pytest.mark.parametrize("args, env, what", [
    (("fast", "0"), {}, "unknown ARM 'fast'"),
    (("adaptive", "x"), {}, "SEED must be a whole number"),
    (("adaptive", "0"), {"TRAIN_S": "0"}, "TRAIN_S must be a positive"),
    (("adaptive", "0"), {"NPROC": "0"}, "NPROC must be a positive"),
    (("adaptive", "0"), {"ITERS": "-5"}, "ITERS must be a positive"),
    (("adaptive", "0"), {"BMIMIC_LAFAN_DIR": "/nonexistent/clips"}, "BMIMIC_LAFAN_DIR must name the folder"),
])
def test_bad_input_is_one_line_exit_2_and_starts_nothing(tmp_path, args, env, what):
    done = _job(*args, RUNS_ROOT=str(tmp_path), **env)
    assert done.returncode == 2 and done.stdout == ""
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and what in lines[0]
    assert list(tmp_path.iterdir()) == []


SITTING = REPO / "sweeps" / "lafan36_whole_sitting.sh"


def test_a_sitting_step_that_cannot_run_is_one_line_and_writes_nothing(tmp_path):
    path = f"{Path(sys.executable).parent}:/usr/bin:/bin"
    env = {"PATH": path, "RUNS_ROOT": str(tmp_path / "runs"), "STATE_DIR": str(tmp_path / "state"),
           "RECORD_DIR": str(tmp_path / "record")}

    def sitting(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["bash", str(SITTING), *args], capture_output=True, text=True, timeout=60, env=env)

    unknown = sitting("adaptive_hybrid", "0", "dance")
    assert unknown.returncode == 2 and unknown.stderr.startswith("error: unknown step 'dance'")
    assert "restore|train|save|wholeclip" in unknown.stderr
    nothing = sitting("adaptive_hybrid", "0", "wholeclip")  # before any training: no checkpoint to evaluate
    assert nothing.returncode == 2 and nothing.stderr.startswith("error: ") and "no checkpoint" in nothing.stderr
    assert sitting("design", "0", "save").returncode == 2  # not an arm of the study
    assert not any(tmp_path.iterdir())
