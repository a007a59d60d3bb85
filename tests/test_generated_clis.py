"""Generated adversarial inputs, part 2 (issue 47): hypothesis draws the arguments of every console
script (train, race, eval, play, export, sim2sim, bench, launch, convert, report, index, races), the
environment variables they read, damage to a run folder and to its tables. The property of
tests/test_generated_inputs.py holds for each: bad input is one `error:` line (or argparse's usage
line) and exit status 2, or the command reaches its work; never a traceback, never a write on refusal.

The commands run in this process. Where the work itself is expensive (an evaluation, a rollout, a
benchmark, training) it is replaced by a stub that stops the command there (`Reached`): what is tested
is everything before it (argument parsing, path handling, the run folder's checks, the config), the
layers where the findings were. Sized for the default suite on two cores (`-m slow` draws more);
BMIMIC_HARNESS_EXAMPLES=500 draws 500 examples per console script (and per tool of the run-folder damage).

Issue 77's classes are drawn too: deep, huge and alias-bomb JSON and YAML, numbers that are not finite in
bench and race records, FIFOs and device files (as arguments and as any file of a run, where a reader
that blocks would hang: every call runs under an alarm), links out of a run folder, output folders holding
a user's files of bmimic's names (never replaced, whether the command refuses or not), tables that break
their invariants (always refused), and torchrun's rank variables of a rank without peers.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import signal
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.conftest import run_module_as_main

FAST = settings(derandomize=True, database=None, deadline=None, max_examples=30,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
TWENTY = settings(FAST, max_examples=20)
"""For table damage: an accepted example writes a whole report (seconds)."""
EXAMPLES = int(os.environ.get("BMIMIC_HARNESS_EXAMPLES") or 5)
"""Examples drawn per console script (and per tool of the run-folder damage): 5 keeps the default suite
fast on two cores; BMIMIC_HARNESS_EXAMPLES=500 is issue 77's bar."""
PER_SCRIPT = settings(FAST, max_examples=EXAMPLES)
MORE = settings(FAST, max_examples=200)
DEEPER = settings(FAST, max_examples=100)
"""For run-folder and table damage beyond the default draw: an example costs about a second (a tool's
checks, or a whole report), so 100 more of each, beside the 30 and 20 that the quick tier draws."""
BASE = ["device=cpu", "num_envs=2", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2", "motion=easy_only",
        "motion.duration_s=7", "eval.horizon_s=0.2", "progress_bar=false", "logger=none"]


class Reached(BaseException):
    """A stubbed expensive step was reached: the command accepted its input (not an Exception, so that
    no handler of the command swallows it)."""


class Hung(BaseException):
    """A command ran past CALL_LIMIT_S: a read that blocks (a FIFO) or never ends (a device) is the finding."""


CALL_LIMIT_S = 120
"""The most one call may take (the slowest accepted examples reach their stub in ~20 s on two busy cores)."""


def _reached(*args, **kwargs):
    raise Reached


def _exit_rank(code: int) -> None:
    raise SystemExit(code)  # a torchrun rank's exit without teardown (os._exit) would end the test's process


# --------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def world(tmp_path_factory) -> dict:
    """A trained run (tables, checkpoint, ONNX), a race JSON, a sweep, a LAFAN1-style CSV: the inputs the
    generated arguments point at, copied per example where a command could write."""
    from tests.conftest import train_in_process

    root = tmp_path_factory.mktemp("world")
    run = train_in_process(root / "run", *BASE, "max_iterations=1", cwd=root)
    race = root / "race.json"
    race.write_text(json.dumps({"kind": "bmimic-race-1", "config": {"overrides": [], "sampler": "uniform", "seed": 0},
                                "evaluations": [{"iteration": 1, "env_steps": 16, "wall_from_launch_s": 3.0,
                                                 "success_rate": 0.5, "mpkpe_rel_mm": 40.0}],
                                "thresholds": [{"metric": "eval_success_rate", "threshold": 0.9, "status": "censored",
                                                "iteration": None, "env_steps": None, "wall_from_launch_s": None,
                                                "wall_from_first_iteration_s": None}]}))
    sweep = root / "sweep"
    shutil.copytree(run, sweep / "sampler=uniform" / "seed=0")
    (sweep / "multirun.yaml").write_text("{}\n")
    table = np.zeros((40, 36))
    table[:, 0], table[:, 2], table[:, 6] = np.linspace(0, 0.3, 40), 0.79, 1.0
    np.savetxt(root / "clip.csv", table, delimiter=",", fmt="%.6f")
    (root / "file.txt").write_text("a user's file\n")
    (root / "folder").mkdir()
    (root / "folder" / "mine.txt").write_text("a user's file\n")
    # issue 77's inputs: records deep, huge, an alias bomb or not finite; a FIFO; a link out of the run
    (root / "deep.json").write_text("[" * 5000 + "]" * 5000)
    (root / "bomb.yaml").write_text(ALIAS_BOMB)
    with open(root / "huge.json", "wb") as f:  # sparse: larger than any record may be, written in no time
        f.write(b"[")
        f.truncate(65 * 2**20)
    (root / "nonfinite.json").write_text('[{"gpus": 1, "num_envs_per_gpu": 2, "env_steps_per_s": Infinity, '
                                         '"scaling": NaN}]')
    os.mkfifo(root / "fifo")
    (root / "linked.pt").symlink_to(run / "checkpoints" / "latest.pt")
    # a folder of the user's files named as bmimic's outputs (report, evaluation, export): never replaced
    (root / "foreign").mkdir()
    for name in ("report.md", "runs.csv", "eval_summary.json", "eval_bins.parquet", "races.csv"):
        (root / "foreign" / name).write_text("a user's file\n")
    return {"root": root, "run": run, "race": race, "sweep": sweep, "csv": root / "clip.csv"}


