"""Training continues across sittings exactly: N + M iterations in two legs (a pause, then resume=true)
equal one unbroken run of N + M, tensors and tables alike, wall-clock fields aside; and a study's state
file (bmimic.state) carries a job into a fresh run folder, with its bad inputs refused."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pandas as pd
import pytest
import torch

from tests.conftest import TINY, cli_env

pytestmark = pytest.mark.slow

# An evaluation every 2 iterations, the pause after iteration 2 (an evaluated one) and a robust final
# evaluation at the pause: it must draw nothing from training's random streams. Pushes and observation
# noise are on (training), so every world's state and the noisy observation must carry over.
BASE = [a for a in TINY if not a.startswith("max_iterations")] + [
    "max_iterations=5", "eval.every_iters=2", "ppo.save_interval=2", "sampler=adaptive", "sampler.log_every=1",
    "eval.robust=true", "logger=none"]
WALL_CLOCK = {"wall_time_s", "fps", "collection_time_s", "learning_time_s"}


def train(args, cwd):
    out = subprocess.run([sys.executable, "-m", "bmimic.train", *args], cwd=cwd, capture_output=True, text=True,
                         timeout=900, env=cli_env())
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    return out


def state_cli(args, cwd):
    return subprocess.run([sys.executable, "-m", "bmimic.state", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300, env=cli_env())


@pytest.fixture(scope="module")
def legs(tmp_path_factory):
    root = tmp_path_factory.mktemp("legs")
    whole, split = root / "whole", root / "split"
    train([*BASE, f"hydra.run.dir={whole}"], cwd=root)
    first = train([*BASE, f"hydra.run.dir={split}", "stop_at_iteration=2"], cwd=root)
    assert "paused at iteration 2" in first.stdout + first.stderr
    second = train([*BASE, f"hydra.run.dir={split}", "resume=true"], cwd=root)
    assert "start afresh" not in second.stdout + second.stderr  # the worlds carried over
    return root, whole, split


def tensors(tree, prefix=""):
    """{'a.b': tensor-or-value} of a nested checkpoint dict."""
    if isinstance(tree, dict):
        out = {}
        for k, v in tree.items():
            out.update(tensors(v, f"{prefix}{k}."))
        return out
    if isinstance(tree, (list, tuple)):
        out = {}
        for i, v in enumerate(tree):
            out.update(tensors(v, f"{prefix}{i}."))
        return out
    return {prefix[:-1]: tree}


def assert_same_checkpoint(a, b):
    a, b = tensors(a), tensors(b)
    assert set(a) == set(b)
    for key in a:
        if key.endswith("wall_time_s") or key == "config":  # the config records each launch's own run folder
            continue
        x, y = a[key], b[key]
        if isinstance(x, torch.Tensor):
            assert x.dtype == y.dtype and torch.equal(x, y), key
        else:
            assert x == y, key


def test_two_legs_equal_one_run(legs):
    _, whole, split = legs
    a = torch.load(whole / "checkpoints" / "latest.pt", weights_only=True)
    b = torch.load(split / "checkpoints" / "latest.pt", weights_only=True)
    assert a["iter"] == b["iter"] == 5
    assert "env" in a and a["env"]["tensors"]["sim.qpos"].shape[0] == 2  # the worlds are in the checkpoint
    assert_same_checkpoint(a, b)
    for table in ("train_metrics", "sampler", "eval"):
        x, y = (pd.read_parquet(run / f"{table}.parquet") for run in (whole, split))
        keep = [c for c in x.columns if c not in WALL_CLOCK]
        assert list(x.columns) == list(y.columns), table
        pd.testing.assert_frame_equal(x[keep], y[keep], check_exact=True, obj=table)
    assert list(pd.read_parquet(split / "train_metrics.parquet")["iteration"]) == list(range(5))


def test_mid_run_checkpoint_equals_unbroken_run(legs):
    """The paused leg's checkpoint at iteration 2 is the unbroken run's model_2.pt, worlds included."""
    _, whole, split = legs
    a = torch.load(whole / "checkpoints" / "model_2.pt", weights_only=True)
    b = torch.load(split / "checkpoints" / "model_2.pt", weights_only=True)
    assert_same_checkpoint(a, b)


def test_state_file_carries_a_job_to_a_new_folder(legs, tmp_path):
    root, whole, split = legs
    state = tmp_path / "state" / "job.pt"
    state.parent.mkdir()
    out = state_cli(["save", str(split), str(state), "--moments", "bf16"], cwd=root)
    assert out.returncode == 0, out.stderr
    saved = torch.load(state, weights_only=True)
    assert saved["format"] == "bmimic-state-1" and "env" not in saved and saved["iter"] == 5
    moments = [v for s in saved["optimizer_state_dict"]["state"].values() for v in s.values()
               if isinstance(v, torch.Tensor) and v.dim() > 0]
    assert moments and all(m.dtype == torch.bfloat16 for m in moments)
    full = torch.load(split / "checkpoints" / "latest.pt", weights_only=True)
    for k, v in full["actor_state_dict"].items():  # the weights stay exact
        assert torch.equal(saved["actor_state_dict"][k], v)
    # the next sitting: the committed record (no checkpoints) in a fresh folder, the state restored into it
    sitting = root / "sitting_carried"  # under the launch's working directory, as a study's outputs/ are
    shutil.copytree(split, sitting, ignore=shutil.ignore_patterns("checkpoints", ".lock*"))
    compact(sitting)  # as committed: no hydra.yaml, portable paths
    out = state_cli(["restore", str(state), str(sitting)], cwd=root)
    assert out.returncode == 0, out.stderr
    restored = torch.load(sitting / "checkpoints" / "latest.pt", weights_only=True)
    assert restored["iter"] == 5 and restored["format"] == full["format"]
    for k, v in full["optimizer_state_dict"]["state"].items():
        for n, t in v.items():
            got = restored["optimizer_state_dict"]["state"][k][n]
            assert got.dtype == t.dtype
            # bf16: within one unit in the last place; float32 subnormals (< 2**-126) may round to 0
            assert torch.allclose(got, t, rtol=2**-7, atol=2**-126), n
    train([*BASE, "max_iterations=6", f"hydra.run.dir={sitting}", "resume=true"], cwd=root)
    assert list(pd.read_parquet(sitting / "train_metrics.parquet")["iteration"]) == list(range(6))
    assert torch.load(sitting / "checkpoints" / "latest.pt", weights_only=True)["iter"] == 6
    # the resumed record compacts to a portable one again (the resume's own hydra.yaml names this machine's
    # folders): no folder of this machine stays a record's value (the legs' command lines name theirs)
    again = tmp_path / "again"
    shutil.copytree(sitting, again, ignore=shutil.ignore_patterns("checkpoints", ".lock*", "train.log"))
    compact(again)
    assert not [(p.name, v) for p in again.rglob("*.json") for v in strings(json.loads(p.read_text()))
                if v.startswith(str(root))]
    # the state may replace its own earlier version, never another job's or a foreign file
    out = state_cli(["save", str(sitting), str(state)], cwd=root)
    assert out.returncode == 0, out.stderr
    assert torch.load(state, weights_only=True)["iter"] == 6


def strings(tree):
    """Every string value of a JSON tree."""
    if isinstance(tree, dict):
        return [s for v in tree.values() for s in strings(v)]
    if isinstance(tree, list):
        return [s for v in tree for s in strings(v)]
    return [tree] if isinstance(tree, str) else []


def compact(folder):
    out = subprocess.run([sys.executable, "-m", "analysis.compact", str(folder)], capture_output=True, text=True,
                         timeout=300, env=cli_env())
    assert out.returncode == 0, out.stderr


def refused(args, cwd, *needles):
    out = state_cli(args, cwd)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: "), out.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


def test_bad_states_are_refused_and_nothing_written(legs, tmp_path):
    root, whole, split = legs
    state = tmp_path / "job.pt"
    assert state_cli(["save", str(split), str(state)], cwd=root).returncode == 0
    sitting = tmp_path / "sitting"
    shutil.copytree(split, sitting, ignore=shutil.ignore_patterns("checkpoints", ".lock*"))

    def untouched():
        return sorted(p.relative_to(sitting).as_posix() for p in sitting.rglob("*"))
    before = untouched()
    # damaged (truncated) state
    damaged = tmp_path / "damaged.pt"
    damaged.write_bytes(state.read_bytes()[:2000])
    refused(["restore", str(damaged), str(sitting)], root, str(damaged), "not a readable")
    # a newer format
    newer = tmp_path / "newer.pt"
    s = torch.load(state, weights_only=True)
    torch.save({**s, "format": "bmimic-state-9"}, newer)
    refused(["restore", str(newer), str(sitting)], root, str(newer), "bmimic-state-9", "newer")
    # a plain checkpoint is not a state
    refused(["restore", str(split / "checkpoints" / "latest.pt"), str(sitting)], root, "not a bmimic state")
    # a state whose result-changing config differs from the record's
    other = tmp_path / "other.pt"
    import json
    cfg = json.loads(s["config"])
    cfg["sampler"]["gamma"] = 0.5
    torch.save({**s, "config": json.dumps(cfg)}, other)
    refused(["restore", str(other), str(sitting)], root, "another job", "sampler.gamma")
    # a state ahead of the record's tables
    ahead = tmp_path / "ahead.pt"
    torch.save({**s, "iter": 50}, ahead)
    refused(["restore", str(ahead), str(sitting)], root, "iteration 50")
    assert untouched() == before
    # a run folder that already holds a checkpoint is not overwritten
    latest = split / "checkpoints" / "latest.pt"
    stamp = latest.read_bytes()
    refused(["restore", str(state), str(split)], root, "already holds a checkpoint")
    assert latest.read_bytes() == stamp
    # save never replaces a foreign file, nor another job's state
    foreign = tmp_path / "notes.pt"
    foreign.write_text("mine")
    refused(["save", str(split), str(foreign)], root, str(foreign), "not a state this command may replace")
    assert foreign.read_text() == "mine"
    refused(["save", str(split), str(other)], root, "another job")


def test_a_failed_final_export_fails_the_run(tmp_path):
    """A full disk at the final ONNX export: the run ends `failed` (one error line, exit 2), never `done`
    without the file its record lists; the checkpoint is there for resume=true (issue 77)."""
    run = tmp_path / "run"
    code = ("import sys, errno\nimport bmimic.training.onnx_export as o\n"
            "def full(*a, **k):\n    raise OSError(errno.ENOSPC, 'No space left on device')\n"
            "o.export_checkpoint_onnx = full\nfrom bmimic.train import cli\n"
            f"sys.argv = ['bmimic.train', *{[*TINY, 'logger=none', f'hydra.run.dir={run}']!r}]\ncli()\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=900,
                         env=cli_env())
    errors = [line for line in out.stderr.splitlines() if line.startswith("error:")]
    assert out.returncode == 2 and len(errors) == 1 and "ONNX export of the final checkpoint" in errors[0], out.stderr
    import json
    assert json.loads((run / "status.json").read_text())["status"] == "failed"
    assert (run / "checkpoints" / "latest.pt").is_file()
