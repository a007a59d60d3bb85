"""Adversarial inputs, table-driven: every case runs the real command in-process and is classified.

Each case is one bad or unusual input to `bmimic.train`, `bmimic.eval`, `bmimic.play`,
`bmimic.motion.convert`, `bmimic.launch list`, `bmimic.export`, `bmimic.sim2sim` or `analysis.report`
(tests/cli/test_bad_inputs_36.py holds the cases of issue 36), with what must happen: a clean refusal (exit code
not 0, no traceback, an error line naming the key or file, no folder left behind) or a correct
acceptance (exit code 0 and a check of the result). Around every case the harness watches what the
issue counts: a traceback, a silent wrong result (accepted what must be refused, or accepted with a
wrong result), data lost (a protected run folder changed), code executed (a crafted checkpoint,
npz or config created its sentinel file).

    pytest tests/cli/test_bad_inputs.py -m "not slow"     # the refusals (~2 s each, in-process)
    python -m tests.cli.test_bad_inputs                # the survey: every case, counts per class

Cases that train are `slow`. All share one tiny trained run (`fixture`), made once.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import hashlib
import io
import json
import os
import random
import re
import resource
import runpy
import shutil
import sys
import time
import warnings
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import pytest
import torch

from tests.conftest import wait_for

TINY = ["device=cpu", "num_envs=2", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2", "motion=easy_only",
        "motion.duration_s=7", "eval.horizon_s=0.2", "eval.every_iters=0", "progress_bar=false", "logger=none"]
SENTINEL = "PWNED"


class Evil:
    """Unpickling this creates the sentinel file: the probe for 'code executed'."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self):
        return (open, (self.path, "w"))


# --------------------------------------------------------------------------------------------- running
@dataclasses.dataclass
class Result:
    rc: int
    out: str
    exc: BaseException | None = None


def _run(fn: Callable[[], int | None]) -> Result:
    buf = io.StringIO()
    rc, exc = 0, None
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(buf), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            rc = fn() or 0
        except SystemExit as e:
            rc = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
        except BaseException as e:  # noqa: BLE001 - an escaping exception is what the harness counts
            import traceback

            exc = e
            rc = 99
            buf.write(traceback.format_exc())
    return Result(rc, buf.getvalue(), exc)


def run_tool(tool: str, args: list[str]) -> Result:
    """The real command, in this process (imports shared): as `python -m bmimic.<tool> ARGS`."""
    if tool == "train":
        def fn():
            sys.argv = ["bmimic.train", *args]
            runpy.run_module("bmimic.train", run_name="__main__")
        return _run(fn)
    if tool == "eval":
        from bmimic import eval as bm_eval

        return _run(lambda: bm_eval.main(args))
    if tool == "play":
        from bmimic import play as bm_play
        from bmimic import render

        # No OpenGL on a test machine: everything play checks happens before the first frame.
        saved = render.select_gl_backend
        render.select_gl_backend = lambda *a, **k: "egl"
        try:
            return _run(lambda: bm_play.main(args))
        finally:
            render.select_gl_backend = saved
    if tool == "convert":
        from bmimic.motion import convert

        return _run(lambda: convert.main(args))
    if tool == "launch":
        from bmimic import launch

        return _run(lambda: launch.main(["list", *args]))
    if tool == "export":
        from bmimic import export

        return _run(lambda: export.main(args))
    if tool == "sim2sim":
        from bmimic.sim2sim import cli

        return _run(lambda: cli.main([*args, "--workers", "1"]))
    if tool == "report":
        from analysis import report

        return _run(lambda: report.main(args))
    raise ValueError(tool)