def tree(folder: Path) -> dict[str, str]:
    """{relative path: sha256} of every regular file under `folder` (not links, FIFOs or devices; a file over
    1 MiB by its size, inode and modification time: a checkpoint or a sparse record, hashed twice an example)."""
    def digest(p: Path) -> str:
        info = p.stat()
        if info.st_size > 2**20:
            return f"{info.st_size}:{info.st_ino}:{info.st_mtime_ns}"
        return hashlib.sha256(p.read_bytes()).hexdigest()
    return {str(p.relative_to(folder)): digest(p) for p in sorted(folder.rglob("*")) if p.is_file() and not p.is_symlink()}


# --------------------------------------------------------------------------------------------- the commands
def _hydra_app(module: str):
    def run(argv):
        sys.argv = [module, *argv]
        run_module_as_main(module)
        return 0
    return run


def _main(module: str, name: str = "main"):
    def run(argv):
        import importlib

        return getattr(importlib.import_module(module), name)(argv)
    return run


NOT_DEBUGGED = ("hydra._internal.utils", "is_under_debugger", lambda: False)
"""Hydra re-raises an app's error when a tracer is set (it takes hypothesis's for a debugger); the command
line has none, and prints Hydra's message."""
EXIT_RANK = ("bmimic.runtime", "exit_rank", _exit_rank)
COMMANDS = {
    "train": (_hydra_app("bmimic.train"), [("bmimic.job", "build_task", _reached), NOT_DEBUGGED, EXIT_RANK]),
    "race": (_main("bmimic.race"), [("bmimic.job", "build_task", _reached), NOT_DEBUGGED,
                                    ("bmimic.race", "exit_rank", _exit_rank)]),
    "eval": (_main("bmimic.eval"), [("bmimic.eval", "evaluate", _reached), ("bmimic.eval", "evaluate_whole_clip", _reached)]),
    "play": (_main("bmimic.play"), [("bmimic.task", "build_evaluator", _reached),
                                    ("bmimic.render", "select_gl_backend", lambda *a, **k: "egl")]),
    "export": (_main("bmimic.export"), [("bmimic.task", "build_evaluator", _reached)]),
    "sim2sim": (_main("bmimic.sim2sim.cli"), [("bmimic.sim2sim.native_eval", "run_episodes", _reached),
                                              ("bmimic.sim2sim.whole_clip", "run_tasks", _reached),
                                              ("bmimic.render", "select_gl_backend", lambda *a, **k: "egl")]),
    "bench": (_main("bmimic.bench"), [("bmimic.bench", "bench_one", _reached), EXIT_RANK]),
    "launch": (_main("bmimic.launch"), [NOT_DEBUGGED]),
    "convert": (_main("bmimic.motion.convert"), []),
    "report": (_main("analysis.report"), []),
    "index": (_main("analysis.index"), []),
    "races": (_main("analysis.races"), []),
    "race_whole_clip": (_main("analysis.race_whole_clip"), []),
}
"""name -> (run(argv) -> exit status, the (module, attribute, replacement) stubs: `_reached` ends its
expensive work; the others stand in for what a test machine lacks (OpenGL) or adds (a tracer))."""


DISK_FULL = "(disk full at write)"
"""An example's pseudo-variable (never set in the environment): the disk fills at the command's nth atomic write
(bmimic.runs.atomic_io, every file of a run's record and every output goes through it) and stays full. Issue 77
asks for a small temporary filesystem where the machine allows it; a test machine rarely lets a test mount one,
so the fault is planted where each write is flushed, which a full filesystem reports the same way (ENOSPC)."""


def disk_full_at(n: int):
    """atomic_io._fsync_path that fails from the nth file it flushes on (folders' flushes pass)."""
    import errno

    from bmimic.runs import atomic_io

    real, count = atomic_io._fsync_path, [0]

    def fsync(path, directory: bool = False):
        if not directory:
            count[0] += 1
            if count[0] >= n:
                raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, directory=directory)
    return fsync


