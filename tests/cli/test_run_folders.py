"""Run folders are never shared, overwritten or emptied by a launch that does not own them (issue 36):
a pinned folder holding a run, launches in the same second, refused launches in folders they did not
create, resume edge cases, a full disk. Each test is a reproducer of a finding of the adversarial
pass; the training ones run the real command line in this process at tiny sizes (slow)."""

from __future__ import annotations

import errno
import hashlib
import json
import os
from pathlib import Path

import pandas as pd
import pytest

from tests.conftest import run_train

TINY = ["device=cpu", "num_envs=2", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2", "motion=easy_only",
        "motion.duration_s=7", "eval.horizon_s=0.2", "eval.every_iters=0", "progress_bar=false", "logger=none"]


def tree(folder: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under `folder` (hidden ones too)."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def one_error(out: str) -> str:
    errors = [x for x in out.splitlines() if x.startswith("error:")]
    assert len(errors) == 1 and "Traceback" not in out, out[-3000:]
    return errors[0]


def train_ok(cwd: Path, *args: str) -> str:
    code, out = run_train(*TINY, *args, cwd=cwd)
    assert code == 0, out[-3000:]
    return out


# --------------------------------------------------------------------------------------------- fast
def test_claim_gives_a_same_second_launch_its_own_folder(tmp_path) -> None:
    from bmimic.runs.claim import claim

    first = claim(tmp_path / "runs" / "stamp", pinned=False, resume=False, log_name="train.log")
    second = claim(tmp_path / "runs" / "stamp", pinned=False, resume=False, log_name="train.log")
    assert first.run_dir.name == "stamp" and second.run_dir.name == "stamp_1"
    assert first.created == [tmp_path / "runs", tmp_path / "runs" / "stamp"]
    assert second.created == [tmp_path / "runs" / "stamp_1"]
    # a refusal removes the folders it created, never the other launch's
    (first.run_dir / "train.log").write_text("first\n")
    assert second.release() and first.run_dir.is_dir() and (tmp_path / "runs").is_dir()


def test_claim_refuses_a_pinned_folder_holding_a_run_without_resume(tmp_path) -> None:
    from bmimic.runs.claim import ClaimError, claim
    from bmimic.runs.folder import write_status

    run = tmp_path / "run"
    write_status(run, "done", 3)
    with pytest.raises(ClaimError, match="already holds a run .status done at iteration 3"):
        claim(run, pinned=True, resume=False, log_name="train.log")
    assert claim(run, pinned=True, resume=True, log_name="train.log").created == []
    empty = tmp_path / "empty"
    empty.mkdir()
    assert claim(empty, pinned=True, resume=False, log_name=None).created == []
    with pytest.raises(ClaimError, match="cannot create the folder"):
        claim("/proc/x", pinned=True, resume=False, log_name=None)


def test_release_keeps_what_the_folder_held_before_the_launch(tmp_path) -> None:
    from bmimic.runs.claim import claim
    from bmimic.runs.folder import LOCK, lock_run, write_status

    (tmp_path / "train.log").write_text("earlier lines\n")
    write_status(tmp_path, "failed", 0)  # a run: its owner's notes stay
    (tmp_path / "notes.log").write_text("mine\n")
    c = claim(tmp_path, pinned=True, resume=True, log_name="train.log")
    with open(tmp_path / "train.log", "a") as f:
        f.write("this launch\n")
    held = lock_run(tmp_path)
    assert c.own_log() == "this launch\n"
    assert not c.release(held)
    assert (tmp_path / "train.log").read_text() == "earlier lines\n" and (tmp_path / "notes.log").exists()
    assert not (tmp_path / LOCK).exists()  # created and held by this launch: removed
    held.close()


def test_claim_refuses_a_pinned_folder_of_someone_elses_files_even_with_resume(tmp_path) -> None:
    """Issue 47: a folder holding a user's own metrics.json, provenance.json and checkpoints/policy_1.onnx
    (no status.json, no .hydra) was written into with exit status 0. A launch writes only into a new or
    empty folder or its own run; what a killed launch leaves (its lock, its log) does not count."""
    from bmimic.runs.claim import ClaimError, check_sweep_folder, claim
    from bmimic.runs.folder import LOCK

    mine = tmp_path / "mine"
    (mine / "checkpoints").mkdir(parents=True)
    for name in ("metrics.json", "provenance.json", "checkpoints/policy_1.onnx"):
        (mine / name).write_text("the user's\n")
    for resume in (False, True):
        with pytest.raises(ClaimError, match=r"holds files that are not a bmimic run \(checkpoints, metrics.json, "):
            claim(mine, pinned=True, resume=resume, log_name="train.log")
    assert sorted(p.name for p in mine.rglob("*")) == ["checkpoints", "metrics.json", "policy_1.onnx", "provenance.json"]
    killed = tmp_path / "killed"
    killed.mkdir()
    (killed / LOCK).touch()
    (killed / "train.log").write_text("a launch killed before it wrote anything\n")
    assert claim(killed, pinned=True, resume=False, log_name="train.log").created == []
    with pytest.raises(ClaimError, match="hydra.sweep.dir=.*holds files that are not a bmimic sweep"):
        check_sweep_folder(mine)
    (mine / "multirun.yaml").write_text("{}\n")
    check_sweep_folder(mine)  # a sweep's own folder


def test_a_lock_is_never_removed_by_a_process_that_does_not_hold_it(tmp_path) -> None:
    from bmimic.runs.claim import claim
    from bmimic.runs.folder import LOCK, holds_lock, lock_run

    c = claim(tmp_path / "run", pinned=False, resume=False, log_name=None)
    winner = lock_run(c.run_dir)  # another launch took the lock meanwhile
    inode = (c.run_dir / LOCK).stat().st_ino
    c.release(None)  # this launch does not hold it
    assert (c.run_dir / LOCK).stat().st_ino == inode and holds_lock(winner, c.run_dir)
    assert lock_run(c.run_dir) is None
    winner.close()


def test_lock_run_relocks_a_lock_file_replaced_while_locking(tmp_path, monkeypatch) -> None:
    """A lock taken on a file that was unlinked meanwhile is not the run's lock: lock_run locks the
    file the path names now, so two processes can never both believe they hold the run."""
    import fcntl

    from bmimic.runs import folder as run_folder

    real = fcntl.flock
    calls = {"n": 0}

    def flock(f, op):
        calls["n"] += 1
        if calls["n"] == 1:  # the file is replaced between open() and flock()
            os.unlink(tmp_path / run_folder.LOCK)
            (tmp_path / run_folder.LOCK).touch()
        return real(f, op)

    monkeypatch.setattr(run_folder.fcntl, "flock", flock)
    f = run_folder.lock_run(tmp_path)
    assert calls["n"] == 2 and run_folder.holds_lock(f, tmp_path)
    f.close()


def test_resume_true_takes_the_newest_run_with_a_matching_config(tmp_path) -> None:
    """Issue 35, 5: `sampler=uniform seed=3 resume=true` must not continue an adaptive run."""
    from bmimic.runs.folder import write_resolved_config
    from bmimic.training.resume import ResumeRefusedError, matching_run

    base = {"seed": 0, "sampler": {"name": "adaptive", "gamma": 0.9}, "max_iterations": 10, "device": "cpu"}
    runs = []
    for name, changes in (("2026-01-01_00-00-00", {}), ("2026-01-02_00-00-00", {"seed": 3}),
                          ("2026-01-03_00-00-00", {"sampler": {"name": "uniform", "gamma": 0.9}})):
        run = tmp_path / name
        write_resolved_config(run, base | changes)
        runs.append(run)
    assert matching_run(runs, base | {"max_iterations": 99, "device": "cuda"}) == runs[0]  # budget keys aside
    assert matching_run(runs, base | {"seed": 3}) == runs[1]
    assert matching_run(runs, base | {"sampler": {"name": "adaptive", "gamma": 0.5}},
                        allowed=["sampler.gamma"]) == runs[0]
    with pytest.raises(ResumeRefusedError) as e:
        matching_run(runs, base | {"seed": 7})
    text = str(e.value)
    assert "\n" not in text and all(r.name in text for r in runs) and "seed" in text and "sampler.name" in text


def test_status_is_rewritten_in_place_when_the_disk_is_full(tmp_path, monkeypatch) -> None:
    from bmimic.runs import atomic_io
    from bmimic.runs import folder as run_folder

    run_folder.write_status(tmp_path, "running", 5)

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(atomic_io.tempfile, "mkstemp", full)
    with pytest.raises(run_folder.WriteError, match="No space left"):
        run_folder.atomic_write_text(tmp_path / "x.txt", "x")
    run_folder.write_status(tmp_path, "failed", 5, error="disk full")
    assert run_folder.read_status(tmp_path)["status"] == "failed"


def test_a_folder_path_longer_than_the_os_allows_is_refused_before_anything_is_made(tmp_path) -> None:
    """Issue 77: ENAMETOOLONG in the launch guard became a Hydra warning, then Hydra's mkdir traceback."""
    from bmimic.runs.claim import ClaimError, _mkdirs, check_sweep_folder, claim

    for path, words in ((tmp_path / "ok" / ("a" * 300), "a folder name of 300 bytes, more than the 255"),
                        (tmp_path.joinpath(*["b" * 200] * 25), "bytes, more than the 4095 a path may have")):
        with pytest.raises(ClaimError, match=words):
            claim(path, pinned=True, resume=False, log_name="train.log")
        with pytest.raises(ClaimError, match=words):
            claim(path, pinned=False, resume=False, log_name="train.log")
        with pytest.raises(ClaimError, match=words):
            check_sweep_folder(path)
    assert list(tmp_path.iterdir()) == []
    # and any folder the OS refuses half-way: what was made on the way is removed
    with pytest.raises(OSError):
        _mkdirs(tmp_path / "ok" / "fine" / ("a" * 300), exist_ok=True)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------------------------- end to end
@pytest.mark.slow
def test_a_pinned_folder_holding_a_run_is_refused_without_resume(tmp_path) -> None:
    train_ok(tmp_path, "max_iterations=1", "hydra.run.dir=pinned")
    before = tree(tmp_path / "pinned")
    code, out = run_train(*TINY, "max_iterations=1", "hydra.run.dir=pinned", cwd=tmp_path)
    assert code == 2 and "resume=true" in one_error(out)
    assert tree(tmp_path / "pinned") == before


@pytest.mark.slow
def test_a_run_dir_longer_than_the_os_allows_is_one_line_and_writes_nothing(tmp_path) -> None:
    for path, words in ((tmp_path / "ok" / ("a" * 300), "a folder name of 300 bytes"),
                        (tmp_path.joinpath(*["b" * 200] * 25), "more than the 4095 a path may have")):
        code, out = run_train(*TINY, "max_iterations=1", f"hydra.run.dir={path}", cwd=tmp_path)
        assert code == 2 and words in one_error(out), out[-3000:]
        assert "warning" not in out.lower()
    code, out = run_train("-m", *TINY, "max_iterations=1", "seed=1,2", f"hydra.sweep.dir={tmp_path / ('c' * 300)}",
                          cwd=tmp_path)
    assert code == 2 and "hydra.sweep.dir=" in one_error(out), out[-3000:]
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_same_second_launches_get_their_own_folders(tmp_path) -> None:
    """A fixed timestamp pattern plays two launches in the same second: the second gets its own
    folder, and when it is refused it takes nothing of the first's (train.log, the lock)."""
    stamp = "hydra.run.dir=outputs/runs/x/${now:%Y}"
    train_ok(tmp_path, "max_iterations=1", stamp)
    (first,) = (tmp_path / "outputs" / "runs" / "x").iterdir()
    before = tree(first)
    assert "train.log" in before and ".bmimic.lock" in before
    code, out = run_train(*TINY, "max_iterations=1", stamp, "sampler.gamma=0", cwd=tmp_path)
    assert code == 2 and "sampler.gamma" in one_error(out)
    assert tree(first) == before and [p.name for p in first.parent.iterdir()] == [first.name]
    train_ok(tmp_path, "max_iterations=1", stamp)
    assert sorted(p.name for p in first.parent.iterdir()) == [first.name, f"{first.name}_1"]
    assert tree(first) == before


@pytest.mark.slow
@pytest.mark.parametrize("where", ["folder", "cwd"])
def test_a_refused_launch_removes_only_what_it_created(tmp_path, where) -> None:
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "notes.log").write_text("my notes\n")
    (folder / "train.log").write_text("an earlier log\n")
    before = tree(folder)
    target = "hydra.run.dir=." if where == "cwd" else f"hydra.run.dir={folder}"
    code, out = run_train(*TINY, "max_iterations=1", target, "ppo.gamma=1.5", cwd=folder)
    # Refused for the bad value or, first, for the user's files (a launch never writes among them).
    error = one_error(out)
    assert code == 2 and ("ppo.gamma" in error or "holds files that are not a bmimic run (notes.log)" in error)
    assert folder.is_dir() and tree(folder) == before