# --------------------------------------------------------------------------------------------- workspace
def tree_hash(folder: Path, skip: tuple[str, ...] = ()) -> str:
    """One digest of every file's path and bytes under `folder`."""
    h = hashlib.sha256()
    for p in sorted(folder.rglob("*")):
        if p.is_file() and p.name not in skip:
            h.update(str(p.relative_to(folder)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


class Workspace:
    """A working folder (the cwd of every case) with one tiny trained run and the bad files."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self.data = self.root / "data"
        self.data.mkdir(parents=True, exist_ok=True)
        self.sentinel = self.root / SENTINEL
        self._run: Path | None = None

    @contextlib.contextmanager
    def cwd(self):
        old = os.getcwd()
        os.chdir(self.root)
        try:
            yield
        finally:
            os.chdir(old)

    # ------------------------------------------------------------------ the trained run
    @property
    def run(self) -> Path:
        """outputs/runs/fixture/<stamp>: 2 iterations, checkpoints at 1 and 2, done."""
        if self._run is None:
            with self.cwd():
                res = run_tool("train", [*TINY, "run_name=fixture", "max_iterations=2", "ppo.save_interval=1"])
            runs = sorted((self.root / "outputs" / "runs" / "fixture").iterdir())
            assert res.rc == 0 and len(runs) == 1, res.out[-3000:]
            self._run = runs[0]
        return self._run

    def copy_run(self, name: str) -> Path:
        dst = self.root / "copies" / name
        if not dst.exists():
            shutil.copytree(self.run, dst)
        return dst

    # ------------------------------------------------------------------ motion files
    def motion_arrays(self) -> dict:
        """The arrays of a good 7 s motion npz (the fixture's built-in motion)."""
        path = self.data / "good.npz"
        if not path.exists():
            from bmimic.motion.config import MotionConfig, load_motion
            from bmimic.robot import load_mjmodel

            motion = load_motion(MotionConfig(source="builtin", builtin="easy_only", duration_s=7.0),
                                 load_mjmodel("g1"), cache_dir=self.root / "outputs" / "cache")
            motion.save(path)
        with np.load(path) as f:
            return {k: f[k] for k in f.files}

    def npz(self, name: str, change: Callable[[dict], dict | None] | None = None) -> Path:
        arrays = self.motion_arrays()
        if change is not None:
            arrays = change(arrays) or arrays
        path = self.data / f"{name}.npz"
        np.savez(path, **arrays)
        return path

    def csv(self, name: str, text: str | None = None, change: Callable[[np.ndarray], np.ndarray] | None = None) -> Path:
        path = self.data / f"{name}.csv"
        if text is None:
            table = lafan_table()
            if change is not None:
                table = change(table)
            text = "\n".join(",".join(f"{v:.6f}" for v in row) for row in table) + "\n"
        path.write_text(text)
        return path

    def write(self, name: str, content: bytes | str) -> Path:
        path = self.data / name
        path.write_bytes(content if isinstance(content, bytes) else content.encode())
        return path

    # ------------------------------------------------------------------ checkpoints
    def evil_checkpoint(self, name: str = "evil.pt") -> Path:
        path = self.data / name
        state = {"actor_state_dict": {}, "iter": 1, "payload": Evil(str(self.sentinel))}
        torch.save(state, path)
        return path

    def legacy_run(self, name: str) -> Path:
        """A copy of the fixture whose checkpoints are in format 1 (pickled numpy RNG state, bmimic before
        format 2): its pickle names numpy globals, so every loader refuses it."""
        run = self.root / "copies" / f"legacy_{name}"
        if not run.exists():
            shutil.copytree(self.run, run)
            for p in (run / "checkpoints").glob("*.pt"):
                state = torch.load(p, weights_only=True)
                state["rng"] = {"python": random.getstate(), "numpy": np.random.get_state(),
                                "torch": torch.get_rng_state()}
                state["format"] = "bmimic-checkpoint-1"
                del state["config"], state["meta"]
                torch.save(state, p)
            # ... and its resolved config predates the options added with format 2
            cfg = json.loads((run / "resolved_config.json").read_text())
            del cfg["resume_allow_changes"]
            del cfg["sim"]["max_abs_qvel"], cfg["sim"]["max_root_distance_m"], cfg["env"]["max_abs_step_reward"]
            (run / "resolved_config.json").write_text(json.dumps(cfg))
        return run


def lafan_table(rows: int = 40) -> np.ndarray:
    """A valid LAFAN1 G1 CSV table: standing, root at 0.79 m, identity quaternion (x y z w)."""
    table = np.zeros((rows, 36))
    table[:, 2] = 0.79
    table[:, 6] = 1.0
    table[:, 0] = np.linspace(0, 0.3, rows)
    return table


# --------------------------------------------------------------------------------------------- cases
@dataclasses.dataclass
class Case:
    id: str
    tool: str
    args: Callable[[Workspace], list[str]] | list[str]
    expect: str = "refuse"
    """"refuse": exit code != 0 and an error line containing `match`; "accept": exit code 0 and `check`."""
    match: str = ""
    check: Callable[[Workspace, Result], bool] | None = None
    slow: bool = False
    patch: Callable[[Workspace], contextlib.AbstractContextManager] | None = None
    leaves_launch_dir: bool = False
    """The command writes a new folder under outputs/runs (its own): an accepted run, or one stopped
    after it started training (its folder records the failure)."""


def _m(change):  # an npz variant as motion.path overrides
    def args(ws: Workspace, _c=change):
        name = f"m{abs(hash(_c.__code__.co_code)) % 10**8}"
        return [*TINY, "max_iterations=1", "motion=file", f"motion.path={ws.npz(name, _c)}"]
    return args


def _setitem(key, value):
    def change(d):
        d[key] = value
    return change


def _scale(key, factor):
    def change(d):
        d[key] = d[key] * factor
    return change


def _shift_root(metres):
    def change(d):
        d["body_pos_w"] = d["body_pos_w"] + np.asarray([metres, 0.0, 0.0], dtype=d["body_pos_w"].dtype)
    return change


def _drop(key):
    def change(d):
        del d[key]
    return change


def _nan_at(key):
    def change(d):
        a = d[key].copy()
        a.reshape(-1)[5] = np.nan
        d[key] = a
    return change


def _segments(text):
    return _setitem("segments", np.asarray(text))


def _train(*extra: str, iters: int = 1) -> list[str]:
    return [*TINY, f"max_iterations={iters}", *extra]


def _resume(*extra: str, iters: int = 3) -> Callable[[Workspace], list[str]]:
    def args(ws: Workspace):
        ws.run  # noqa: B018 - the fixture run must exist before the case resolves resume=true
        return [*TINY, "run_name=fixture", f"max_iterations={iters}", "resume=true", *extra]
    return args


@contextlib.contextmanager
def _held_lock(ws: Workspace):
    from bmimic.runs.folder import lock_run

    f = lock_run(ws.run)
    try:
        yield
    finally:
        f.close()


@contextlib.contextmanager
def _disk_full(ws: Workspace):
    real = np.savez

    def savez(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    np.savez = savez
    try:
        yield
    finally:
        np.savez = real


@contextlib.contextmanager
def _on_sys_path(ws: Workspace):
    (ws.data / "evilterm.py").write_text(f"open({str(ws.sentinel)!r}, 'w').close()\ndef f(env):\n    return env\n")
    sys.path.insert(0, str(ws.data))
    try:
        yield
    finally:
        sys.path.remove(str(ws.data))
        sys.modules.pop("evilterm", None)


def _eval_copy_with_config(name: str, edit: Callable[[str], str]) -> Callable[[Workspace], list[str]]:
    def args(ws: Workspace):
        run = ws.copy_run(name)
        cfg = run / ".hydra" / "config.yaml"
        cfg.write_text(edit((ws.run / ".hydra" / "config.yaml").read_text()))
        return [str(run), "--episodes-per-bin", "1"]
    return args


def _resumed_to(iters: int) -> Callable[[Workspace, Result], bool]:
    def check(ws: Workspace, res: Result) -> bool:
        runs = sorted((ws.root / "outputs" / "runs" / "fixture").iterdir())
        run = runs[-1]
        train = pd.read_parquet(run / "train_metrics.parquet")
        # one folder: the resumed run logged into its own, and the launch's new folder is gone
        return list(train["iteration"]) == list(range(iters)) and len(runs) == 1 and \
            "resumed from" in (run / "train.log").read_text()
    return check


def _motion_fps_is(hz: float) -> Callable[[Workspace, Result], bool]:
    def check(ws: Workspace, res: Result) -> bool:
        # the start-up block's motion line: "motion  <name>: <source>; <duration> s at <fps> Hz"
        return re.search(rf"^\s*motion\s.* s at {hz:g} Hz$", res.out, flags=re.M) is not None
    return check


def _converted(ws: Workspace, res: Result) -> bool:
    from bmimic.motion.motion import Motion

    return Motion.load(ws.data / "out_force.npz", None).fps == 50.0


def cases() -> list[Case]:
    c: list[Case] = []
    add = c.append
    # ---------------------------------------------------------------- unknown keys, also with +
    for arg, key in (("+sampler.gama=0.5", "sampler.gama"), ("++sampler.gama=0.5", "sampler.gama"),
                     ("+ppo.lr=1e-3", "ppo.lr"), ("+foo=1", "foo"), ("+env.episode_len_s=5", "env.episode_len_s"),
                     ("+sim.time_step=0.01", "sim.time_step"), ("+motion.pth=x.npz", "motion.pth"),
                     ("+eval.horizon=2", "eval.horizon"), ("+robot.anchor=pelvis", "robot.anchor"),
                     ("+env.reset.joint_pos_range=0.2", "env.reset.joint_pos_range")):
        add(Case(f"unknown key {arg}", "train", _train(arg), match=key))
    for arg, key in (("sampler.gama=0.5", "sampler.gama"), ("ppo.lr=1", "ppo.lr"), ("sampler=adaptve", "adaptve"),
                     ("motion=nope", "nope"), ("seed=abc", "seed"), ("num_envs=two", "num_envs"),
                     ("ppo.actor_hidden_dims=5", "actor_hidden_dims"), ("progress_bar=maybe", "progress_bar")):
        add(Case(f"hydra refuses {arg}", "train", _train(arg), match=key))
    # ---------------------------------------------------------------- NaN and infinity
    for key in ("sampler.gamma", "sampler.lambda_uniform", "sampler.bin_size_seconds", "ppo.learning_rate",
                "ppo.gamma", "ppo.clip_param", "ppo.entropy_coef", "sim.timestep_s", "env.episode_length_s",
                "eval.horizon_s", "time_limit_s", "motion.duration_s", "motion.fps_in",
                "env.rewards.action_rate.weight", "robot.action_scale_factor", "sim.max_abs_qvel"):
        for value in ("nan", "inf"):
            add(Case(f"{key}={value}", "train", _train(f"{key}={value}"), match=key))
    add(Case("-inf in a list", "train", _train("env.events.foot_friction.params.friction_range=[0.3,-inf]"),
             match="friction_range"))
    add(Case("nan in term params", "train", _train("env.terminations.anchor_pos.params.threshold_m=nan"),
             match="threshold_m"))
    # ---------------------------------------------------------------- devices
    for dev in ("gpu", "cuda:x", "cuda:-1", "CPU", "mps", "cuda:00", "cpu:0", "''"):
        add(Case(f"device={dev}", "train", _train(f"device={dev}"), match="device"))
    if not torch.cuda.is_available():
        for dev in ("cuda", "cuda:0", "cuda:7"):
            add(Case(f"device={dev} without a GPU", "train", _train(f"device={dev}"), match="device"))
    # ---------------------------------------------------------------- sampler group vs name
    add(Case("sampler=uniform sampler.name=adaptive", "train", _train("sampler=uniform", "sampler.name=adaptive"),
             match="sampler.name"))
    add(Case("sampler.name=beyondmimic under the default sampler", "train", _train("sampler.name=beyondmimic"),
             match="sampler.name"))
    add(Case("sampler.name=foo", "train", _train("sampler.name=foo"), match="sampler.name"))
    # ---------------------------------------------------------------- each sampler's own keys
    add(Case("sampler=beyondmimic sampler.alpha=2", "train", _train("sampler=beyondmimic", "sampler.alpha=2"),
             match="sampler.alpha"))
    add(Case("sampler=beyondmimic sampler.uniform_ratio=0", "train",
             _train("sampler=beyondmimic", "sampler.uniform_ratio=0"), match="uniform_ratio"))
    add(Case("sampler=uniform sampler.gamma=0.5", "train", _train("sampler=uniform", "sampler.gamma=0.5"),
             match="gamma"))
    add(Case("+sampler.alpha under the default sampler", "train", _train("+sampler.alpha=0.5"), match="alpha"))
    # the peer samplers (issue 24)
    for args, key in ((("sampler=egm", "sampler.power_end=0"), "power_end"),
                      (("sampler=egm", "sampler.uniform_start=1.5"), "uniform_start"),
                      (("sampler=egm", "sampler.power_end=sharp"), "power_end"),
                      (("sampler=gmt", "sampler.subclip_bins=0"), "subclip_bins"),
                      (("sampler=gmt", "sampler.initial_level=0.5"), "initial_level"),
                      (("sampler=gmt", "sampler.clip_balance=clips"), "clip_balance"),
                      (("sampler=phc", "eval.every_iters=1", "sampler.mode=medium"), "sampler.mode"),
                      (("sampler=phc", "eval.every_iters=0"), "eval.every_iters"),
                      (("sampler=protomotions", "eval.every_iters=1", "sampler.failure_decay=2"), "failure_decay"),
                      (("sampler=protomotions", "eval.every_iters=1", "sampler.min_weight=0"), "min_weight"),
                      (("sampler=phc", "sampler.gamma=0.5"), "gamma")):
        add(Case(" ".join(args), "train", _train(*args), match=key))
    # ---------------------------------------------------------------- ranges and meanings
    for arg, key in (
        ("num_envs=0", "num_envs"), ("num_envs=-3", "num_envs"), ("max_iterations=-1", "max_iterations"),
        ("ppo.num_mini_batches=3", "num_mini_batches"), ("ppo.num_steps_per_env=0", "num_steps_per_env"),
        ("ppo.gamma=1.5", "ppo.gamma"), ("ppo.lam=-0.1", "ppo.lam"), ("ppo.learning_rate=0", "learning_rate"),
        ("ppo.clip_param=-0.2", "clip_param"), ("ppo.entropy_coef=-1", "entropy_coef"),
        ("ppo.value_loss_coef=-1", "value_loss_coef"), ("ppo.max_grad_norm=0", "max_grad_norm"),
        ("ppo.num_learning_epochs=0", "num_learning_epochs"), ("ppo.desired_kl=0", "desired_kl"),
        ("ppo.init_noise_std=-1", "init_noise_std"), ("ppo.actor_hidden_dims=[0]", "actor_hidden_dims"),
        ("ppo.critic_hidden_dims=[64,-1]", "critic_hidden_dims"), ("ppo.activation=softmaxx", "activation"),
        ("ppo.noise_std_type=foo", "noise_std_type"), ("ppo.schedule=linear", "schedule"),
        ("ppo.float32_matmul_precision=low", "float32_matmul_precision"), ("ppo.save_interval=0", "save_interval"),
        ("sim.decimation=0", "decimation"), ("sim.timestep_s=0", "timestep_s"), ("sim.timestep_s=-0.005", "timestep_s"),
        ("sim.integrator=verlet", "integrator"), ("sim.solver=pgs", "solver"), ("sim.cone=round", "cone"),
        ("sim.nconmax=0", "nconmax"), ("sim.njmax=-1", "njmax"), ("sim.max_abs_qvel=0", "max_abs_qvel"),
        ("sim.max_root_distance_m=-1", "max_root_distance_m"), ("env.max_abs_step_reward=0", "max_abs_step_reward"),
        ("env.episode_length_s=0", "episode_length_s"), ("env.episode_length_s=0.001", "episode_length_s"),
        ("env.events.foot_friction.params.friction_range=[1.6,0.3]", "foot_friction.params.friction_range"),
        ("env.events.foot_friction.params.friction_range=[0.3]", "friction_range"),
        ("env.events.push.interval_range_s=[3,1]", "push.interval_range_s"),
        ("env.events.push.mode=startup", "push.mode"), ("env.events.torso_com.params.offset_m=[0.1]", "offset_m"),
        ("+env.events.torso_com.params.scale=2", "torso_com.params"),
        ("env.events.push.func=no_such_event", "push.func"),
        ("env.reset.root_pos_range_m=[0.05]", "root_pos_range_m"),
        ("env.reset.joint_pos_range_rad=-0.1", "joint_pos_range_rad"),
        ("env.rewards.action_rate.func=nope", "action_rate.func"),
        ("+env.rewards.extra={func:not_a_reward}", "extra"),
        ("~env.policy_observations", "policy_observations"),
        ("logger=mlflow", "logger"), ("time_limit_s=0", "time_limit_s"), ("time_limit_s=-5", "time_limit_s"),
        ("stop_at_iteration=0", "stop_at_iteration"),
        ("run_name=../escape", "run_name"), ("run_name=a/b", "run_name"), ("run_name=''", "run_name"),
        ("sweep_name=..", "sweep_name"),
        ("sampler.bin_size_seconds=0", "bin_size_seconds"), ("sampler.bin_size_seconds=100", "bin_size_seconds"),
        ("sampler.K=0", "sampler.K"), ("sampler.gamma=0", "sampler.gamma"), ("sampler.lambda_uniform=2", "lambda"),
        ("sampler.alpha_smooth=0", "alpha_smooth"), ("sampler.accounting.attribution=middle", "attribution"),
        ("sampler.accounting.failure=sometimes", "sampler.accounting.failure"),
        ("sampler.accounting.failure_threshold=0", "failure_threshold"), ("sampler.alpha=0.01", "sampler.alpha"),
        ("eval.every_iters=-1", "every_iters"), ("eval.horizon_s=0", "horizon_s"),
        ("eval.episodes_per_bin=0", "episodes_per_bin"), ("eval.max_envs=0", "max_envs"),
        ("robot.anchor_body=nose", "anchor_body"), ("robot.mjcf_path=/nonexistent/g1.xml", "g1.xml"),
        ("motion.builtin=ballet", "ballet"), ("motion.source=web", "motion.source"),
        ("motion.duration_s=0", "duration"), ("motion.duration_s=-5", "duration"),
        ("motion.start_s=-1", "start_s"), ("motion.end_s=99", "end_s"), ("motion.end_s=0.5", "motion"),
        ("resume_allow_changes=[sampler.gama]", "resume_allow_changes"),
    ):
        add(Case(arg, "train", _train(arg), match=key))
    # ---------------------------------------------------------------- memory
    add(Case("num_envs=100000000 on a CPU", "train", _train("num_envs=100000000"), match="num_envs"))
    add(Case("num_envs=2**40", "train", _train("num_envs=1099511627776"), match="num_envs"))
    # ---------------------------------------------------------------- control rate vs motion rate
    add(Case("sim.decimation=2: motion resampled to 100 Hz", "train", _train("sim.decimation=2"), "accept",
             check=_motion_fps_is(100), slow=True, leaves_launch_dir=True))
    add(Case("sim.timestep_s=0.004: motion resampled to 62.5 Hz", "train", _train("sim.timestep_s=0.004"),
             "accept", check=_motion_fps_is(62.5), slow=True, leaves_launch_dir=True))
    # ---------------------------------------------------------------- motion files (through train)
    add(Case("motion=file without a path", "train", _train("motion=file", "motion.path=null"), match="motion.path"))
    add(Case("motion.path missing", "train", _train("motion=file", "motion.path=/nonexistent.npz"),
             match="nonexistent.npz"))
    add(Case("motion.path is a folder", "train", lambda ws: _train("motion=file", f"motion.path={ws.data}"),
             match="data"))
    add(Case("motion.path .txt", "train", lambda ws: _train("motion=file", f"motion.path={ws.write('m.txt', 'x')}"),
             match="m.txt"))
    add(Case("empty npz file", "train", lambda ws: _train("motion=file", f"motion.path={ws.write('e.npz', b'')}"),
             match="e.npz"))
    add(Case("random bytes npz", "train",
             lambda ws: _train("motion=file", f"motion.path={ws.write('r.npz', os.urandom(999))}"), match="r.npz"))
    add(Case("truncated npz", "train", lambda ws: _train(
        "motion=file", f"motion.path={ws.write('t.npz', ws.npz('full').read_bytes()[:5000])}"), match="t.npz"))
    add(Case("npz with a pickled object array", "train", lambda ws: _train("motion=file", "motion.path=" + str(
        ws.npz("pickled", _setitem("joint_pos", np.asarray([Evil(str(ws.sentinel))], dtype=object))))),
        match="pickled.npz"))
    for name, change, match in (
        ("missing joint_vel", _drop("joint_vel"), "joint_vel"),
        ("scalar joint_pos", _setitem("joint_pos", np.float32(1.0)), "joint_pos"),
        ("string joint_pos", _setitem("joint_pos", np.asarray([["a", "b"]])), "joint_pos"),
        ("bool body_pos_w", lambda d: d.update(body_pos_w=d["body_pos_w"] > 0), "body_pos_w"),
        ("complex body_quat_w", lambda d: d.update(body_quat_w=d["body_quat_w"].astype(np.complex64)), "body_quat_w"),
        ("1-D body_pos_w", lambda d: d.update(body_pos_w=d["body_pos_w"].reshape(-1)), "body_pos_w"),
        ("segments not JSON", _segments("{not json"), "segments"),
        ("segments a dict", _segments('{"a": 1}'), "segments"),
        ("segments entry without end", _segments('[{"name": "a", "start_s": 0, "difficulty": "easy"}]'), "segments"),
        ("segments entry a number", _segments("[3]"), "segments"),
        ("segment beyond the motion", _segments('[{"name":"a","start_s":0,"end_s":99,"difficulty":"e"}]'), "segment"),
        ("segment with NaN", _segments('[{"name":"a","start_s":NaN,"end_s":1,"difficulty":"e"}]'), "segment"),
        ("segments an array", _setitem("segments", np.asarray(["[]", "[]"])), "segments"),
        ("fps 0", _setitem("fps", np.asarray([0])), "fps"),
        ("fps NaN", _setitem("fps", np.asarray([np.nan])), "fps"),
        ("fps two numbers", _setitem("fps", np.asarray([50, 30])), "fps"),
        ("fps a string", _setitem("fps", np.asarray(["fifty"])), "fps"),
        ("NaN in body_pos_w", _nan_at("body_pos_w"), "body_pos_w"),
        ("inf in joint_vel", lambda d: d.update(joint_vel=np.full_like(d["joint_vel"], np.inf)), "joint_vel"),
        ("root 1e6 m away", _shift_root(1e6), "from the origin"),
        ("root 2 km away", _shift_root(2000.0), "from the origin"),
        ("quaternions not unit", _scale("body_quat_w", 2.0), "norm"),
        ("no joint/body names", lambda d: [d.pop("joint_names"), d.pop("body_names")] and None, "names"),
        ("duplicate joint names", lambda d: d.update(joint_names=np.asarray([d["joint_names"][0]] * len(
            d["joint_names"]))), "duplicates"),
        ("joint names of another robot", lambda d: d.update(joint_names=np.asarray(
            [f"j{i}" for i in range(len(d["joint_names"]))])), "missing joints"),
        ("float clip_starts", _setitem("clip_starts", np.asarray([0.0])), "clip_starts"),
        ("clip_starts not at 0", _setitem("clip_starts", np.asarray([3])), "clip_starts"),
        ("body count != names", lambda d: d.update(body_names=d["body_names"][:-1]), "body"),
        ("joint beyond its limit", lambda d: d.update(joint_pos=d["joint_pos"] + 3.0), "outside its range"),
        ("one frame", lambda d: d.update({k: d[k][:1] for k in ("joint_pos", "joint_vel", "body_pos_w", "body_quat_w",
                                                              "body_lin_vel_w", "body_ang_vel_w")}), "motion"),
    ):
        add(Case(f"npz: {name}", "train", _m(change), match=match))
    add(Case("npz at 30 fps: resampled to 50 Hz", "train",
             lambda ws: _train("motion=file", f"motion.path={ws.npz('fps30', _resample_to(30.0))}"), "accept",
             check=_motion_fps_is(50), slow=True, leaves_launch_dir=True))
    for name, make, match in (
        ("csv with a header", lambda ws: ws.csv("header", "x,y,z\n" + "0," * 35 + "0\n"), "header"),
        ("csv with 35 columns", lambda ws: ws.csv("short", change=lambda t: t[:, :35]), "columns"),
        ("csv with NaN", lambda ws: ws.csv("nan", change=lambda t: np.where(np.arange(36) == 9, np.nan, t)),
         "not finite"),
        ("csv quaternion not unit", lambda ws: ws.csv("quat", change=lambda t: t * np.where(
            np.arange(36) == 6, 2.0, 1.0)), "quaternion"),
        ("csv binary garbage", lambda ws: ws.write("bin.csv", os.urandom(300)), "bin.csv"),
        ("csv empty", lambda ws: ws.csv("empty", ""), "empty"),
        ("csv one row", lambda ws: ws.csv("one", change=lambda t: t[:1]), "frames"),
        ("csv is a folder", lambda ws: (ws.data / "dir.csv").mkdir(exist_ok=True) or ws.data / "dir.csv", "dir.csv"),
    ):
        add(Case(name, "train", lambda ws, _mk=make: _train("motion=file", f"motion.path={_mk(ws)}"), match=match))
    add(Case("motion.fps_in=0", "train", lambda ws: _train("motion=file", f"motion.path={ws.csv('ok')}",
                                                          "motion.fps_in=0"), match="fps"))
    # ---------------------------------------------------------------- resume (the fixture stays byte-identical)
    add(Case("resume=/nonexistent", "train", _train("resume=/nonexistent/run"), match="does not exist"))
    add(Case("resume=a crafted checkpoint", "train", lambda ws: _train(f"resume={ws.evil_checkpoint()}"),
             match="refused"))
    add(Case("resume=a truncated checkpoint", "train", lambda ws: _train(
        f"resume={ws.write('trunc.pt', (ws.run / 'checkpoints' / 'model_1.pt').read_bytes()[:20000])}"),
        match="not a readable"))
    add(Case("resume=an empty file", "train", lambda ws: _train(f"resume={ws.write('empty.pt', b'')}"),
             match="not a readable"))
    add(Case("resume=a text file", "train", lambda ws: _train(f"resume={ws.write('text.pt', 'hello')}"),
             match="not a readable"))
    add(Case("resume=a folder without checkpoints", "train", lambda ws: _train(f"resume={_empty_dir(ws)}"),
             match="no readable checkpoint"))
    add(Case("resume=true, run done at max_iterations", "train", _resume(iters=2), match="done at iteration 2"))
    add(Case("resume=true with a changed gamma", "train", _resume("sampler.gamma=0.5"), match="sampler.gamma"))
    add(Case("resume=true with another sampler", "train", _resume("sampler=uniform"), match="sampler.name"))
    add(Case("resume=true with another num_envs", "train", _resume("num_envs=4"), match="num_envs"))
    add(Case("resume=true with another motion", "train", _resume("motion.duration_s=8"), match="motion.duration_s"))
    add(Case("resume=true with other observations", "train", _resume("~env.policy_observations.base_lin_vel"),
             match="env.policy_observations"))
    add(Case("resume_allow_changes=[sampler] across samplers", "train",
             _resume("sampler=uniform", "resume_allow_changes=[sampler]"), match="sampler"))
    add(Case("resume_allow_changes=[num_envs] with another num_envs", "train", lambda ws: _train(
        f"resume={ws.copy_run('num_envs')}", "num_envs=4", "resume_allow_changes=[num_envs]", "run_name=fixture",
        iters=3), "accept", check=lambda ws, r: json.loads((ws.root / "copies" / "num_envs" / "resumes.json").read_text(
        ))[-1]["changes"]["num_envs"] == [2, 4], slow=True))
    add(Case("resume_allow_changes=[env] other observations", "train",
             _resume("~env.policy_observations.base_lin_vel", "resume_allow_changes=[env]"), match="fit"))
    add(Case("resume of a run being trained", "train", _resume(), match="another process", patch=_held_lock))
    add(Case("resume=an older checkpoint into its own run", "train", lambda ws: _train(
        f"resume={ws.run / 'checkpoints' / 'model_1.pt'}", f"hydra.run.dir={ws.run}", iters=3),
        match="older than"))
    add(Case("resume=format-1 checkpoint", "train", lambda ws: _train(
        f"resume={ws.legacy_run('refused')}", iters=3), match="refused: its pickle needs the global numpy"))
    add(Case("resume of a run whose latest.pt is truncated", "train", lambda ws: _train(
        f"resume={_truncated_latest(ws)}", "run_name=fixture", iters=3), "accept",
        check=lambda ws, r: "latest.pt" in r.out and "resuming from model_2.pt" in r.out and json.loads(
            (ws.root / "copies" / "truncated" / "status.json").read_text())["iteration"] == 3, slow=True))
    add(Case("resume with resume_allow_changes=[sampler.gamma]", "train",
             _resume("sampler.gamma=0.5", "resume_allow_changes=[sampler.gamma]"), "accept",
             check=lambda ws, r: _resumed_to(3)(ws, r) and "sampler.gamma" in (ws.run / "resumes.json").read_text(),
             slow=True))
    # ---------------------------------------------------------------- eval
    ev = [("missing folder", lambda ws: [str(ws.root / "no_such_folder" / "run")], "no such run"),
          ("not a run folder", lambda ws: [str(ws.data)], "not a run folder"),
          ("crafted checkpoint", lambda ws: [str(_in_run(ws, "evil_eval", ws.evil_checkpoint("model_9.pt")))],
           "refused"),
          ("truncated checkpoint", lambda ws: [str(_in_run(ws, "trunc_eval", ws.write(
              "model_8.pt", (ws.run / "checkpoints" / "model_1.pt").read_bytes()[:30000])))], "not a readable"),
          ("empty checkpoint", lambda ws: [str(_in_run(ws, "empty_eval", ws.write("model_7.pt", b"")))],
           "not a readable"),
          ("format-1 checkpoint", lambda ws: [str(ws.legacy_run("eval"))], "refused: its pickle needs"),
          ("--episodes-per-bin 0", lambda ws: [str(ws.run), "--episodes-per-bin", "0"], "episodes_per_bin"),
          ("--horizon-s nan", lambda ws: [str(ws.run), "--horizon-s", "nan"], "horizon_s"),
          ("--horizon-s -1", lambda ws: [str(ws.run), "--horizon-s", "-1"], "horizon_s"),
          ("--max-envs 0", lambda ws: [str(ws.run), "--max-envs", "0"], "max_envs"),
          ("--device gpu", lambda ws: [str(ws.run), "--device", "gpu"], "device"),
          ("unknown override", lambda ws: [str(ws.run), "eval.horizn_s=3"], "horizn_s"),
          ("+ override", lambda ws: [str(ws.run), "+eval.x=3"], "dotted key=value"),
          ("nan override", lambda ws: [str(ws.run), "sampler.gamma=nan"], "sampler.gamma"),
          ("config.yaml garbage", _eval_copy_with_config("garbage_cfg", lambda t: "{{{: ::"), "config.yaml"),
          ("config with an unknown key", _eval_copy_with_config("unknown_cfg", lambda t: t + "\nbogus: 1\n"),
           "bogus"),
          ("config term from a foreign module", _eval_copy_with_config(
              "foreign_cfg", lambda t: t.replace("func: action_rate_l2", "func: evilterm:f")), "evilterm")]
    for name, args, match in ev:
        add(Case(f"eval: {name}", "eval", args, match=match,
                 patch=_on_sys_path if "foreign" in name else None))
    # ---------------------------------------------------------------- play (no OpenGL needed up to here)
    for name, args, match in (
        ("crafted checkpoint", lambda ws: [str(_in_run(ws, "evil_play", ws.evil_checkpoint("model_6.pt")))],
         "refused"),
        ("--seconds 0", lambda ws: [str(ws.run), "--seconds", "0"], "--seconds"),
        ("--fps -1", lambda ws: [str(ws.run), "--fps", "-1"], "--fps"),
        ("--start-s 999", lambda ws: [str(ws.run), "--start-s", "999"], "--start-s"),
        ("--out .avi", lambda ws: [str(ws.run), "--out", str(ws.root / "v.avi")], "v.avi"),
        ("--device cuda:x", lambda ws: [str(ws.run), "--device", "cuda:x"], "device"),
        ("format-1 checkpoint", lambda ws: [str(ws.legacy_run("play"))], "refused: its pickle needs"),
    ):
        add(Case(f"play: {name}", "play", args, match=match))
    # ---------------------------------------------------------------- convert
    for name, args, match in (
        ("OUT is IN", lambda ws: [str(ws.csv("same")), str(ws.data / "same.csv")], "same.csv"),
        ("OUT is IN through a link", lambda ws: [str(ws.csv("linked")), str(_link(ws))], "input file itself"),
        ("OUT not .npz", lambda ws: [str(ws.csv("a")), str(ws.data / "a.out")], ".npz"),
        ("OUT exists", lambda ws: [str(ws.csv("b")), str(ws.npz("exists"))], "--force"),
        ("OUT is a folder", lambda ws: [str(ws.csv("c")), str(_dir_npz(ws))], "folder"),
        ("OUT in a missing folder", lambda ws: [str(ws.csv("d")), str(ws.root / "no_such_folder" / "x.npz")],
         "does not exist"),
        ("IN missing", lambda ws: [str(ws.root / "no_such_file.csv"), str(ws.data / "o1.npz")], "not found"),
        ("IN is a folder", lambda ws: [str(ws.data), str(ws.data / "o2.npz")], "not found"),
        ("IN with a header", lambda ws: [str(ws.csv("h2", "a,b\n1,2\n")), str(ws.data / "o3.npz")], "column"),
        ("--fps-in 0", lambda ws: [str(ws.csv("e")), str(ws.data / "o4.npz"), "--fps-in", "0"], "fps"),
        ("--fps-out nan", lambda ws: [str(ws.csv("f")), str(ws.data / "o5.npz"), "--fps-out", "nan"], "fps"),
        ("--frames 5 2", lambda ws: [str(ws.csv("g")), str(ws.data / "o6.npz"), "--frames", "5", "2"], "--frames"),
        ("--frames 0 10", lambda ws: [str(ws.csv("h")), str(ws.data / "o7.npz"), "--frames", "0", "10"], "--frames"),
        ("disk full", lambda ws: [str(ws.csv("i")), str(ws.data / "o8.npz")], "No space"),
        ("root 2 km away", lambda ws: [str(ws.csv("far", change=lambda t: t + np.where(np.arange(36) == 0, 2000, 0))),
                                      str(ws.data / "o9.npz")], "from the origin"),
    ):
        add(Case(f"convert: {name}", "convert", args, match=match, patch=_disk_full if name == "disk full" else None))
    add(Case("convert: OUT exists, --force", "convert", lambda ws: [
        str(ws.csv("forced")), str(ws.npz("out_force")), "--force"], "accept", check=_converted))
    # ---------------------------------------------------------------- sweep dry run
    for name, args, match in (
        ("unknown study", ["+sweep=nope"], "nope"),
        ("unknown + key in a sweep", ["+sweep=gamma", "+sampler.gama=0.5"], "sampler.gama"),
        ("NaN in a sweep", ["+sweep=gamma", "sampler.gamma=0.5,nan"], "sampler.gamma"),
        ("sampler name vs group in a sweep", ["+sweep=sampler_ablation", "sampler.name=adaptive"], "sampler.name"),
        ("bad value in a sweep", ["+sweep=gamma", "seed=x,y"], "seed"),
    ):
        add(Case(f"launch list: {name}", "launch", args, match=match))
    return c


def _resample_to(fps: float):
    def change(d):
        from bmimic.motion.motion import Motion

        names = {k: d[k] for k in ("joint_names", "body_names")}
        m = Motion(fps=float(d["fps"][0]), joint_names=list(names["joint_names"]), body_names=list(names["body_names"]),
                   **{k: d[k] for k in ("joint_pos", "joint_vel", "body_pos_w", "body_quat_w", "body_lin_vel_w",
                                        "body_ang_vel_w")}).resample(fps)
        d.update(fps=np.asarray([fps]), joint_pos=m.joint_pos, joint_vel=m.joint_vel, body_pos_w=m.body_pos_w,
                 body_quat_w=m.body_quat_w, body_lin_vel_w=m.body_lin_vel_w, body_ang_vel_w=m.body_ang_vel_w)
        d.pop("segments", None)
    return change


def _truncated_latest(ws: Workspace) -> Path:
    run = ws.copy_run("truncated")
    latest = run / "checkpoints" / "latest.pt"
    latest.write_bytes(latest.read_bytes()[: latest.stat().st_size // 2])
    return run


def _empty_dir(ws: Workspace) -> Path:
    d = ws.data / "no_checkpoints"
    d.mkdir(exist_ok=True)
    return d


def _in_run(ws: Workspace, name: str, checkpoint: Path) -> Path:
    run = ws.copy_run(name)
    dst = run / "checkpoints" / checkpoint.name
    shutil.copy(checkpoint, dst)
    return dst


def _link(ws: Workspace) -> Path:
    link = ws.data / "linked.npz"
    if not link.is_symlink():
        link.symlink_to(ws.data / "linked.csv")
    return link


def _dir_npz(ws: Workspace) -> Path:
    d = ws.data / "folder.npz"
    d.mkdir(exist_ok=True)
    return d


# --------------------------------------------------------------------------------------------- classification
CLASSES = ("clean refusal", "correct acceptance", "traceback", "silent wrong", "data lost", "code executed",
           "wrong refusal", "refusal left files")


def classify(ws: Workspace, case: Case) -> tuple[str, str]:
    """(class, detail) of one case run in the workspace."""
    with ws.cwd():
        args = case.args(ws) if callable(case.args) else list(case.args)
        ws.run  # noqa: B018 - the fixture exists before the protected hashes are taken
        protected = {p: tree_hash(p, skip=("train.log",)) for p in _protected(ws)}
        runs_dir = ws.root / "outputs" / "runs"
        before = {p for p in runs_dir.glob("*/*")}
        if ws.sentinel.exists():
            ws.sentinel.unlink()
        with case.patch(ws) if case.patch else contextlib.nullcontext():
            res = run_tool(case.tool, args)
        after = {p for p in runs_dir.glob("*/*")}
    lines = [x for x in res.out.strip().splitlines() if x.strip()]
    errors = [x for x in lines if x.startswith("error:")]
    detail = errors[-1] if errors else (lines[-1] if lines else "")
    if ws.sentinel.exists():
        return "code executed", detail
    changed = [str(p) for p, h in protected.items() if h != tree_hash(p, skip=("train.log",))]
    if changed and case.expect == "refuse":
        return "data lost", f"changed: {changed}"
    if "Traceback (most recent call last)" in res.out or res.exc is not None:
        return "traceback", res.out[-1500:]
    if case.expect == "refuse":
        if res.rc == 0:
            return "silent wrong", "accepted: " + detail
        said = " ".join(errors) if errors else " ".join(lines)
        if case.match and case.match.lower() not in said.lower():
            return "silent wrong", f"refused without naming {case.match!r}: {said[-400:]}"
        if after - before and not case.leaves_launch_dir:
            return "refusal left files", str(sorted(after - before))
        return "clean refusal", detail
    if res.rc != 0:
        return "wrong refusal", res.out[-1500:]
    ok = case.check(ws, res) if case.check else True
    return ("correct acceptance", detail) if ok else ("silent wrong", "accepted with a wrong result: " + detail)


def _protected(ws: Workspace) -> list[Path]:
    return [p for p in (ws.run,) if p.exists()]


ALL = cases()
EXPECTED = {"refuse": "clean refusal", "accept": "correct acceptance"}


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> Workspace:
    return Workspace(tmp_path_factory.mktemp("bad_inputs"))


def _marks(i: int, case: Case) -> list:
    """Cases that train are slow; so are three in four train refusals (each composes and checks a
    config for ~2 s on a CPU), to keep the default run short: the survey and `-m slow` run them all."""
    train_index = sum(1 for c in ALL[:i] if c.tool == "train")
    return [pytest.mark.slow] if case.slow or (case.tool == "train" and train_index % 4) else []


@pytest.mark.parametrize("case", [pytest.param(c, id=c.id, marks=_marks(i, c)) for i, c in enumerate(ALL)])
def test_bad_input(ws: Workspace, case: Case) -> None:
    kind, detail = classify(ws, case)
    assert kind == EXPECTED[case.expect], f"{kind}: {detail}"


def test_enough_cases() -> None:
    assert len(ALL) >= 150 and len({c.id for c in ALL}) == len(ALL)


def test_run_files_honour_the_umask(ws: Workspace) -> None:
    """Run folders, checkpoints and motion caches get 0666 & ~umask (0644 under umask 022)."""
    from bmimic.runs.folder import current_umask

    want = 0o666 & ~current_umask()
    files = [ws.run / "status.json", ws.run / "checkpoints" / "latest.pt", ws.run / "train_metrics.parquet",
             ws.run / ".hydra" / "config.yaml", *(ws.root / "outputs" / "cache").glob("*.npz")]
    assert len(files) >= 5
    assert {f.name: oct(f.stat().st_mode & 0o777) for f in files} == {f.name: oct(want) for f in files}


# --------------------------------------------------------------------------------------------- beyond the table
def test_crafted_checkpoint_is_refused_by_every_loader(tmp_path) -> None:
    """The one loader every command uses refuses a pickle that would create a file, in one line."""
    from bmimic.training.checkpoints import UnsafeCheckpointError, load_checkpoint_file

    ws = Workspace(tmp_path)
    path = ws.evil_checkpoint()
    with pytest.raises(UnsafeCheckpointError) as err:
        load_checkpoint_file(path)
    assert "\n" not in str(err.value) and ("builtins.open" in str(err.value) or "io.open" in str(err.value))
    assert not ws.sentinel.exists()


def test_absurd_num_envs_is_refused_before_allocating(tmp_path) -> None:
    ws = Workspace(tmp_path)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with ws.cwd():
        res = run_tool("train", _train("num_envs=1000000000"))
    assert res.rc == 2 and "need about" in res.out and "Traceback" not in res.out
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak < 1_000_000  # KiB: under 1 GiB grown


@pytest.mark.slow
def test_planted_nan_is_reset_counted_and_never_reaches_the_loss(tmp_path, monkeypatch) -> None:
    """One world's state turns NaN and another's blows up mid-run: both are reset and counted on the
    device, the count is in the console and metrics.json, every loss stays finite."""
    from bmimic.envs.tracking_env import TrackingEnv

    calls = {"n": 0}
    step = TrackingEnv.step

    def planted(self, actions):
        calls["n"] += 1
        if calls["n"] == 6:
            self.sim.qvel[0, 7] = float("nan")
        if calls["n"] == 11:
            self.sim.qvel[1, 0] = 5e4  # finite but far beyond sim.max_abs_qvel
        return step(self, actions)

    monkeypatch.setattr(TrackingEnv, "step", planted)
    ws = Workspace(tmp_path)
    with ws.cwd():
        res = run_tool("train", [*TINY, "max_iterations=3", "run_name=nan"])
    assert res.rc == 0, res.out[-3000:]
    run = next((tmp_path / "outputs" / "runs" / "nan").iterdir())
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["nonfinite_resets"] >= 1 and metrics["out_of_bounds_resets"] >= 1
    assert "broken world-steps" in res.out
    rows = pd.read_parquet(run / "train_metrics.parquet")
    losses = rows[[c for c in rows.columns if c.startswith("loss/")]].to_numpy()
    assert np.isfinite(losses).all() and np.isfinite(rows["mean_reward"].dropna()).all()


@pytest.mark.slow
def test_contact_overflow_is_counted_in_the_done_line_and_metrics_and_beyond_a_share_stops_the_run(
        tmp_path, monkeypatch) -> None:
    """Issue 47: `sim.nconmax=1` overflowed the contact buffers on every step and the run ended "done"
    without a word in its done line or metrics.json. The overflow is counted there; above
    bmimic.training.health.OVERFLOW_SHARE of the world-steps the run stops, status failed."""
    from bmimic.training import health

    ws = Workspace(tmp_path)
    with ws.cwd():
        monkeypatch.setattr(health, "OVERFLOW_SHARE", 1.0)  # never stops: what the record says
        res = run_tool("train", _train("sim.nconmax=1", "run_name=counted"))
        assert res.rc == 0, res.out[-3000:]
        run = next((tmp_path / "outputs" / "runs" / "counted").iterdir())
        metrics = json.loads((run / "metrics.json").read_text())
        assert metrics["overflow_world_steps"] >= 1
        done = [line for line in res.out.splitlines() if line.startswith("done:")]
        assert done and "world-steps overflowed the contact/constraint buffers (raise sim.nconmax" in done[0]
        monkeypatch.setattr(health, "OVERFLOW_SHARE", 0.1)
        res = run_tool("train", _train("sim.nconmax=1", "run_name=stopped"))
    assert res.rc == 2 and "Traceback" not in res.out, res.out[-3000:]
    errors = [line for line in res.out.splitlines() if line.startswith("error:")]
    assert len(errors) == 1 and "overflowed the contact/constraint buffers" in errors[0] and "sim.nconmax" in errors[0]
    run = next((tmp_path / "outputs" / "runs" / "stopped").iterdir())
    assert json.loads((run / "status.json").read_text())["status"] == "failed"


def test_atomic_write_keeps_the_extension_and_honours_the_umask(tmp_path) -> None:
    from bmimic.runs.folder import atomic_write

    seen = []
    old = os.umask(0o022)
    try:
        atomic_write(tmp_path / "play.mp4", lambda tmp: (seen.append(tmp), Path(tmp).write_bytes(b"x")))
        assert (tmp_path / "play.mp4").stat().st_mode & 0o777 == 0o644
        os.umask(0o077)
        atomic_write(tmp_path / "private.json", lambda tmp: Path(tmp).write_text("{}"))
        assert (tmp_path / "private.json").stat().st_mode & 0o777 == 0o600
    finally:
        os.umask(old)
    name = Path(seen[0]).name
    assert name.startswith(".play.mp4.tmp-") and name.endswith(".mp4")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["play.mp4", "private.json"]


def test_error_log_appends_are_atomic_and_complete(tmp_path) -> None:
    """Concurrent appenders (processes) never lose or tear an entry."""
    import multiprocessing as mp

    ctx = mp.get_context("fork")
    procs = [ctx.Process(target=_append_many, args=(tmp_path, k)) for k in range(4)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
    lines = (tmp_path / "errors.log").read_text().splitlines()
    entries = [x for x in lines if x.startswith("===")]
    assert len(entries) == 4 * 25 and all(x.endswith("attempt") for x in entries)


def _append_many(folder: Path, k: int) -> None:
    from bmimic.runs.folder import append_error_log

    for i in range(25):
        append_error_log(folder, f"writer {k} entry {i} attempt")


@pytest.mark.slow
def test_kill_9_mid_run_then_resume_loses_at_most_one_checkpoint_interval(tmp_path) -> None:
    """SIGKILL between checkpoints, then `resume=true`: the iterations since the last checkpoint are
    trained again (at most ppo.save_interval), and no table row is duplicated."""
    import re
    import signal
    import subprocess

    interval, total = 3, 12
    run = tmp_path / "run"
    args = [sys.executable, "-m", "bmimic.train", *TINY, f"max_iterations={total}", f"ppo.save_interval={interval}",
            f"hydra.run.dir={run}", "progress_bar=true"]
    log = tmp_path / "first.log"
    with open(log, "w") as out:
        proc = subprocess.Popen(args, cwd=tmp_path, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    def done() -> int:  # iterations finished, from the progress bar
        return max([int(k) for k in re.findall(rf"(\d+)/{total}", log.read_text())] or [0])

    try:
        wait_for(proc, lambda: done() >= 2 * interval + 1, "past the second checkpoint, before the third")
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    done = done()
    saved = torch.load(run / "checkpoints" / "latest.pt", weights_only=True)["iter"]
    res = subprocess.run([*args, "resume=true"], cwd=tmp_path, capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    iterations = pd.read_parquet(run / "train_metrics.parquet")["iteration"].tolist()
    lost = done - saved
    print(f"kill -9 after {done} iterations, last checkpoint {saved}: {lost} iterations trained again "
          f"(save_interval {interval}); {len(iterations) - len(set(iterations))} duplicate rows")
    assert 0 <= lost <= interval and iterations == list(range(total))
    assert json.loads((run / "status.json").read_text()) | {"updated": None} == {
        "status": "done", "iteration": total, "error": None, "updated": None}


# --------------------------------------------------------------------------------------------- the survey
def survey(root: Path, include_slow: bool = True, cases: list[Case] | None = None) -> dict[str, int]:
    """Run every case (of `cases`, default this table), print one line per case and the counts per class."""
    ws = Workspace(root)
    counts = {k: 0 for k in CLASSES}
    t0 = time.time()
    for case in ALL if cases is None else cases:
        if case.slow and not include_slow:
            continue
        kind, detail = classify(ws, case)
        counts[kind] += 1
        flag = "" if kind == EXPECTED[case.expect] else "  <-- "
        print(f"{kind:20s} {case.tool:8s} {case.id}{flag}{'' if not flag else detail[:300]}", flush=True)
    print(f"\n{sum(counts.values())} cases in {time.time() - t0:.0f} s:")
    for k, n in counts.items():
        print(f"  {k:20s} {n}")
    return counts


if __name__ == "__main__":
    import argparse
    import tempfile

    p = argparse.ArgumentParser(description="Run every adversarial case and count the outcomes.")
    p.add_argument("--fast", action="store_true", help="skip the cases that train")
    a = p.parse_args()
    result = survey(Path(tempfile.mkdtemp(prefix="bmimic-bad-inputs-")), include_slow=not a.fast)
    bad = sum(result[k] for k in ("traceback", "silent wrong", "data lost", "code executed", "wrong refusal",
                                  "refusal left files"))
    sys.exit(1 if bad else 0)