def call(name: str, argv: list[str], env: dict[str, str | None], cwd: Path) -> tuple[int | str, str]:
    """Run command `name` with `argv` in this process, with `env` set (None: unset) in `cwd`; its exit
    status ("reached" at a stub) and everything it printed. Any other exception fails the test: on
    the command line it would be a traceback."""
    import importlib
    import logging

    run, stubs = COMMANDS[name]
    env = dict(env)
    full_at = env.pop(DISK_FULL, None)
    if full_at is not None:  # the disk fills at the command's nth atomic write and stays full
        stubs = [*stubs, ("bmimic.runs.atomic_io", "_fsync_path", disk_full_at(int(full_at)))]
    saved_env = {k: os.environ.get(k) for k in env}
    saved = sys.argv, os.getcwd(), logging.getLogger().handlers[:], logging.getLogger().level
    patched = []
    out = io.StringIO()
    try:
        for k, v in env.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
        for module, attr, replacement in stubs:
            mod = importlib.import_module(module)
            patched.append((mod, attr, getattr(mod, attr)))
            setattr(mod, attr, replacement)
        os.chdir(cwd)
        # As in a new process: no handler of an earlier in-process run (the world's train.log) is attached.
        logging.getLogger().handlers[:] = []

        def hung(signum, frame):
            raise Hung(f"{name} {argv} {env}: still running after {CALL_LIMIT_S} s (a read that blocks?)")
        previous = signal.signal(signal.SIGALRM, hung)
        signal.alarm(CALL_LIMIT_S)
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            try:
                rc = run(argv)
            except SystemExit as e:
                rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
            except Reached:
                rc = "reached"
            except Exception as e:  # noqa: BLE001 - the finding: a traceback on the command line
                import traceback

                raise AssertionError(f"{name} {argv} {env}: {type(e).__name__}: {e}\n{traceback.format_exc()}\n"
                                     f"{out.getvalue()[-2000:]}") from None
            finally:
                signal.alarm(0)
                signal.signal(signal.SIGALRM, previous)
    finally:
        for mod, attr, value in patched:
            setattr(mod, attr, value)
        sys.argv, _, handlers, level = saved
        os.chdir(saved[1])
        logging.getLogger().handlers[:] = handlers
        logging.getLogger().setLevel(level)
        for k, v in saved_env.items():
            os.environ.pop(k, None) if v is None else os.environ.__setitem__(k, v)
    return rc, out.getvalue()


def holds(name: str, rc, said: str, argv=()) -> None:
    """The property: no traceback, no C++ stack frames (torch's); a refusal is exit status 2 with one `error:`
    line (argparse: its usage and error lines). (Hydra's own blocks, exit 1, were allowed for train and race
    until issue 77: a config path or name that names nothing is one line now too.)"""
    assert "Traceback" not in said and "frame #" not in said, said[-3000:]
    if rc in (0, "reached"):
        return
    if rc == 1 and name in ("train", "race") and re.search(r"^\d+ job\(s\) failed or were refused:$", said, re.M):
        return  # a multirun whose jobs failed, each recorded in its folder: exit 1 by design (sweeping.outcomes)
    errors = [line for line in said.splitlines() if line.startswith("error:") or ": error:" in line]
    assert rc == 2 and len(errors) == 1, f"{name} {list(argv)}: exit {rc}, {len(errors)} error lines:\n{said[-3000:]}"


# --------------------------------------------------------------------------------------------- values
NUMBERS = ["0", "-1", "1", "2", "nan", "inf", "-inf", "1e308", "1e-300", "abc", "", " ", "9" * 30, "0x10", "1_000",
           "3.5", "1,2", "-0"]
"""Values for a numeric flag."""
CONDITIONS = ["nominal", "robust", "nominal,robust", "", "x", "robust,robust", ","]
"""Values for --conditions (whole-clip evaluation)."""


def paths(w: dict) -> list[str]:
    root, run = w["root"], w["run"]
    return [str(run), str(run / "checkpoints" / "latest.pt"), str(run / "checkpoints" / "motion_policy_1.onnx"),
            str(run / "checkpoints" / "policy_1.onnx"), str(run / "metrics.json"), str(run / "eval.parquet"),
            str(w["race"]), str(w["sweep"]), str(w["csv"]), str(root / "file.txt"), str(root / "folder"),
            str(root / "nothing" / "x"), "/dev/null", "/", ".", "..", "~", "-", "x" * 300, str(root / ("y" * 300)),
            "a\nb", "\udcff.npz", "/proc/x", "out.npz", "out.json", "out.mp4", "v.gif", "report", "r,e;p|o'rt",
            # issue 77
            str(root / "deep.json"), str(root / "bomb.yaml"), str(root / "huge.json"), str(root / "nonfinite.json"),
            str(root / "fifo"), "/dev/zero", str(root / "linked.pt"), str(root / "foreign"),
            str(root / "foreign" / "report.md"), str(root / "ok" / ("z" * 300))]