@pytest.mark.slow
def test_resume_true_in_a_pinned_folder_without_checkpoint_never_continues_a_sibling(tmp_path) -> None:
    train_ok(tmp_path, "max_iterations=1", "hydra.run.dir=runs/sibling")
    before = tree(tmp_path / "runs" / "sibling")
    out = train_ok(tmp_path, "max_iterations=1", "hydra.run.dir=runs/pinned", "resume=true")
    assert "holds no checkpoint" in out
    assert tree(tmp_path / "runs" / "sibling") == before
    assert json.loads((tmp_path / "runs" / "pinned" / "status.json").read_text())["status"] == "done"


@pytest.mark.slow
def test_resume_true_continues_the_run_with_this_config_and_lists_candidates_otherwise(tmp_path) -> None:
    train_ok(tmp_path, "max_iterations=1", "run_name=r", "seed=0")
    train_ok(tmp_path, "max_iterations=1", "run_name=r", "seed=1")  # newer, another seed
    older, newer = sorted((tmp_path / "outputs" / "runs" / "r").iterdir())
    newer_before = tree(newer)
    train_ok(tmp_path, "max_iterations=2", "run_name=r", "seed=0", "resume=true")
    assert json.loads((older / "status.json").read_text())["iteration"] == 2
    assert tree(newer) == newer_before
    code, out = run_train(*TINY, "max_iterations=3", "run_name=r", "seed=5", "resume=true", cwd=tmp_path)
    line = one_error(out)
    assert code == 2 and older.name in line and newer.name in line and "seed" in line
    assert len(list(older.parent.iterdir())) == 2


