"""Ctrl-C and SIGTERM end the current iteration: the run gets a checkpoint, its tables and status
`interrupted`, one line is printed and the exit status is 130 / 143; a resume loses no completed
iteration. A launcher's own signal (submitit's SIGUSR2: requeue) runs after that checkpoint. The dry
run and the sweep index tell a dead job (status running, no lock holder) from a running one."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time

import pandas as pd
import pytest

from bmimic.runs.folder import lock_held, lock_run, write_status
from bmimic.training.interrupts import StopSignals
from tests.cli.test_sweeps import hydra_config_restored  # noqa: F401  (a fixture)
from tests.conftest import RANKS_GROUP, REPO, TINY, cli_env, run_train, wait_for


def _status(run) -> dict:
    return json.loads((run / "status.json").read_text())


def _iterations(run) -> list[int]:
    return pd.read_parquet(run / "train_metrics.parquet")["iteration"].tolist()


# ----------------------------------------------------------------------------------------- the handlers
def test_the_first_signal_asks_to_stop_and_the_second_stops():
    # What the handlers were before: Python's default_int_handler for SIGINT, or SIG_IGN when this
    # process was started in the background by a non-interactive shell (which ignores SIGINT there).
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with StopSignals() as stop:
        assert not stop.requested
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.01)  # the handler runs in this (the main) thread at the next bytecode
        assert stop.requested and stop.name == "SIGTERM" and stop.exit_code == 143
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)  # a second signal: SIGINT's default, at once
            time.sleep(1)
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before  # restored


def test_a_signal_ends_a_phase_marked_at_once_there_and_then():
    """Issue 47: a set-up of minutes (a huge motion, torchrun's rendezvous) acknowledged SIGTERM and went
    on. A phase with nothing to save midway ends at the signal (StopNow, which no `except Exception`
    swallows); a signal that came before it began ends it as it begins."""
    from bmimic.training.interrupts import StopNow

    with StopSignals() as stop:
        with pytest.raises(StopNow):
            with stop.at_once():
                try:
                    os.kill(os.getpid(), signal.SIGTERM)
                    time.sleep(5)
                except Exception:  # noqa: BLE001 - the code a phase runs cannot swallow it
                    pytest.fail("StopNow was caught as an Exception")
        assert stop.requested and stop.at_once_depth == 0
        with pytest.raises(StopNow):
            stop.begin_at_once()
    with StopSignals() as stop:
        with stop.at_once():
            pass
        os.kill(os.getpid(), signal.SIGTERM)  # outside the phase: a stop after the iteration, as before
        time.sleep(0.01)
        assert stop.requested


def test_a_launchers_handler_runs_after_the_stop():
    calls = []
    previous = signal.signal(signal.SIGUSR2, lambda signum, frame: calls.append(signum))
    try:
        with StopSignals() as stop:
            os.kill(os.getpid(), signal.SIGUSR2)
            time.sleep(0.01)
            assert stop.requested and calls == []  # held back until the checkpoint is written
            stop.chain()
        assert calls == [signal.SIGUSR2] and stop.exit_code == 128 + signal.SIGUSR2
    finally:
        signal.signal(signal.SIGUSR2, previous)


# ------------------------------------------------------------------------------- training, in this process
def test_sigterm_mid_run_checkpoints_the_iteration_and_a_resume_loses_nothing(tmp_path, monkeypatch):
    from bmimic.training.runner import Trainer

    record = Trainer._record_iteration

    def record_then_signal(self, it, *args, **kwargs):
        row = record(self, it, *args, **kwargs)
        if it == 1:  # SLURM's SIGTERM arrives during iteration 2 (index 1) of 4
            os.kill(os.getpid(), signal.SIGTERM)
        return row

    monkeypatch.setattr(Trainer, "_record_iteration", record_then_signal)
    run = tmp_path / "run"
    overrides = [*TINY, "max_iterations=4", "ppo.save_interval=1000", "logger=none", f"hydra.run.dir={run}"]
    code, out = run_train(*overrides)
    assert code == 143, out[-3000:]
    assert out.strip().splitlines()[-1].startswith("interrupted by SIGTERM after iteration 2: checkpoint")
    assert "Traceback" not in out
    assert _status(run)["status"] == "interrupted" and _status(run)["iteration"] == 2
    assert (run / "checkpoints" / "model_2.pt").exists() and not (run / "metrics.json").exists()
    before = pd.read_parquet(run / "train_metrics.parquet")
    assert before["iteration"].tolist() == [0, 1]  # every completed iteration's row was written

    monkeypatch.setattr(Trainer, "_record_iteration", record)
    code, out = run_train(*TINY, "max_iterations=4", "logger=tensorboard", f"resume={run}",
                          f"hydra.run.dir={tmp_path / 'x'}")
    assert code == 0, out[-3000:]
    assert _status(run)["status"] == "done" and _iterations(run) == list(range(4))
    after = pd.read_parquet(run / "train_metrics.parquet")
    pd.testing.assert_frame_equal(after.iloc[:2].reset_index(drop=True), before)  # kept as they were
    # A finished run ends with the commands that evaluate and report it.
    assert [line for line in out.splitlines() if line.startswith("next: ")] == [
        f"next: bmimic-eval {run} (evaluate), bmimic-report {run} (report), "
        f"tensorboard --logdir {run / 'tensorboard'} (curves)"]


def _signal_then_wait(original):
    """`original`, after a SIGTERM to this process and 60 s of work that a stop must cut short."""
    def slow(*args, **kwargs):
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(60)
        return original(*args, **kwargs)
    return slow


def test_sigterm_during_the_set_up_or_an_evaluation_ends_it_at_once(tmp_path, monkeypatch):
    """Issue 47: SIGTERM was acknowledged and ignored for as long as the set-up (or an evaluation) took.
    In the set-up nothing is written and the launch's folder is removed; in an evaluation the iteration
    it evaluates is checkpointed (status interrupted), and a resume evaluates it again."""
    import bmimic.job
    from bmimic.training.evaluator import Evaluator

    run = tmp_path / "setup"
    monkeypatch.setattr(bmimic.job, "build_task", _signal_then_wait(bmimic.job.build_task))
    start = time.monotonic()
    code, out = run_train(*TINY, "max_iterations=2", "logger=none", f"hydra.run.dir={run}")
    assert code == 143 and time.monotonic() - start < 50, out[-3000:]
    assert out.strip().splitlines()[-1] == "interrupted by SIGTERM before training started; nothing was written"
    assert "Traceback" not in out and not run.exists()
    monkeypatch.undo()

    run = tmp_path / "eval"
    monkeypatch.setattr(Evaluator, "evaluate", _signal_then_wait(Evaluator.evaluate))
    start = time.monotonic()
    code, out = run_train(*TINY, "max_iterations=4", "eval.every_iters=2", "logger=none", f"hydra.run.dir={run}")
    assert code == 143 and time.monotonic() - start < 50, out[-3000:]
    assert out.strip().splitlines()[-1].startswith("interrupted by SIGTERM after iteration 2: checkpoint")
    assert _status(run) == {**_status(run), "status": "interrupted", "iteration": 2}
    assert (run / "checkpoints" / "model_2.pt").exists() and _iterations(run) == [0, 1]
    monkeypatch.undo()
    code, out = run_train(*TINY, "max_iterations=4", "eval.every_iters=2", "logger=none", f"resume={run}",
                          f"hydra.run.dir={tmp_path / 'x'}")
    assert code == 0, out[-3000:]
    assert _status(run)["status"] == "done" and _iterations(run) == [0, 1, 2, 3]
    assert sorted(set(pd.read_parquet(run / "eval.parquet")["iteration"])) == [4]


@RANKS_GROUP
@pytest.mark.slow
def test_a_torchrun_rank_without_peers_ends_in_one_line_or_at_sigterm(tmp_path):
    """Issue 47: WORLD_SIZE=2 RANK=0 MASTER_ADDR/PORT without the other rank printed nothing for 10
    minutes and ignored two SIGTERMs. The rendezvous now says it waits, ends after
    BMIMIC_RENDEZVOUS_TIMEOUT_S with one line, and a SIGTERM ends it within seconds."""
    from tests.conftest import free_port

    env = {**cli_env(), "WORLD_SIZE": "2", "RANK": "0", "LOCAL_RANK": "0", "MASTER_ADDR": "127.0.0.1",
           "MASTER_PORT": str(free_port()), "BMIMIC_RENDEZVOUS_TIMEOUT_S": "3"}
    out = subprocess.run([sys.executable, "-m", "bmimic.train", *TINY, "hydra.run.dir=alone"], cwd=tmp_path, env=env,
                         capture_output=True, text=True, timeout=300)
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert out.returncode == 2 and len(errors) == 1 and "Traceback" not in out.stderr, out.stderr[-3000:]
    assert "rank 0 of 2 could not meet the other ranks" in errors[0] and "within 3 s" in errors[0]
    assert not (tmp_path / "alone").exists()
    env["BMIMIC_RENDEZVOUS_TIMEOUT_S"] = "600"
    proc = subprocess.Popen([sys.executable, "-m", "bmimic.train", *TINY, "hydra.run.dir=waiting"], cwd=tmp_path,
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        lines = []
        for line in proc.stdout:  # it says what it waits for
            lines.append(line)
            if "waiting for the other ranks" in line:
                break
        proc.send_signal(signal.SIGTERM)
        start = time.monotonic()
        rest, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 143 and time.monotonic() - start < 20, "".join(lines) + rest
    assert rest.strip().splitlines()[-1] == "interrupted by SIGTERM before training started; nothing was written"
    assert not (tmp_path / "waiting").exists()


@RANKS_GROUP
@pytest.mark.parametrize("rank, addr", [("1", "127.0.0.1"), ("0", "no.such.host.invalid")])
def test_a_rank_without_peers_says_its_own_line_first_and_leaves_no_folder(tmp_path, rank, addr):
    """Issue 77: RANK=1 without rank 0 exited 2 with no `error:` line (only rank 0 spoke), about thirty lines
    of C++ stack frames from torch's TCP client, and the run folder Hydra made for it (train.log)."""
    from tests.conftest import free_port

    env = {**cli_env(), "WORLD_SIZE": "2", "RANK": rank, "LOCAL_RANK": rank, "MASTER_ADDR": addr,
           "MASTER_PORT": str(free_port()), "BMIMIC_RENDEZVOUS_TIMEOUT_S": "1"}
    t0 = time.monotonic()
    out = subprocess.run([sys.executable, "-m", "bmimic.train", *TINY, "hydra.run.dir=runs/alone"], cwd=tmp_path,
                         env=env, capture_output=True, text=True, timeout=120)
    said = (out.stdout + out.stderr).strip().splitlines()
    assert out.returncode == 2 and len(said) == 1 and said[0].startswith("error: torchrun: rank "), said
    assert f"rank {rank} of 2 could not meet the other ranks" in said[0] and "frame #" not in out.stderr
    assert list(tmp_path.iterdir()) == [] and time.monotonic() - t0 < 60


def test_the_address_is_waited_for_in_python_before_torch_connects(monkeypatch):
    from bmimic.rendezvous import DistributedSetupError, meet, wait_for_address
    from tests.conftest import free_port

    port = free_port()
    t0 = time.monotonic()
    with pytest.raises(Exception, match="nothing listened there"):
        wait_for_address("127.0.0.1", port, 1, time.monotonic() + 0.3)
    with pytest.raises(Exception, match="does not resolve"):
        wait_for_address("no.such.host.invalid", port, 0, time.monotonic() + 5)
    assert time.monotonic() - t0 < 5
    import socket

    with socket.create_server(("127.0.0.1", 0)) as server:  # rank 0's store listening: rank 1 goes on at once
        wait_for_address("127.0.0.1", server.getsockname()[1], 1, time.monotonic() + 5)
    monkeypatch.setenv("MASTER_ADDR", "127.0.0.1")
    monkeypatch.setenv("MASTER_PORT", str(port))
    with pytest.raises(DistributedSetupError, match=r"rank 1 of 2 could not meet .* within 0.5 s \(nothing"):
        meet(1, 2, 0.5)


def test_torchrun_variables_are_checked_before_anything_runs(monkeypatch):
    from bmimic.runtime import DistributedSetupError, process_rank, torchrun_env

    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    assert torchrun_env() == (0, 1, 0)
    cases = [({"WORLD_SIZE": "abc"}, "WORLD_SIZE='abc': must be a whole number >= 1"),
             ({"WORLD_SIZE": "0"}, "WORLD_SIZE='0'"), ({"RANK": "-1"}, "RANK='-1'"),
             ({"LOCAL_RANK": "x"}, "LOCAL_RANK='x'"), ({"RANK": "3"}, "RANK=3 with WORLD_SIZE=1"),
             ({"WORLD_SIZE": "2"}, "WORLD_SIZE=2 without RANK"),
             ({"WORLD_SIZE": "2", "RANK": "1"}, "without MASTER_ADDR"),
             ({"WORLD_SIZE": "2", "RANK": "1", "MASTER_ADDR": "h", "MASTER_PORT": "notaport"}, "MASTER_PORT='notaport'"),
             ({"WORLD_SIZE": "2", "RANK": "1", "MASTER_ADDR": "h", "MASTER_PORT": "70000"}, "MASTER_PORT='70000'")]
    for env, words in cases:
        with monkeypatch.context() as m:
            for k, v in env.items():
                m.setenv(k, v)
            with pytest.raises(DistributedSetupError, match=re.escape(words)):
                torchrun_env()
            assert process_rank() >= 0  # the error paths' rank never raises
    code, out = run_train(*TINY, env={"WORLD_SIZE": "2", "RANK": "x"})
    assert code == 2 and out.strip() == "error: RANK='x': must be a whole number >= 0 (torchrun sets it; unset it to " \
        "run one process)", out[-2000:]


# --------------------------------------------------------------------------------------- dead or running
def test_a_lock_is_held_only_while_a_process_holds_it(tmp_path):
    assert not lock_held(tmp_path)  # no lock file
    write_status(tmp_path, "running", 5)
    held = lock_run(tmp_path)  # what a live trainer holds
    try:
        assert lock_held(tmp_path)
    finally:
        held.close()
    assert not lock_held(tmp_path)  # a dead trainer's lock died with it
    again = lock_run(tmp_path)
    assert again is not None  # the probe left nothing held behind
    again.close()


def test_the_dry_run_and_the_index_say_dead(tmp_path, hydra_config_restored):  # noqa: F811
    from analysis.index import build_index
    from bmimic.sweeping.jobs import list_jobs
    from tests.analysis.synthetic_runs import write_run

    sweep = tmp_path / "sweep"
    overrides = ["+sweep=sampler_ablation", "seed=0", f"hydra.sweep.dir={sweep}"]
    _, jobs = list_jobs(overrides)
    runs = {j.overrides: j.run_dir for j in jobs}
    for (job_overrides, run), state in zip(sorted(runs.items()), ("running", "running"), strict=True):
        write_run(run, sampler="uniform", seed=0, overrides=list(job_overrides), mastery=[10, 20, 30, 40],
                  status=state)
    live_run = sorted(runs.values())[0]
    held = lock_run(live_run)
    try:
        _, jobs = list_jobs(overrides)
        assert {j.run_dir: j.status for j in jobs} == {r: "running" if r == live_run else "dead" for r in runs.values()}
        index = build_index(sweep).set_index("job")["status"].to_dict()
        assert sorted(index.values()) == ["dead", "running"]
    finally:
        held.close()


# ---------------------------------------------------------------------------------- real signals (slow)
def _train_proc(tmp_path, *overrides):
    return subprocess.Popen([sys.executable, "-m", "bmimic.train", *TINY, "logger=none", *overrides],
                            cwd=tmp_path, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
def test_a_cpu_run_killed_mid_way_resumes_and_loses_no_completed_iteration(tmp_path):
    """SLURM's SIGTERM from outside (SIGINT takes the same path: test_the_first_signal_asks_to_stop...)."""
    sig, code = signal.SIGTERM, 143
    run = tmp_path / "run"
    proc = _train_proc(tmp_path, "max_iterations=400", "ppo.save_interval=1000", f"hydra.run.dir={run}")
    try:
        wait_for(proc, lambda: _status(run)["status"] == "running", "the run started")
        time.sleep(3.0)  # a few iterations in
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=300)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == code, err[-3000:]
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith(f"interrupted by {sig.name} after")
    done = _status(run)["iteration"]
    assert _status(run)["status"] == "interrupted" and 0 < done < 400
    assert _iterations(run) == list(range(done)) and (run / "checkpoints" / f"model_{done}.pt").exists()
    resumed = subprocess.run([sys.executable, "-m", "bmimic.train", *TINY, "logger=none", f"resume={run}",
                              f"max_iterations={done + 2}"], cwd=tmp_path, env=cli_env(), capture_output=True,
                             text=True, timeout=600)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert _status(run)["status"] == "done" and _iterations(run) == list(range(done + 2))


def _descendants(pid: int) -> list[int]:
    """Every process below `pid` (Linux /proc)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        try:
            children = [int(c) for t in os.listdir(f"/proc/{p}/task")
                        for c in open(f"/proc/{p}/task/{t}/children").read().split()]
        except OSError:
            continue
        out += children
        todo += children
    return out


def _cmdline(pid: int) -> str:
    try:
        return open(f"/proc/{pid}/cmdline").read().replace("\0", " ")
    except OSError:
        return ""


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="finds the job's process in /proc")
def test_a_preempted_submitit_job_is_requeued_and_resumes_from_its_checkpoint(tmp_path):
    """submitit's local launcher plays SLURM: SIGUSR2 to the job (what SLURM sends before a time limit or
    on preemption) makes bmimic checkpoint the iteration, then submitit requeues the job, which resumes."""
    sweep = tmp_path / "sweep"
    proc = subprocess.Popen(
        [sys.executable, "-m", "bmimic.train", "-m", "hydra/launcher=submitit_local", "hydra.launcher.timeout_min=20",
         *TINY, "logger=none", "sampler=uniform", "max_iterations=60", "ppo.save_interval=1000",
         f"hydra.sweep.dir={sweep}"], cwd=REPO, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, start_new_session=True)
    job = None
    try:
        def started() -> bool:
            nonlocal job
            found = [p for p in sweep.rglob("status.json")]
            job = found[0].parent if found else None
            return job is not None and _status(job)["status"] == "running"

        wait_for(proc, started, "the submitit job started training")
        time.sleep(3.0)
        tasks = [p for p in _descendants(proc.pid) if "submitit.core._submit" in _cmdline(p)]
        assert len(tasks) == 1, [_cmdline(p) for p in _descendants(proc.pid)]
        os.kill(tasks[0], signal.SIGUSR2)
        out, err = proc.communicate(timeout=900)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 0, err[-3000:]
    assert _status(job)["status"] == "done" and _iterations(job) == list(range(60))
    log = (job / "errors.log").read_text()
    assert "interrupted by a signal after iteration" in log  # the requeued attempt found the checkpoint
    resumes = json.loads((job / "resumes.json").read_text())
    stopped_at = resumes[-1]["iteration"]
    assert 0 < stopped_at < 60 and (job / "checkpoints" / f"model_{stopped_at}.pt").exists()