FLAGS = {
    "eval": {"--episodes-per-bin": NUMBERS, "--horizon-s": NUMBERS, "--max-envs": NUMBERS, "--device": "device",
             "--out": "path", "--force": None, "--trust-checkpoint": None, "--whole-clip": [*NUMBERS, None],
             "--conditions": CONDITIONS},
    "play": {"--seconds": NUMBERS, "--start-s": NUMBERS, "--out": "path", "--width": NUMBERS, "--height": NUMBERS,
             "--fps": NUMBERS, "--device": "device", "--msaa": NUMBERS, "--no-ghost": None, "--no-text": None,
             "--trust-checkpoint": None},
    "export": {"--out": "path", "--force": None, "--trust-checkpoint": None},
    "sim2sim": {"--model": ["bmimic_g1", "project", "menagerie", "/nonexistent.xml", "path"], "--episodes-per-bin": NUMBERS,
                "--horizon-s": NUMBERS, "--max-mpkpe-rel-mm": NUMBERS, "--workers": NUMBERS,
                "--joint-dynamics": ["model", "metadata", "x"], "--video": "path", "--video-start-s": NUMBERS,
                "--video-s": NUMBERS, "--out": "path", "--clip": ["clip", "", ",", "nosuch", "path"],
                "--whole-clip": NUMBERS, "--conditions": CONDITIONS, "--seed": NUMBERS},
    "bench": {"--envs": ["2", "0", "abc", "2,4", "1e9", "", "-1", "2,,4"], "--iters": NUMBERS, "--device": "device",
              "--only": ["sim", "train", "nothing", "", "sim,bogus"], "--json": "path", "--multigpu-json": "path"},
    "convert": {"--fps-in": NUMBERS, "--fps-out": NUMBERS, "--frames": "two numbers", "--mjcf": "path",
                "--force": None, "--allow-implausible": None},
    "report": {"--out": "path", "--mastery-threshold": NUMBERS, "--mastery-persist": NUMBERS,
               "--success-threshold": NUMBERS, "--baseline": ["uniform", "adaptive", "", "x"],
               "--resamples": NUMBERS, "--max-iteration": NUMBERS, "--allow-mixed": None},
    "races": {"--out": "path"},
    "race": {"--budget-s": NUMBERS, "--success": ["0.9", "0.9,0.99", "2", "x", "", "nan"],
             "--mpkpe-rel-mm": ["40", "0", "-1", "x"], "--sustain": NUMBERS, "--json": "path",
             "--whole-clip-success": ["0.9", "0.9,0.95", "1.5", "x", "", "nan"], "--no-whole-clip": None,
             "--native-whole-clip": NUMBERS},
    "race_whole_clip": {"--native": None, "--model": ["bmimic_g1", "menagerie", "", "x/y"], "--json": "path"},
    "index": {},
    "launch": {},
    "train": {},
}
"""Each command's options and the values drawn for them ("path": a path; "device": a device; None: a
switch). test_every_option_of_every_command_is_drawn keeps this list equal to the commands' --help."""
DEVICES = ["cpu", "auto", "cuda", "cuda:0", "cuda:x", "gpu", "", "CPU", "cuda:-1"]
HYDRA_ARGS = ["--cfg", "job", "--help", "--info", "-m", "--resolve", "-c", "hydra/launcher=slurm",
              "-cp", "-cp=/nonexistent", "--config-path=pkg://nothing_here", "-cn=nope", "--config-name=train",
              "-cd=/nonexistent", "--config-dir=.",
              "hydra/launcher=joblib_gpus", "hydra/launcher=nope", "+sweep=sampler_ablation", "+sweep=nope",
              "resume=true", "hydra.verbose=true", "sampler=uniform", "seed=1,2", "seed=${oc.env:BMIMIC_GEN_SEED}",
              "max_cpu_hours=null", "--multirun", "hydra.job.chdir=true", "'", "=", "a=b=c"]
"""Hydra arguments of train and race (with paths for hydra.run.dir, hydra.sweep.dir, resume)."""
ENV = {
    "WORLD_SIZE": ["abc", "0", "1", "2", "-1", ""], "RANK": ["0", "1", "x", "-1", "5"], "LOCAL_RANK": ["0", "x", "-3"],
    "MASTER_ADDR": ["", "127.0.0.1", "no.such.host.invalid"], "MASTER_PORT": ["0", "70000", "x", ""],
    "CUDA_VISIBLE_DEVICES": ["", "0,0", "-1", "abc"], "BMIMIC_LAFAN_DIR": ["", "/nonexistent", "path"],
    "BMIMIC_RENDEZVOUS_TIMEOUT_S": ["0", "nan", "x", "-5", "1e300"], "BMIMIC_SOURCE_COMMIT": ["", "\n", "x" * 500],
    "BMIMIC_MENAGERIE_G1": ["/nonexistent.xml", "path"], "BMIMIC_GEN_SEED": ["3", "x", ""], "HOME": ["/nonexistent"],
    "TMPDIR": ["/nonexistent"], "SLURM_JOB_ID": ["1", "x"], "OMP_NUM_THREADS": ["x", "0"],
}
"""Environment variables the commands (or the libraries they start) read, and values drawn for them."""