@pytest.mark.slow
def test_resume_of_a_run_at_max_iterations_adds_no_second_final_evaluation(tmp_path) -> None:
    """Killed after its last checkpoint, before the status write: the resume finishes the run
    without evaluating the final iteration again."""
    from bmimic.runs.folder import write_status

    run = tmp_path / "run"
    train_ok(tmp_path, "max_iterations=2", "eval.every_iters=1", f"hydra.run.dir={run}")
    rows = pd.read_parquet(run / "eval.parquet")
    write_status(run, "running", 2)
    train_ok(tmp_path, "max_iterations=2", "eval.every_iters=1", f"hydra.run.dir={run}", "resume=true")
    again = pd.read_parquet(run / "eval.parquet")
    assert len(again) == len(rows) and sorted(again["iteration"].unique()) == [1, 2]


@pytest.mark.slow
def test_stop_at_iteration_pauses_a_run_that_resume_continues_to_its_budget(tmp_path) -> None:
    """stop_at_iteration=1 of max_iterations=3: the run pauses after iteration 1 with its budget (3) recorded;
    asking again to pause at 1 is refused in one line, the run byte-identical; resume=true trains 2 and 3."""
    run = tmp_path / "run"
    out = train_ok(tmp_path, "max_iterations=3", "stop_at_iteration=1", f"hydra.run.dir={run}")
    assert "paused at iteration 1" in out
    assert json.loads((run / "status.json").read_text())["iteration"] == 1
    assert json.loads((run / "resolved_config.json").read_text())["max_iterations"] == 3
    before = tree(run)
    code, out = run_train(*TINY, "max_iterations=3", "stop_at_iteration=1", f"hydra.run.dir={run}", "resume=true",
                          cwd=tmp_path)
    assert code == 2 and "stop_at_iteration=1 leaves nothing to train" in one_error(out)
    assert tree(run) == before
    train_ok(tmp_path, "max_iterations=3", f"hydra.run.dir={run}", "resume=true")
    assert json.loads((run / "metrics.json").read_text())["iterations"] == 3
    changes = json.loads((run / "resumes.json").read_text())[-1]["changes"]
    assert "max_iterations" not in changes and changes["stop_at_iteration"] == [1, None]


