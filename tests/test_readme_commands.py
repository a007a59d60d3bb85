"""Every command in the README's bash blocks runs, so that the README cannot go stale (the README's
first command, `python -m bmimic.train`, exactly as written).

Each command line (continuations joined, `&&` chains split, console scripts read as their `python -m`
form) is either run here, in order, in one temporary folder, on the CPU at smoke scale (training
overrides appended, the README's sizes replaced, placeholders such as `<timestamp>` and `RUN` filled
with the runs made by earlier lines), or matched by a SKIP rule that says why it cannot run on a test
machine. A line that is neither fails the test: a new README command needs a decision here.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.conftest import REPO, SHARED_MOTIONS, cli_env, run_train
from tests.test_readme import code_lines

pytestmark = pytest.mark.slow

SMOKE = ["device=cpu", "num_envs=2", "max_iterations=2", "ppo.num_steps_per_env=8", "ppo.num_mini_batches=2",
         "eval.horizon_s=0.2", "eval.episodes_per_bin=1", "progress_bar=false", "logger=none"]
"""Appended to every training command (the README's own values of these keys are dropped)."""

SMOKE_FLAGS = {"--episodes-per-bin": "1", "--horizon-s": "0.2", "--seconds": "0.2", "--envs": "2", "--iters": "1",
               "--whole-clip": "1"}
"""The README's sizes of eval, play, bench and sim2sim replaced by these."""

SMOKE_EVAL = ["--horizon-s", "0.2"]
"""Appended to an eval of windows that names no horizon: the README's first run keeps its default of 2 s
(100 steps in every bin; 257 bins of the walk clip took minutes on 2 cores), the other runs have 0.2 s."""

SKIP = [
    (r"^pip install", "the set-up itself: CI installs into a fresh venv (.ci/run), test_packaging installs the wheel"),
    (r"^pytest", "the test suite"),
    (r"hydra/launcher=slurm", "needs a SLURM cluster (tests/cli/test_sweeps.py runs submitit's local launcher)"),
    (r"^torchrun --nnodes", "needs several nodes (tests/training/test_distributed.py runs two CPU 'nodes')"),
    (r"^sbatch ", "needs SLURM (tests/training/test_distributed.py runs the script with a stub srun)"),
    (r"--model my_g1\.xml", "my_g1.xml stands for the user's own MJCF"),
    (r"^export BMIMIC_LAFAN_DIR=/data/", "a placeholder path: the tests read $BMIMIC_LAFAN_DIR when it is set"),
    (r"\+sweep=my_study|outputs/sweeps/my_study", "the README's own study needs its sweep file, which tests/cli/test_own_study.py "
                                                  "writes from the README's yaml block and runs end to end"),
    (r"library_run|lafan36_whole", "the committed library policy: tests/cli/test_library_policy.py restores, evaluates "
                                    "and exports it (from the repository, not this temporary folder)"),
    (r"bmimic\.race|bmimic-race", "a race trains until its thresholds (minutes on a GPU); tests/cli/test_race.py runs "
                                  "a tiny one on the CPU"),
]
"""(pattern, why) of the README lines that cannot run on a CPU test machine."""

EXPECT = {r"motion\.clips=\[\{path: a\.csv": "library of 2 clips (a, b)"}
"""What a command's output must say, beyond exit status 0 (the first command, run exactly as written,
must say that it is a smoke-scale run)."""

DATA_MOTIONS = re.compile(r"motion=lafan_|dance1_subject1\.csv")
"""Lines that need the LAFAN1 clips (not shipped); run when they are here, else skipped as such."""


@dataclass
class Workspace:
    """The temporary folder the README's commands run in, and what earlier lines made there."""

    root: Path
    runs: list[Path] = field(default_factory=list)
    resumes: int = 0
    examples: int = 0
    exact: bool = False
    """The README's first command has run exactly as written (no smoke overrides)."""
    ran: list[tuple[str, float]] = field(default_factory=list)
    """(command, seconds) of every command run."""
    skipped: list[tuple[str, str]] = field(default_factory=list)
    cwd: Path | None = None
    """Where the next part of an `&&` chain runs (a `cd` moves it into the first run folder)."""

    def first_run(self) -> Path:
        assert self.runs, "a README command needs a run folder before any training command ran"
        return self.runs[0]

    def fill(self, arg: str) -> str:
        """Placeholders of the README filled with this workspace's runs and checkpoints."""
        run = self.first_run() if re.search(r"<timestamp>|\bRUN\b|<t[12]>|2026-01-01_12-00-00", arg) else None
        if run is None:
            return arg
        checkpoints = sorted((run / "checkpoints").glob("model_*.pt"), key=lambda p: int(p.stem.split("_")[1]))
        onnx = sorted((run / "checkpoints").glob("motion_policy_*.onnx"))
        arg = re.sub(r"RUN/checkpoints/model_\d+\.pt", str(checkpoints[-1]), arg)
        arg = re.sub(r"RUN/checkpoints/motion_policy_\d+\.onnx", str(onnx[-1]) if onnx else arg, arg)
        arg = re.sub(r"outputs/runs/default/(<timestamp>|2026-01-01_12-00-00)", str(run), arg)
        if "<t1>" in arg or "<t2>" in arg:
            a, b = self.comparable_pair()
            arg = arg.replace("outputs/runs/a/<t1>", str(a)).replace("outputs/runs/b/<t2>", str(b))
        return str(run) if arg == "RUN" else arg

    def comparable_pair(self) -> tuple[Path, Path]:
        """Two runs a report may compare, as a reader's two arms would be: one motion, one budget (the
        README's first run was resumed to a longer budget than the examples)."""
        from bmimic.runs.folder import read_resolved_config

        def key(run: Path) -> str:
            cfg = read_resolved_config(run) or {}
            return json.dumps([cfg.get(k) for k in ("motion", "max_iterations", "num_envs")], sort_keys=True)

        by_key: dict[str, list[Path]] = {}
        for run in self.runs:
            by_key.setdefault(key(run), []).append(run)
        pairs = [runs for runs in by_key.values() if len(runs) > 1]
        assert pairs, "the README compares two runs, but no two of its runs share a motion and a budget"
        return pairs[0][0], pairs[0][-1]


SCRIPTS = {name: target.split(":")[0] for name, target in
           tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"].items()}


def chains() -> list[list[str]]:
    """The README's command lines in order, each an `&&` chain of commands, console scripts as their
    `python -m` form."""
    out = []
    for line in code_lines():
        chain = []
        for part in (p.strip() for p in line.split("&&")):
            first = part.split()[0]
            chain.append(f"python -m {SCRIPTS[first]}{part[len(first):]}" if first in SCRIPTS else part)
        out.append(chain)
    return out


def commands() -> list[str]:
    return [c for chain in chains() for c in chain]


def _smoke_train(args: list[str], ws: Workspace) -> list[str]:
    keys = {a.split("=")[0] for a in SMOKE}
    args = [a for a in args if a.split("=")[0] not in keys]
    extra = list(SMOKE)
    if any(a.startswith("resume=") for a in args):
        # A resume keeps the run's own sizes (the first run's, the README's defaults: 4 iterations) and
        # continues it a little further each time; only budget and logistics keys change.
        ws.resumes += 1
        extra = ["device=cpu", f"max_iterations={4 + ws.resumes}", "progress_bar=false", "logger=none"]
    if "-m" in args:  # one job per arm is enough: the first seed, the first value of a swept key
        extra += ["seed=0", "sampler.gamma=0.9"] if "+sweep=gamma" in args else ["seed=0"]
    elif not any(a.startswith(("resume=", "run_name=", "hydra.run.dir=", "--")) for a in args):
        # Each example at smoke sizes is its own run_name, as for a reader trying them one at a time: the
        # README's `resume=true` continues the latest run of run_name=default, the first command's.
        ws.examples += 1
        extra.append(f"run_name=example_{ws.examples}")
    return [ws.fill(a) for a in args] + extra


def _smoke_flags(args: list[str], ws: Workspace) -> list[str]:
    out = []
    for i, a in enumerate(args):
        out.append(SMOKE_FLAGS[args[i - 1]] if i and args[i - 1] in SMOKE_FLAGS else ws.fill(a))
    return out


def _library_files(ws: Workspace) -> None:
    """a.csv, b.npz and clips/*.npz of the README's library examples, cut from the built-in motion."""
    import mujoco  # noqa: F401
    import numpy as np

    from bmimic.motion.builtin import generate_builtin
    from bmimic.robot import load_mjmodel

    motion = generate_builtin(load_mjmodel(), "easy_only", 0, 20.0)
    root_xyzw = motion.body_quat_w[:, 0][:, [1, 2, 3, 0]]
    rows = np.concatenate([motion.body_pos_w[:, 0], root_xyzw, motion.joint_pos], axis=1)
    np.savetxt(ws.root / "a.csv", rows, delimiter=",")  # LAFAN1 G1 layout; read at 30 fps: 33 s, slowed
    motion.save(ws.root / "b.npz")
    (ws.root / "clips").mkdir(exist_ok=True)
    for name in ("one", "two"):
        motion.save(ws.root / "clips" / f"{name}.npz")


def run_line(command: str, ws: Workspace, gl_ok: bool) -> None:
    start = time.monotonic()
    for pattern, why in SKIP:
        if re.search(pattern, command):
            ws.skipped.append((command, why))
            return
    if DATA_MOTIONS.search(command) and not (SHARED_MOTIONS / "walk1_subject1.csv").is_file():
        ws.skipped.append((command, "needs the LAFAN1 clips (not shipped; set BMIMIC_LAFAN_DIR)"))
        return
    args = shlex.split(command)
    if args[:3] == ["python", "-m", "bmimic.train"] and "-m" in args[3:]:  # a sweep: Hydra's launchers
        _subprocess(command, [sys.executable, "-m", "bmimic.train", *_smoke_train(args[3:], ws)], ws)
    elif args[:3] == ["python", "-m", "bmimic.train"]:
        exact = not (ws.exact or args[3:])  # the README's first command, exactly as written
        train = [] if exact else _smoke_train(args[3:], ws)
        ws.exact = True
        before = set(_runs(ws))
        if "motion=library" in train and not (ws.root / "b.npz").exists():
            _library_files(ws)
        code, out = run_train(*train, cwd=ws.cwd or ws.root)
        assert code == 0, f"{command}\n  ran as: bmimic.train {' '.join(train)}\n{out[-3000:]}"
        expected = [t for p, t in EXPECT.items() if re.search(p, command)] + (["smoke-scale run"] if exact else [])
        for text in expected:
            assert text in out, f"{command}: no {text!r} in\n{out[-3000:]}"
        ws.runs += sorted(set(_runs(ws)) - before)
    elif args[0] == "torchrun":
        tail = args[args.index("bmimic.train") + 1:]
        cmd = [sys.executable, "-m", "torch.distributed.run", *args[1:args.index("-m")], "-m", "bmimic.train",
               *_smoke_train(tail, ws)]
        _subprocess(command, cmd, ws)
    elif args[:2] == ["python", "-m"]:
        if args[2] == "bmimic.play" and not gl_ok:
            ws.skipped.append((command, "no offscreen OpenGL backend on this machine"))
            return
        if "--model" in args and args[args.index("--model") + 1] == "menagerie" and not _menagerie():
            ws.skipped.append((command, "MuJoCo Menagerie's G1 is not here (set BMIMIC_MENAGERIE_G1)"))
            return
        if args[2] == "bmimic.motion.convert":
            shutil.copy(SHARED_MOTIONS / args[3], ws.root / args[3])
        rest = _smoke_flags(args[3:], ws)
        if args[2] == "bmimic.eval" and not {"--horizon-s", "--whole-clip"} & set(rest):
            rest += SMOKE_EVAL
        if args[2] == "bmimic.bench":
            rest += ["--device", "cpu", "--only", "collect"]  # tests/cli/test_bench.py times every part
        _subprocess(command, [sys.executable, "-m", args[2], *rest], ws)
    elif args[0] == "cd":  # the README's `cd <a run folder> && bmimic-eval .`: the rest runs in a run here
        ws.cwd = ws.runs[-1]  # a run no evaluation or sim2sim touched yet
    else:
        pytest.fail(f"README command neither run nor skipped: {command!r} (add a rule in {Path(__file__).name})")
    ws.ran.append((command, time.monotonic() - start))


def _runs(ws: Workspace) -> list[Path]:
    return [p.parent for p in (ws.root / "outputs").rglob("status.json")] if (ws.root / "outputs").exists() else []


def _menagerie() -> bool:
    from bmimic.sim2sim.model import Sim2SimError, find_menagerie

    try:
        find_menagerie()
    except Sim2SimError:
        return False
    return True


def _subprocess(command: str, argv: list[str], ws: Workspace) -> None:
    out = subprocess.run(argv, cwd=ws.cwd or ws.root, capture_output=True, text=True, timeout=900, env=cli_env())
    assert out.returncode == 0, f"{command}\n  ran as: {' '.join(argv[1:])}\n{out.stdout[-2000:]}{out.stderr[-3000:]}"


def test_every_readme_command_runs_or_says_why_not(tmp_path):
    from bmimic import render

    gl_ok = any(render.probe_gl_backend(b) is None for b in render.GL_BACKENDS)
    ws = Workspace(tmp_path)
    for chain in chains():
        ws.cwd = None
        for command in chain:
            run_line(command, ws, gl_ok)
    assert ws.ran and len(ws.ran) + len(ws.skipped) == len(commands())
    assert (tmp_path / "outputs" / "sweeps" / "sampler_ablation" / "report" / "report.md").is_file()
    assert (tmp_path / "my_report" / "report.md").is_file()
    report = "\n".join([*(f"  {s:6.1f} s  {c}" for c, s in ws.ran), *(f"  skipped: {c}  ({why})" for c, why in ws.skipped)])
    print(f"\n{len(ws.ran)} README commands ran, {len(ws.skipped)} skipped:\n{report}")


def test_the_commands_are_read_with_their_console_scripts():
    cmds = commands()
    assert "python -m bmimic.train sampler=uniform seed=3" in cmds
    assert "python -m analysis.report outputs/sweeps/sampler_ablation" in cmds
    assert not any(c.split()[0] in SCRIPTS for c in cmds)
    assert os.sep not in "".join(SCRIPTS)  # names, not paths