@st.composite
def command_line(draw, w: dict, names=tuple(COMMANDS)):
    name = draw(st.sampled_from(names))
    pool = paths(w)

    def value(kind):
        if kind == "path":
            return draw(st.sampled_from(pool))
        if kind == "device":
            return draw(st.sampled_from(DEVICES))
        if kind == "two numbers":
            return [draw(st.sampled_from(NUMBERS)), draw(st.sampled_from(NUMBERS))]
        v = draw(st.sampled_from(kind))
        return draw(st.sampled_from(pool)) if v == "path" else v  # ("path" among the values: any path)

    argv = []
    if name in ("train", "race"):
        argv += BASE + ["max_iterations=1", "max_cpu_hours=null"]
        for a in draw(st.lists(st.sampled_from(HYDRA_ARGS + ["hydra.run.dir", "hydra.sweep.dir", "resume"]),
                               max_size=3)):
            argv += [f"{a}={draw(st.sampled_from(pool))}"] if a in ("hydra.run.dir", "hydra.sweep.dir", "resume") \
                else [a]
    elif name == "launch":
        argv += [draw(st.sampled_from(["list", "list", "run", ""]))]
        argv += draw(st.lists(st.sampled_from(HYDRA_ARGS), max_size=3))
    else:
        positional = {"convert": 2, "report": draw(st.integers(0, 2)), "races": draw(st.integers(0, 2)),
                      "index": draw(st.integers(0, 2))}.get(name, 1)
        fitting = {"convert": [str(w["csv"]), "out.npz"], "races": [str(w["race"])], "index": [str(w["sweep"])],
                   "report": [str(w["run"]), str(w["sweep"])], "bench": []}.get(name, [str(w["run"])])
        argv += [draw(st.sampled_from(fitting[k:k + 1] * 3 + pool)) if fitting[k:k + 1] else draw(st.sampled_from(pool))
                 for k in range(positional)]
    if name in ("eval", "play") and draw(st.booleans()):
        argv.append(draw(st.sampled_from(["eval.horizon_s=nan", "seed=1.5", "nosuch.key=1", "=", "motion.path=x"])))
    for flag in draw(st.lists(st.sampled_from(sorted(FLAGS[name]) or ["--help"]), max_size=4, unique=True)):
        kind = FLAGS[name].get(flag)
        v = None if kind is None else value(kind)
        argv += [flag, *(v if isinstance(v, list) else [] if v is None else [v])]
    env = {k: draw(st.sampled_from(ENV[k])) for k in draw(st.lists(st.sampled_from(sorted(ENV)), max_size=3,
                                                                   unique=True))}
    env = {k: (str(w["root"] / "folder") if v == "path" else v) for k, v in env.items()}
    if draw(st.integers(0, 9)) == 0:  # torchrun's variables of a rank whose peers never come (issue 77)
        from tests.conftest import free_port

        rank = draw(st.sampled_from(["0", "1"]))
        env.update(WORLD_SIZE="2", RANK=rank, LOCAL_RANK=rank, MASTER_ADDR=draw(st.sampled_from(
            ["127.0.0.1", "no.such.host.invalid"])), MASTER_PORT=str(free_port()))
    env.setdefault("BMIMIC_RENDEZVOUS_TIMEOUT_S", "1")  # a rank without peers waits 1 s, not 300
    if draw(st.integers(0, 7)) == 0:  # a full disk (issue 77)
        env[DISK_FULL] = str(draw(st.integers(1, 6)))
    if name == "bench" and "--envs" not in argv:
        argv += ["--envs", "2", "--iters", "1"]
    return name, argv, env


def _property(example, w: dict, tmp: Path) -> int | str:
    name, argv, env = example
    before, users = tree(w["root"]), tree(w["root"] / "foreign")
    rc, said = call(name, argv, env, tmp)
    holds(name, rc, said, [*argv, env])
    assert tree(w["root"] / "foreign") == users, f"{name} {argv}: replaced a user's file of one of its output names"
    leftovers = [p for folder in (tmp, w["root"]) for p in folder.rglob(".*.tmp-*")]
    assert not leftovers, f"{name} {argv} {env}: left half-written files {leftovers[:3]}"
    if rc not in (0, "reached"):
        assert tree(w["root"]) == before, f"{name} {argv}: refused, but changed the files it was given"
        runs = tmp / "outputs" / "runs"
        if DISK_FULL in env:  # a run the full disk stopped after it began: kept, and it says it failed
            for status in runs.glob("**/status.json"):
                assert json.loads(status.read_text())["status"] == "failed", f"{name} {argv} {env}: {status}"
        else:
            assert not runs.exists() or not any(runs.iterdir()), f"{name} {argv} {env}: refused, but left a run folder"
    return rc