@pytest.mark.slow
def test_resume_into_another_folder_does_not_copy_that_folders_log(tmp_path) -> None:
    """`resume=A hydra.run.dir=B`: A's log gets this launch's lines, not B's earlier log; B keeps it."""
    run_a = tmp_path / "a"
    train_ok(tmp_path, "max_iterations=1", f"hydra.run.dir={run_a}")
    other = tmp_path / "b"
    other.mkdir()
    (other / "train.log").write_text("B's own earlier log\n")
    train_ok(tmp_path, "max_iterations=2", f"resume={run_a}", f"hydra.run.dir={other}")
    log_a = (run_a / "train.log").read_text()
    assert "B's own earlier log" not in log_a and "resumed from" in log_a
    assert (other / "train.log").read_text() == "B's own earlier log\n"


def _full_disk_after(monkeypatch, name_part: str, nth: int = 1) -> None:
    """From the `nth` atomic write of a file whose name contains `name_part` on, no new file can be
    created (ENOSPC), as on a full disk; files already there can still be rewritten in place."""
    from bmimic.runs import atomic_io

    real = atomic_io.tempfile.mkstemp
    state = {"seen": 0}

    def mkstemp(*a, prefix="", **k):
        state["seen"] += name_part in prefix and state["seen"] < nth
        if state["seen"] >= nth:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(*a, prefix=prefix, **k)

    monkeypatch.setattr(atomic_io.tempfile, "mkstemp", mkstemp)


