"""A sweep is checked whole before any job runs, and the dry run checks it the same way (issue 36):
jobs that map to one folder, a job the sweep would refuse, a sweep folder outside outputs/, and a
study's parameters given to a single run. Each test is a reproducer of a finding; none trains."""

from __future__ import annotations

import pytest

from tests.conftest import run_train

TINY = ["device=cpu", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2", "motion=easy_only", "motion.duration_s=7",
        "eval.horizon_s=0.2", "progress_bar=false", "logger=none", "max_iterations=1"]


def files(folder) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def launch_list(*overrides: str, cwd) -> tuple[int, str]:
    import contextlib
    import io
    import os

    from bmimic import launch

    out, old = io.StringIO(), os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            code = launch.main(["list", *overrides])
    finally:
        os.chdir(old)
    return code, out.getvalue()


def error_line(out: str) -> str:
    errors = [x for x in out.splitlines() if x.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in out, out[-3000:]
    return errors[0]


@pytest.mark.parametrize("arms", [["num_envs=4,8"], ["eval.every_iters=1,2", "num_envs=2"]])
def test_jobs_sharing_a_folder_are_refused_before_any_runs_and_by_the_dry_run(tmp_path, arms) -> None:
    key = arms[0].split("=")[0]
    code, out = run_train("-m", *TINY, *arms, "sweep_name=dup", cwd=tmp_path)
    line = error_line(out)
    assert code == 2 and "one folder" in line and key in line
    assert files(tmp_path) == []  # no job ran, no sweep folder was made
    code, listed = launch_list(*TINY, *arms, "sweep_name=dup", cwd=tmp_path)
    assert code == 2 and error_line(listed) == line


def test_the_dry_run_refuses_a_job_the_sweep_refuses(tmp_path) -> None:
    code, listed = launch_list(*TINY, "num_envs=2", "sampler.gamma=0,0.5", "sweep_name=g", cwd=tmp_path)
    line = error_line(listed)
    assert code == 2 and "sampler.gamma" in line and "job 0" in line
    code, out = run_train("-m", *TINY, "num_envs=2", "sampler.gamma=0,0.5", "sweep_name=g", cwd=tmp_path)
    assert code == 2 and error_line(out) == line and files(tmp_path) == []


@pytest.mark.parametrize("name", ["../..", "..", "a/../../b"])
def test_a_sweep_name_never_writes_outside_outputs(tmp_path, name) -> None:
    work = tmp_path / "work"
    work.mkdir()
    code, out = run_train("-m", *TINY, "num_envs=2", f"sweep_name={name}", cwd=work)
    assert code == 2 and "sweep_name" in error_line(out)
    assert files(tmp_path) == ["work"]


def test_a_study_given_to_a_single_run_warns_that_its_sweep_is_ignored(tmp_path) -> None:
    code, out = run_train(*TINY, "+sweep=gamma", "ppo.gamma=1.5", cwd=tmp_path)
    assert code == 2 and "ppo.gamma" in error_line(out)
    warning = [x for x in out.splitlines() if "+sweep=gamma" in x and "-m" in x]
    assert warning and "sampler.gamma" in warning[0]
    assert files(tmp_path) == []