FULL_DISK_COMMANDS = {
    "report": lambda w, tmp: [str(w["run"]), "--out", str(tmp / "report")],
    "index": lambda w, tmp: [str(w["sweep"])],
    "races": lambda w, tmp: [str(w["race"]), "--out", str(tmp / "races")],
    "convert": lambda w, tmp: [str(w["csv"]), str(tmp / "clip.npz")],
}
"""Commands and the arguments that get them to their writes, each run with the disk full at its 1st, 2nd,
... write. (eval, export and train are stubbed here before theirs; a run's final export on a full disk is
tests/cli/test_resume_exact.py's, its status on a full disk tests/cli/test_run_folders.py's.)"""


@pytest.mark.parametrize("name", sorted(FULL_DISK_COMMANDS))
def test_a_full_disk_at_any_write_is_one_line_and_leaves_no_half_file(world, name, tmp_path_factory):
    """Issue 77: report or export on a full filesystem left partial CSVs or an empty folder. Each write the
    command makes fails in turn; every time it ends in one error line, exit 2, nothing half-written, the
    inputs and the output folder unchanged (no file of the writes before the failing one), until n passes its
    last write and it completes."""
    for n in range(1, 40):
        with scratch(tmp_path_factory, "full") as tmp:
            work = tmp / "work"
            if name == "index":  # the index writes into the sweep it reads: a copy of it
                shutil.copytree(world["sweep"], work)
                argv = [str(work)]
            else:
                work.mkdir()
                argv = FULL_DISK_COMMANDS[name](world, work)
            before = tree(work)
            if _property((name, argv, {DISK_FULL: str(n)}), world, tmp) in (0, "reached"):
                break  # n is past the command's last write
            assert tree(work) == before, f"{name} {argv}: refused at write {n}, but left what it wrote before"
    assert n > 1, f"{name}: wrote nothing, so the full disk was never met"


@contextlib.contextmanager
def scratch(tmp_path_factory, name: str):
    """A folder for one example, removed after it: 500 examples of a run's copy (16 MB each) would fill a disk."""
    folder = tmp_path_factory.mktemp(name)
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)


@pytest.mark.parametrize("name", sorted(COMMANDS))
@PER_SCRIPT
@given(data=st.data())
def test_generated_command_lines_of_each_console_script(world, name, data, tmp_path_factory):
    with scratch(tmp_path_factory, "cli") as tmp:
        _property(data.draw(command_line(world, names=(name,))), world, tmp)


@pytest.mark.slow
@MORE
@given(data=st.data())
def test_more_generated_command_lines(world, data, tmp_path_factory):
    with scratch(tmp_path_factory, "cli") as tmp:
        _property(data.draw(command_line(world)), world, tmp)


def test_every_option_of_every_command_is_drawn(world, tmp_path):
    """FLAGS lists every option each command's --help shows (a new flag is drawn from the day it exists)."""
    for name in COMMANDS:
        if name in ("train", "launch", "index"):  # Hydra's and positional-only command lines: drawn above
            continue
        rc, said = call(name, ["--help"], {}, tmp_path)
        assert rc == 0, said
        usage = said.split("\n\n")[0]  # argparse's usage block names every option
        shown = set(re.findall(r"\[(--[a-z][a-z-]+)", usage)) - {"--help"}
        assert shown <= set(FLAGS[name]), (name, shown - set(FLAGS[name]))


# --------------------------------------------------------------------------------------------- run folders
DAMAGE_FILES = ["status.json", "metrics.json", "provenance.json", "resolved_config.json", "motion_segments.json",
                ".hydra/config.yaml", ".hydra/overrides.yaml", ".hydra/hydra.yaml", "checkpoints/latest.pt",
                "checkpoints/model_1.pt", "checkpoints/motion_policy_1.onnx", "train_metrics.parquet",
                "eval.parquet", "sampler.parquet"]
DAMAGE = ["delete", "empty", "garbage", "truncate", "folder", "symlink_dir", "symlink_loop", "json_types", "yaml_types",
          "deep", "fifo", "device", "alias_bomb", "huge", "nonfinite", "outside"]
"""(issue 77: FIFOs and devices for every file of the run, not only its JSON and YAML records; a huge record;
numbers that are not finite; a file that is a link to a copy outside the run)"""
ALIAS_BOMB = "a: &a [x, x, x, x, x, x, x, x, x, x]\n" + "".join(
    f"{c}: &{c} [{', '.join(['*' + p] * 10)}]\n" for p, c in zip("abcdefg", "bcdefgh"))
"""YAML whose document has 10**8 leaves once its aliases are expanded (issue 77)."""
TOOLS = {"report": lambda run: [str(run)], "index": lambda run: [str(run.parent)],
         "eval": lambda run: [str(run), "--episodes-per-bin", "1"], "export": lambda run: [str(run)],
         "sim2sim": lambda run: [str(run), "--episodes-per-bin", "1", "--workers", "1"],
         "play": lambda run: [str(run), "--seconds", "0.1"],
         "train": lambda run: [*BASE, "max_iterations=2", f"resume={run}", "hydra.run.dir=elsewhere"]}


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink(missing_ok=True)