@pytest.mark.slow
@pytest.mark.parametrize("when", ["model_", "latest.pt"])
def test_a_full_disk_during_training_ends_in_one_line_and_a_consistent_run(tmp_path, monkeypatch, when) -> None:
    """The disk fills while the second checkpoint is written, at either of its two files."""
    import torch

    run = tmp_path / "run"
    _full_disk_after(monkeypatch, when, nth=2)
    code, out = run_train(*TINY, "max_iterations=4", "ppo.save_interval=1", f"hydra.run.dir={run}", cwd=tmp_path)
    assert code != 0 and "No space left" in one_error(out)
    assert json.loads((run / "status.json").read_text())["status"] == "failed"
    latest = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["iter"]
    numbered = [int(p.stem.split("_")[1]) for p in (run / "checkpoints").glob("model_*.pt")]
    assert numbered and latest >= max(numbered)


@pytest.mark.slow
def test_a_full_disk_during_a_resume_ends_in_one_line(tmp_path, monkeypatch) -> None:
    run = tmp_path / "run"
    train_ok(tmp_path, "max_iterations=1", f"hydra.run.dir={run}")
    _full_disk_after(monkeypatch, "")
    code, out = run_train(*TINY, "max_iterations=2", f"hydra.run.dir={run}", "resume=true", cwd=tmp_path)
    assert code != 0 and "No space left" in one_error(out)
    assert json.loads((run / "status.json").read_text())["status"] != "running"


