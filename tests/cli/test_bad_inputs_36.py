"""The adversarial cases of issue 36, in the harness of tests/cli/test_bad_inputs.py: each is a
reproducer of one finding (a traceback, a silent wrong result, data lost or a hang), run through the
real command in this process and classified the same way.

    pytest tests/cli/test_bad_inputs_36.py -m "not slow"
    python -m tests.cli.test_bad_inputs_36            # the survey: every case, counts per class

Findings that need more than one command (run-folder ownership, resume edge cases, a full disk,
sweeps, broken worlds) are tests of their own: tests/cli/test_run_folders.py,
tests/cli/test_launch_checks.py, tests/training/test_broken_worlds.py.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from tests.cli.test_bad_inputs import (
    CLASSES,
    EXPECTED,
    Case,
    Result,
    Workspace,
    _train,
    classify,
    survey,
)

UNSET = "BMIMIC_TEST_UNSET_VARIABLE"


# --------------------------------------------------------------------------------------------- inputs
def _npz_arg(name: str, change, *extra: str) -> callable:
    def args(ws: Workspace):
        return _train("motion=file", f"motion.path={ws.npz(name, change)}", "max_iterations=3", *extra)
    return args


def _shift_z(metres: float):
    def change(d):
        d["body_pos_w"] = d["body_pos_w"] + np.asarray([0.0, 0.0, metres], dtype=d["body_pos_w"].dtype)
    return change


def _library_end(ws: Workspace) -> list[str]:
    return _train("motion=library", f"motion.clips=[{{path: {ws.npz('lib_a', None)}, end_s: 1e308}}]")


def _copy_with(name: str, edit) -> callable:
    """A copy of the fixture run changed by `edit(run)`; returns the copy."""
    def make(ws: Workspace) -> Path:
        run = ws.root / "copies" / name
        if not run.exists():
            shutil.copytree(ws.run, run)
            edit(run)
        return run
    return make


def _edit_config(old: str, new: str):
    def edit(run: Path) -> None:
        cfg = run / ".hydra" / "config.yaml"
        text = cfg.read_text()
        assert old in text, old
        cfg.write_text(text.replace(old, new, 1))
    return edit


def _unrecorded_env(value: str):
    """A shared run whose config reads an environment variable and that records no resolved values
    (resolved_config.json, written since issue 47): nothing says what the variable held when it
    trained. (With the record, eval takes the recorded values and never reads the reader's.)"""
    def edit(run: Path) -> None:
        _edit_config("name: easy_only", f"name: {value}")(run)
        (run / "resolved_config.json").unlink()
    return edit


def _other_task(run: Path) -> None:
    """The copy now says it trained on an 8 s motion: its checkpoints (7 s) are another run's."""
    _edit_config("duration_s: 7", "duration_s: 8")(run)
    resolved = json.loads((run / "resolved_config.json").read_text())
    resolved["motion"]["duration_s"] = 8.0
    (run / "resolved_config.json").write_text(json.dumps(resolved))


def _set_iter(value):
    def edit(run: Path) -> None:
        for p in (run / "checkpoints").glob("*.pt"):
            state = torch.load(p, weights_only=True)
            state["iter"] = value
            torch.save(state, p)
    return edit


def _table_without(table: str, column: str):
    def edit(run: Path) -> None:
        path = run / table
        pd.read_parquet(path).drop(columns=[column]).to_parquet(path)
    return edit


def _corrupt(relative: str, data: bytes, with_eval: bool = False):
    def edit(run: Path) -> None:
        if with_eval:  # a bmimic.eval result of the latest checkpoint, then damaged
            folder = run / "eval" / "model_2"
            folder.mkdir(parents=True, exist_ok=True)
            shutil.copy(run / "eval.parquet", folder / "eval_bins.parquet")
            (folder / "eval_summary.json").write_text("{}")
        (run / relative).write_bytes(data)
    return edit


def _onnx_metadata(**changes: str):
    """Edit the metadata of a run copy's motion_policy ONNX files in place."""
    def edit(run: Path) -> None:
        import onnx

        for path in (run / "checkpoints").glob("motion_policy_*.onnx"):
            proto = onnx.load(str(path))
            for entry in proto.metadata_props:
                if entry.key in changes:
                    entry.value = changes[entry.key]
            onnx.save(proto, str(path))
    return edit


def _onnx_with(name: str, **changes: str) -> callable:
    """A copy of the fixture's motion_policy ONNX with metadata values replaced."""
    def args(ws: Workspace) -> list[str]:
        import onnx

        src = max((ws.run / "checkpoints").glob("motion_policy_*.onnx"))
        out = ws.data / f"{name}.onnx"
        proto = onnx.load(str(src))
        for entry in proto.metadata_props:
            if entry.key in changes:
                entry.value = changes[entry.key](entry.value) if callable(changes[entry.key]) else changes[entry.key]
        onnx.save(proto, str(out))
        return [str(out)]
    return args


def _nan_threshold(value: str) -> str:
    terms = json.loads(value)
    for t in terms:
        t["params"] = {k: float("nan") for k in t["params"]}
    return json.dumps(terms)


def _a_file(ws: Workspace) -> Path:
    path = ws.data / "a_file.txt"
    path.write_text("not a folder\n")
    return path


def _other_motion_run(ws: Workspace) -> Path:
    """A copy of the fixture that claims another motion (its config says motion.name: other)."""
    return _copy_with("other_motion", _edit_config("name: easy_only", "name: other"))(ws)


@contextlib.contextmanager
def _read_only(ws: Workspace, where: str = "copies"):
    """Writes below ws.root/<where> are refused as in an immutable folder (root ignores chmod)."""
    try:
        from bmimic.runs import atomic_io
    except ImportError:  # bmimic before issue 36 (the survey of the unfixed code)
        from bmimic.runs import folder as atomic_io

    real = atomic_io.tempfile.mkstemp
    folder = str(ws.root / where)

    def mkstemp(*a, dir=None, **k):
        if dir is not None and str(dir).startswith(folder):
            raise PermissionError(errno.EPERM, "Operation not permitted")
        return real(*a, dir=dir, **k)

    atomic_io.tempfile.mkstemp = mkstemp
    try:
        yield
    finally:
        atomic_io.tempfile.mkstemp = real


def _nan_weights(run: Path) -> None:
    """Every actor weight NaN: a policy whose actions break every world on its first step."""
    for p in (run / "checkpoints").glob("*.pt"):
        state = torch.load(p, weights_only=True)
        state["actor_state_dict"] = {k: torch.full_like(v, float("nan")) if v.is_floating_point() else v
                                     for k, v in state["actor_state_dict"].items()}
        torch.save(state, p)
    for p in (run / "checkpoints").glob("*.onnx"):
        p.unlink()  # written again from the NaN weights by bmimic.export where a case needs them


def _summary(run: Path, tool: str = "eval") -> dict:
    folder = run / "eval" if tool == "eval" else run / "sim2sim" / "bmimic_g1"
    (summary,) = folder.glob("*/eval_summary.json")
    return json.loads(summary.read_text())


def _all_broken(name: str, tool: str = "eval"):
    """The evaluation of copy `name` failed every episode, each because its world broke."""
    def check(ws: Workspace, res: Result) -> bool:
        s = _summary(ws.root / "copies" / name, tool)
        return s["eval_success_rate"] == 0.0 and s["eval_broken"] == s["episodes"] > 0
    return check


def _report_counts_copy_once(ws: Workspace, res: Result) -> bool:
    runs = pd.read_csv(ws.root / "copies" / "report_dup" / "runs.csv")
    return int(runs["included"].sum()) == 1 and runs["problem"].fillna("").str.contains("byte-identical").any()


def cases() -> list[Case]:
    c: list[Case] = []
    add = c.append
    # ---------------------------------------------------------------- config values (one line, exit 2)
    for arg, key in ((f"seed=${{oc.env:{UNSET}}}", "seed"), ("max_iterations=${oc.env:HOME}", "max_iterations"),
                     ("~seed", "seed"), ("~device", "device"), ("~sampler", "sampler"),
                     ("seed=18446744073709551616", "seed"),
                     ("ppo.actor_hidden_dims=[]", "actor_hidden_dims"),
                     ("ppo.critic_hidden_dims=[]", "critic_hidden_dims"),
                     ("ppo.actor_hidden_dims=[1000000000]", "actor_hidden_dims"),
                     ("sim.timestep_s=1e-300", "timestep_s"), ("hydra.run.dir=/proc/x", "/proc/x"),
                     ("env.rewards.action_rate.func=bmimic.envs.mdp.terminations:bad_anchor_ori", "action_rate"),
                     ("env.terminations.anchor_pos.func=bmimic.envs.mdp.rewards:action_rate_l2", "anchor_pos"),
                     ("env.rewards.action_rate.func=bmimic.motion.math:output_times", "action_rate")):
        add(Case(f"train {arg}", "train", _train(arg), match=key))
    # ---------------------------------------------------------------- motion rates and windows
    add(Case("csv motion.fps_in=1e-300", "train", lambda ws: _train(
        "motion=file", f"motion.path={ws.csv('tiny_fps')}", "motion.fps_in=1e-300"), match="fps"))
    add(Case("npz fps 1e-300", "train", lambda ws: _train(
        "motion=file", f"motion.path={ws.npz('fps_tiny', lambda d: d.update(fps=np.asarray([1e-300])))}"),
        match="fps"))
    add(Case("library end_s 1e308", "train", _library_end, match="end_s"))
    add(Case("convert --fps-in 1e-300", "convert", lambda ws: [str(ws.csv("conv_tiny")), str(ws.data / "c1.npz"),
                                                              "--fps-in", "1e-300"], match="fps"))
    add(Case("convert --fps-out 1e300", "convert", lambda ws: [str(ws.csv("conv_huge")), str(ws.data / "c2.npz"),
                                                              "--fps-out", "1e300"], match="fps"))
    # ---------------------------------------------------------------- broken worlds stop a run in one line
    add(Case("train sim.max_abs_qvel=1e-6, below the motion's own speeds", "train",
             _train("sim.max_abs_qvel=1e-6", iters=3), match="max_abs_qvel"))
    for name, args in (("ppo.learning_rate=1e10", lambda ws: _train("ppo.learning_rate=1e10", iters=3)),
                       ("motion root z = -100 m", _npz_arg("z_minus_100", _shift_z(-100.0), "motion.check_plausible=false"))):
        match = "learning_rate" if "learning" in name else "broken"
        add(Case(f"train {name} stops in one line", "train", args, match=match, slow=True, leaves_launch_dir=True))
    add(Case("train a motion with velocities of 1e30", "train", _npz_arg("vel_1e30", lambda d: d.update(
        joint_vel=np.full_like(d["joint_vel"], 1e30), body_lin_vel_w=np.full_like(d["body_lin_vel_w"], 1e30))),
        match="max_abs_qvel"))
    # ---------------------------------------------------------------- broken worlds are failures
    add(Case("eval: a policy whose weights are NaN is refused (issue 77: was evaluated as every episode failing)",
             "eval", lambda ws: [str(_copy_with("nan_eval", _nan_weights)(ws)), "--episodes-per-bin", "1"],
             match="NaN or infinite"))
    add(Case("eval: sim.max_abs_qvel=1e-6, below the motion's own speeds", "eval", lambda ws: [
        str(_copy_with("qvel_eval", lambda r: None)(ws)), "sim.max_abs_qvel=1e-6", "--episodes-per-bin", "1"],
        match="max_abs_qvel"))
    add(Case("eval: on a motion 100 m below the floor every episode fails", "eval", lambda ws: [
        str(_copy_with("z_eval", lambda r: None)(ws)), "motion.source=file",
        f"motion.path={ws.npz('z_eval_motion', _shift_z(-100.0))}", "motion.check_plausible=false",
        "--episodes-per-bin", "1"], "accept",
        check=_all_broken("z_eval")))
    add(Case("export: a policy whose weights are NaN is refused, so no ONNX of it reaches sim2sim", "export",
             lambda ws: [str(_copy_with("nan_s2s", _nan_weights)(ws))], match="NaN or infinite"))
    add(Case("sim2sim: sim_max_abs_qvel=1e-6 breaks every world, so every episode fails", "sim2sim", lambda ws: [
        str(_copy_with("qvel_s2s", _onnx_metadata(sim_max_abs_qvel="1e-06"))(ws)), "--episodes-per-bin", "1"],
        "accept", check=_all_broken("qvel_s2s", "sim2sim")))
    # ---------------------------------------------------------------- run folders
    add(Case("train into the pinned folder of a finished run, no resume", "train",
             lambda ws: _train(f"hydra.run.dir={ws.run}"), match="resume=true"))
    add(Case("resume a run whose train_metrics.parquet lacks iteration", "train", lambda ws: _train(
        f"resume={_copy_with('no_iter_col', _table_without('train_metrics.parquet', 'iteration'))(ws)}",
        "run_name=fixture", iters=3), match="iteration"))
    add(Case("resume an immutable run", "train", lambda ws: _train(
        f"resume={_copy_with('immutable_train', lambda r: None)(ws)}", "run_name=fixture", iters=3),
        match="cannot write", patch=_read_only))
    # ---------------------------------------------------------------- eval
    for name, args, match in (
        ("override interpolating an unset variable", lambda ws: [str(ws.run), f"seed=${{oc.env:{UNSET}}}"], "seed"),
        ("shared config interpolating an unset variable", lambda ws: [str(_copy_with(
            "env_unset", _unrecorded_env(f"${{oc.env:{UNSET}}}"))(ws))], "environment"),
        ("shared config reading the reader's environment", lambda ws: [str(_copy_with(
            "env_secret", _unrecorded_env("${oc.env:HOME}"))(ws))], "environment"),
        ("checkpoint of another run", lambda ws: [str(_copy_with("other_task", _other_task)(ws))], "duration_s"),
        ("checkpoint iter 1e30", lambda ws: [str(_copy_with("iter_huge", _set_iter(10**30))(ws))], "iter"),
        ("checkpoint iter a string", lambda ws: [str(_copy_with("iter_text", _set_iter("two"))(ws))], "iter"),
        ("--episodes-per-bin 100000000", lambda ws: [str(ws.run), "--episodes-per-bin", "100000000"],
         "episodes_per_bin"),
        ("--out an existing file", lambda ws: [str(ws.run), "--out", str(_a_file(ws)), "--episodes-per-bin", "1"],
         "a_file.txt"),
    ):
        add(Case(f"eval: {name}", "eval", args, match=match))
    add(Case("eval: an immutable run folder", "eval", lambda ws: [
        str(_copy_with("immutable_eval", lambda r: None)(ws)), "--episodes-per-bin", "1"], match="cannot write",
        patch=_read_only))
    # ---------------------------------------------------------------- play, export
    for name, args, match in (
        ("--fps nan", lambda ws: [str(ws.run), "--fps", "nan"], "--fps"),
        ("--seconds nan", lambda ws: [str(ws.run), "--seconds", "nan"], "--seconds"),
        ("--seconds 1e9", lambda ws: [str(ws.run), "--seconds", "1e9"], "--seconds"),
        ("--width 100000", lambda ws: [str(ws.run), "--width", "100000", "--height", "100000"], "--width"),
    ):
        add(Case(f"play: {name}", "play", args, match=match))
    add(Case("export: --out an existing file", "export", lambda ws: [str(ws.run), "--out", str(_a_file(ws))],
             match="a_file.txt"))
    # ---------------------------------------------------------------- sim2sim
    for name, args, match in (
        ("--horizon-s inf", lambda ws: [str(ws.run), "--horizon-s", "inf"], "horizon"),
        ("--horizon-s nan", lambda ws: [str(ws.run), "--horizon-s", "nan"], "horizon"),
        ("--episodes-per-bin 100000000", lambda ws: [str(ws.run), "--episodes-per-bin", "100000000"],
         "episodes-per-bin"),
        ("corrupt eval_summary.json", lambda ws: [str(_copy_with("s2s_summary", _corrupt(
            "eval/model_2/eval_summary.json", b"{not json", with_eval=True))(ws))], "eval_summary.json"),
        ("corrupt eval.parquet", lambda ws: [str(_copy_with("s2s_parquet", _corrupt(
            "eval.parquet", b"PAR1 broken"))(ws))], "eval.parquet"),
        ("eval.parquet without its iteration column", lambda ws: [str(_copy_with(
            "s2s_nocol", _table_without("eval.parquet", "iteration"))(ws))], "iteration"),
        ("--out an existing file", lambda ws: [str(ws.run), "--out", str(_a_file(ws))], "a_file.txt"),
        ("motion_fps unlike the control rate", _onnx_with("fps5", motion_fps="5.0"), "motion_fps"),
        ("a NaN termination threshold", _onnx_with("nan_threshold", terminations=_nan_threshold), "threshold"),
        ("motion_num_frames 1e9", _onnx_with("frames1e9", motion_num_frames="1000000000"), "motion_num_frames"),
    ):
        add(Case(f"sim2sim: {name}", "sim2sim", args, match=match))
    # ---------------------------------------------------------------- report
    for name, args, match in (
        ("--resamples 0", lambda ws: [str(ws.run), "--resamples", "0"], "--resamples"),
        ("--resamples -5", lambda ws: [str(ws.run), "--resamples", "-5"], "--resamples"),
        ("--mastery-threshold nan", lambda ws: [str(ws.run), "--mastery-threshold", "nan"], "--mastery-threshold"),
        ("--mastery-threshold 2", lambda ws: [str(ws.run), "--mastery-threshold", "2"], "--mastery-threshold"),
        ("--success-threshold -1", lambda ws: [str(ws.run), "--success-threshold", "-1"], "--success-threshold"),
        ("--out an existing file", lambda ws: [str(ws.run), "--out", str(_a_file(ws))], "a_file.txt"),
        ("runs of different motions", lambda ws: [str(ws.run), str(_other_motion_run(ws)), "--out",
                                                  str(ws.root / "copies" / "report_mixed")], "--allow-mixed"),
    ):
        add(Case(f"report: {name}", "report", args, match=match))
    add(Case("report: an immutable report folder", "report", lambda ws: [
        str(ws.run), "--out", str(ws.root / "copies" / "report_ro"), "--resamples", "20"], match="cannot write",
        patch=_read_only))
    add(Case("report: a byte-identical copy is counted once", "report", lambda ws: [
        str(ws.run), str(_copy_with("dup", lambda r: None)(ws)), "--out", str(ws.root / "copies" / "report_dup"),
        "--resamples", "20"], "accept", check=_report_counts_copy_once, slow=True))
    # ---------------------------------------------------------------- sweep dry run
    for name, args, match in (
        ("jobs sharing a folder (num_envs=4,8)", ["num_envs=4,8"], "one folder"),
        ("jobs sharing a folder (eval.every_iters=1,2)", ["eval.every_iters=1,2"], "one folder"),
        ("a job the sweep would refuse", ["sampler.gamma=0,0.5"], "sampler.gamma"),
        ("sweep_name=../..", ["sweep_name=../.."], "sweep_name"),
    ):
        add(Case(f"launch list: {name}", "launch", args, match=match))
    return c


ALL = cases()


@pytest.fixture(scope="module")
def ws(tmp_path_factory) -> Workspace:
    return Workspace(tmp_path_factory.mktemp("bad_inputs_36"))


@pytest.mark.parametrize("case", [pytest.param(c, id=c.id, marks=[pytest.mark.slow] if c.slow else [])
                                  for c in ALL])
def test_issue_36_case(ws: Workspace, case: Case) -> None:
    os.environ.pop(UNSET, None)
    kind, detail = classify(ws, case)
    assert kind == EXPECTED[case.expect], f"{kind}: {detail}"


def test_cases_are_distinct() -> None:
    assert len({c.id for c in ALL}) == len(ALL) >= 60


if __name__ == "__main__":
    import argparse
    import tempfile

    p = argparse.ArgumentParser(description="Run every case of issue 36 and count the outcomes.")
    p.add_argument("--fast", action="store_true", help="skip the cases that train")
    a = p.parse_args()
    result = survey(Path(tempfile.mkdtemp(prefix="bmimic-bad-inputs-36-")), include_slow=not a.fast, cases=ALL)
    bad = sum(result[k] for k in CLASSES if k not in EXPECTED.values())
    sys.exit(1 if bad else 0)