def damage(run: Path, rel: str, how: str, n: int) -> None:
    path = run / rel
    if how in ("empty", "garbage", "truncate", "json_types", "yaml_types", "deep", "alias_bomb") and not path.is_file():
        return  # (an earlier damage made it a folder or a link)
    if how in ("huge", "nonfinite", "outside") and not path.is_file():
        return
    if how == "delete":
        _remove(path)
    elif how == "empty" and path.is_file():
        path.write_bytes(b"")
    elif how == "garbage" and path.is_file():
        path.write_bytes(bytes(range(256)) * (1 + n % 3))
    elif how == "truncate" and path.is_file():
        data = path.read_bytes()
        path.write_bytes(data[: len(data) * (n % 4) // 4])
    elif how == "folder":
        _remove(path)
        path.mkdir(parents=True, exist_ok=True)
    elif how == "symlink_dir":
        _remove(path)
        path.symlink_to(run)
    elif how == "symlink_loop":
        _remove(path)
        path.symlink_to(path)
    elif how == "json_types" and path.suffix == ".json":
        path.write_text(json.dumps([None, "x", {"status": 5, "iteration": "1x", "num_bins": -1, "seed": "a"}][n % 3]))
    elif how == "deep" and path.suffix in (".json", ".yaml"):
        path.write_text("[" * (2000 + n) + "]" * (2000 + n))
    elif how == "fifo":
        _remove(path)
        os.mkfifo(path)
    elif how == "device":
        _remove(path)
        path.symlink_to("/dev/zero")
    elif how == "alias_bomb" and path.suffix == ".yaml":
        path.write_text(ALIAS_BOMB)
    elif how == "huge" and path.suffix in (".json", ".yaml"):
        with open(path, "r+b") as f:  # sparse, past the largest record a reader takes
            f.truncate(65 * 2**20)
    elif how == "nonfinite" and path.suffix == ".json":
        path.write_text(re.sub(r"(?<=: )-?[0-9][0-9.e+-]*", ["Infinity", "NaN", "-Infinity", "1e999"][n % 4],
                               path.read_text(errors="replace"), count=1 + n % 3))
    elif how == "outside":  # the run's own file, moved out of the run and linked back
        outside = run.parent / f"outside-{n}-{path.name}"
        if not outside.exists():
            shutil.move(path, outside)
            path.symlink_to(outside)
    elif how == "yaml_types" and path.suffix == ".yaml":
        path.write_text(["[]\n", "seed: '${oc.env:NOPE}'\n", "{a: {b: 1}}\n", "- x\n- 1\n"][n % 4])


@st.composite
def run_damage(draw, tools: tuple = ()):
    tools = tools or tuple(sorted(TOOLS))
    changes = draw(st.lists(st.tuples(st.sampled_from(DAMAGE_FILES), st.sampled_from(DAMAGE), st.integers(0, 99)),
                            min_size=1, max_size=3))
    return changes, draw(st.sampled_from(tools))


def _run_damage_property(example, w: dict, tmp: Path) -> None:
    changes, tool = example
    run = tmp / "runs" / "run"
    shutil.copytree(w["run"], run, symlinks=True, ignore=shutil.ignore_patterns("report", "eval", "sim2sim", "videos"))
    for rel, how, n in changes:
        damage(run, rel, how, n)
    before = tree(run)
    rc, said = call(tool, TOOLS[tool](run), {}, tmp)
    holds(tool, rc, said)
    if rc not in (0, "reached"):
        assert tree(run) == before, f"{tool} on {changes}: refused, but changed the run"


@pytest.mark.parametrize("tool", sorted(TOOLS))
@PER_SCRIPT
@given(data=st.data())
def test_generated_run_folder_damage(world, tool, data, tmp_path_factory):
    with scratch(tmp_path_factory, "damage") as tmp:
        _run_damage_property(data.draw(run_damage((tool,))), world, tmp)


@pytest.mark.slow
@DEEPER
@given(example=run_damage())
def test_more_generated_run_folder_damage(world, example, tmp_path_factory):
    with scratch(tmp_path_factory, "damage") as tmp:
        _run_damage_property(example, world, tmp)


# --------------------------------------------------------------------------------------------- tables
TABLES = ["train_metrics", "eval", "sampler"]
TABLE_DAMAGE = ["scale", "value", "nan_column", "drop_column", "text_column", "no_rows", "duplicate_rows",
                "shuffle_bins", "shift_bins", "negate", "bool_column"]
TABLE_VALUES = [0.0, -1.0, 5.0, 1e308, -1e-300, np.nan, np.inf, 0.5, 2.0, 1e9]


BROKEN_INVARIANTS = ["failures_over_visits", "far_iteration", "repeated_iteration", "env_steps_back", "negative_error"]
"""Issue 77's damage that a run record can never hold (a count over its total, an iteration far past the
run's, a repeated iteration, env steps going down, a negative tracking error): always refused, never reported."""


@st.composite
def table_damage(draw):
    return draw(st.lists(st.tuples(st.sampled_from(TABLES), st.sampled_from(TABLE_DAMAGE + BROKEN_INVARIANTS),
                                   st.integers(0, 10**6), st.sampled_from(TABLE_VALUES)), min_size=1, max_size=2))


def break_invariant(df: pd.DataFrame, how: str, n: int) -> bool:
    """Break invariant `how` in `df` in place where its columns allow; whether it did."""
    if not len(df):
        return False
    row = df.index[n % len(df)]
    if how == "failures_over_visits" and {"failures", "visits"} <= set(df.columns):
        df["failures"] = df["failures"].astype("int64")
        df.loc[row, "failures"] = int(df.loc[row, "visits"]) + 1 + n % 3
    elif how == "far_iteration" and "iteration" in df.columns:
        df["iteration"] = df["iteration"].astype("int64")
        df.loc[df.index[-1], "iteration"] = 10**18
    elif how == "negative_error" and "mpkpe_mm" in df.columns:
        df.loc[row, "mpkpe_mm"] = -1.0 - n % 7
    else:
        return False
    return True


def damage_table(df: pd.DataFrame, how: str, n: int, value: float) -> pd.DataFrame:
    column = df.columns[n % len(df.columns)]
    numeric = pd.api.types.is_numeric_dtype(df[column]) and not pd.api.types.is_bool_dtype(df[column])
    if how == "scale" and numeric:
        with np.errstate(all="ignore"):
            df[column] = df[column] * value
    elif how == "value" and len(df):
        df[column] = df[column].astype(object)
        df.loc[df.index[n % len(df)], column] = value
        df[column] = pd.to_numeric(df[column], errors="coerce") if numeric else df[column].astype(str)
    elif how == "nan_column":
        df[column] = np.nan
    elif how == "drop_column":
        df = df.drop(columns=[column])
    elif how == "text_column":
        df[column] = df[column].astype(str) + "x"
    elif how == "no_rows":
        df = df.iloc[:0]
    elif how == "duplicate_rows":
        df = pd.concat([df, df], ignore_index=True)
    elif how == "shuffle_bins" and "bin" in df:
        df["bin"] = np.random.default_rng(n).permutation(df["bin"].to_numpy())
    elif how == "shift_bins" and "bin" in df:
        df["bin"] = df["bin"] + 1 + n % 5
    elif how == "negate" and numeric:
        df[column] = -df[column]
    elif how == "bool_column":
        df[column] = True
    return df


def _grown(df: pd.DataFrame, how: str) -> pd.DataFrame | None:
    """train_metrics with a row added after its last that repeats its iteration, or whose env steps go down."""
    if not len(df) or not {"iteration", "env_steps"} <= set(df.columns):
        return None
    extra = df.iloc[[-1]].copy()
    if how == "env_steps_back":
        extra["iteration"] = extra["iteration"] + 1
        extra["env_steps"] = extra["env_steps"] - 1
    return pd.concat([df, extra], ignore_index=True)


def _table_property(changes, w: dict, tmp: Path) -> None:
    run = tmp / "run"
    shutil.copytree(w["run"], run, ignore=shutil.ignore_patterns("report", "eval", "sim2sim", "videos", "checkpoints"))
    broken = []
    for table, how, n, value in changes:
        path = run / f"{table}.parquet"
        df = pd.read_parquet(path)
        if how in ("repeated_iteration", "env_steps_back"):
            grown = _grown(df, how) if table == "train_metrics" else None
            df = df if grown is None else grown
            broken += [how] if grown is not None else []
        elif how in BROKEN_INVARIANTS:
            broken += [how] if break_invariant(df, how, n) else []
        else:
            df = damage_table(df, how, n, value)
        df.to_parquet(path, index=False)
    before = tree(run)
    rc, said = call("report", [str(run), "--out", str(tmp / "out")], {}, tmp)
    holds("report", rc, said)
    assert rc == 2 or not broken, f"{changes}: the report took a table whose invariants are broken ({broken})"
    if rc != 0:
        assert tree(run) == before and not (tmp / "out" / "report.md").exists(), said[-2000:]
        return
    # Accepted: what the report says is a rate, and it compared one seed of one arm.
    summary = pd.read_csv(tmp / "out" / "runs.csv")
    assert summary["included"].sum() <= 1
    final = pd.read_csv(tmp / "out" / "summary.csv") if (tmp / "out" / "summary.csv").exists() else None
    if final is not None:
        rates = final.filter(regex="failure").select_dtypes("number").to_numpy().ravel()
        assert np.all((rates[np.isfinite(rates)] >= 0) & (rates[np.isfinite(rates)] <= 1)), final.T


@settings(TWENTY, max_examples=max(20, EXAMPLES))
@given(changes=table_damage())
def test_generated_table_damage(world, changes, tmp_path_factory):
    with scratch(tmp_path_factory, "tables") as tmp:
        _table_property(changes, world, tmp)


@pytest.mark.slow
@DEEPER
@given(changes=table_damage())
def test_more_generated_table_damage(world, changes, tmp_path_factory):
    with scratch(tmp_path_factory, "tables") as tmp:
        _table_property(changes, world, tmp)