@pytest.mark.slow
def test_interpolated_values_are_recorded_as_the_values_the_run_trained_with(tmp_path) -> None:
    """Issue 47: `seed=${oc.env:SLURM_ARRAY_TASK_ID}` or `seed=${num_envs}` trained, but the report
    tracebacked and bmimic-eval refused the project's own run (the reader's environment, not the run's
    values). .hydra/config.yaml now holds the values the run trained with (the override stays in
    overrides.yaml); data.lafan_dir, the reader's own folder, stays as written."""
    import yaml

    from analysis.report import main as report_main
    from bmimic import eval as bm_eval

    code, out = run_train(*TINY, "max_iterations=1", "seed=${oc.env:BMIMIC_TEST_TASK_ID}", "hydra.run.dir=env",
                          cwd=tmp_path, env={"BMIMIC_TEST_TASK_ID": "3"})
    assert code == 0, out[-3000:]
    train_ok(tmp_path, "max_iterations=1", "seed=${num_envs}", "hydra.run.dir=key")
    for run, seed in (("env", 3), ("key", 2)):
        folder = tmp_path / run
        config = yaml.safe_load((folder / ".hydra" / "config.yaml").read_text())
        assert config["seed"] == seed and config["data"]["lafan_dir"].startswith("${oc.env:BMIMIC_LAFAN_DIR")
        assert any(o.startswith("seed=${") for o in yaml.safe_load((folder / ".hydra" / "overrides.yaml").read_text()))
        assert bm_eval.main([str(folder), "--episodes-per-bin", "1"]) == 0
        assert report_main([str(folder)]) == 0
        assert pd.read_csv(folder / "report" / "runs.csv")["seed"].tolist() == [seed]


def test_resumes_json_lists_changes_of_the_run_not_of_the_launch() -> None:
    # resume: null -> "True" (and resume_allow_changes) say how this launch treats the
    # run; they are no change of what the run trains.
    from bmimic.training.resume import RunPlan, check_resume_changes

    old = {"resume": None, "resume_allow_changes": [], "max_iterations": 4,
           "sampler": {"gamma": 0.9}}
    new = {**old, "resume": "True", "resume_allow_changes": ["sampler.gamma"],
           "max_iterations": 6, "sampler": {"gamma": 0.5}}
    plan = RunPlan(Path("run"), Path("run"), Path("run/checkpoints/latest.pt"), {"config": json.dumps(old)}, True)
    assert check_resume_changes(plan, new, ["sampler.gamma"]) == {"max_iterations": (4, 6), "sampler.gamma": (0.9, 0.5)}


def test_a_staged_folder_moves_in_whole_or_leaves_everything_as_it_was(tmp_path) -> None:
    """Several files of one command (a report): all of them replace their namesakes in the output folder,
    or, when a write fails, none does and every folder made for them is gone again."""
    from bmimic.runs.atomic_io import atomic_write_text, staged_folder

    out = tmp_path / "made" / "for" / "it"
    with pytest.raises(OSError):
        with staged_folder(out) as stage:
            atomic_write_text(stage / "a.csv", "1\n")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []  # no stage, no parents
    kept = tmp_path / "kept"
    kept.mkdir()
    (kept / "a.csv").write_text("old\n")
    (kept / "user.txt").write_text("mine\n")
    with staged_folder(kept) as stage:
        atomic_write_text(stage / "a.csv", "new\n")
        atomic_write_text(stage / "sub" / "b.md", "b\n")
        assert not (kept / "sub").exists()  # nothing reaches the folder before the block ends
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept"]
    assert (kept / "a.csv").read_text() == "new\n" and (kept / "sub" / "b.md").read_text() == "b\n"
    assert (kept / "user.txt").read_text() == "mine\n"


def test_a_staged_folder_stopped_by_sigterm_leaves_nothing(tmp_path) -> None:
    """Issue 77's second round: `bmimic-report RUN` stopped by SIGTERM left RUN/.report.partial-*/ (the
    default action ends the process where it stands, so no cleanup ran). Inside a stage SIGTERM now raises
    SystemExit(143), and the stage goes as on any failure."""
    import signal
    import subprocess
    import sys
    import time

    from tests.conftest import REPO

    code = ("import sys, time; from pathlib import Path; from bmimic.runs.atomic_io import staged_folder\n"
            "with staged_folder(Path(sys.argv[1]) / 'report') as stage:\n"
            "    (stage / 'a.csv').write_text('x'); print('staged', flush=True); time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", code, str(tmp_path)], cwd=REPO, stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    assert proc.stdout is not None and proc.stdout.readline().strip() == "staged"
    assert [p.name.startswith(".report.partial-") for p in tmp_path.iterdir()] == [True]
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    assert proc.wait(timeout=30) == 143 and time.monotonic() - t0 < 10
    assert list(tmp_path.iterdir()) == []
