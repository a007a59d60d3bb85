"""The committed library policy is one a user can pick up (issue 73, step 5): restored from its
committed state and record, evaluated on a clip it never saw (the synthetic example clip), and exported
with that clip baked in, on a CPU, without the LAFAN1 clips it was trained on."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest

from tests.conftest import REPO, cli_env

pytestmark = pytest.mark.slow

STUDY = REPO / "docs" / "results" / "lafan36_whole"
JOB = "motion=lafan_folder,sampler=adaptive_hybrid/seed=0"


def _run(*args: str, cwd, lafan_dir=None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in cli_env().items() if k != "BMIMIC_LAFAN_DIR"}  # the training clips are not needed
    if lafan_dir is not None:
        env["BMIMIC_LAFAN_DIR"] = str(lafan_dir)
    return subprocess.run([sys.executable, "-m", *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=900)


@pytest.mark.skipif(not (STUDY / "state" / "adaptive_hybrid-s0.pt").is_file(), reason="no committed library state")
def test_the_committed_library_policy_evaluates_and_exports_on_a_clip_it_never_saw(tmp_path):
    shutil.copytree(STUDY / "runs" / JOB, tmp_path / "run")
    # restore records where the clips sit (a resume compares it), so it asks for the folder, not its clips
    (tmp_path / "clips").mkdir()
    restored = _run("bmimic.state", "restore", str(STUDY / "state" / "adaptive_hybrid-s0.pt"), "run", cwd=tmp_path,
                    lafan_dir=tmp_path / "clips")
    assert restored.returncode == 0, restored.stderr
    assert _run("bmimic.motion.example", "clip.csv", cwd=tmp_path).returncode == 0

    evaluated = _run("bmimic.eval", "run", "motion=clip.csv", "--device", "cpu", "--episodes-per-bin", "1",
                     "--horizon-s", "0.5", cwd=tmp_path)
    assert evaluated.returncode == 0, evaluated.stderr[-2000:]
    summaries = list((tmp_path / "run" / "eval").glob("model_*_on_clip-*/eval_summary.json"))
    assert len(summaries) == 1
    summary = json.loads(summaries[0].read_text())
    # the committed policy, whichever sitting committed it last: its record's iteration times the steps per iteration
    record = STUDY / "runs" / JOB
    iteration = json.loads((record / "status.json").read_text())["iteration"]
    config = json.loads((record / "resolved_config.json").read_text())
    assert 0.0 <= summary["eval_success_rate"] <= 1.0
    assert summary["env_steps"] == iteration * config["num_envs"] * config["ppo"]["num_steps_per_env"]

    refused = _run("bmimic.export", "run", "motion=clip.csv", cwd=tmp_path)
    assert refused.returncode == 2 and refused.stderr.strip().startswith("error:") and "--out" in refused.stderr
    exported = _run("bmimic.export", "run", "motion=clip.csv", "--out", "onnx", cwd=tmp_path)
    assert exported.returncode == 0, exported.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "onnx").iterdir()) == [f"motion_policy_{iteration}.onnx",
                                                                     f"policy_{iteration}.onnx"]


def _library_clips():
    import os
    from pathlib import Path

    folder = os.environ.get("BMIMIC_LAFAN_DIR")
    return Path(folder) if folder and len(list(Path(folder).glob("*.csv"))) >= 36 else None


@pytest.mark.skipif(_library_clips() is None, reason="the 36 LAFAN1 clips are absent (not shipped: CC BY-NC-ND); "
                    "set BMIMIC_LAFAN_DIR to a folder of them to run this")
def test_a_restored_state_loads_for_evaluation_on_its_own_clips(tmp_path, monkeypatch):
    """The library's fifth sitting: the committed record names the clips' folder $BMIMIC_LAFAN_DIR while the
    restored checkpoint names this machine's, and `bmimic.eval RUN` refused it as trained on another task.
    Both now read as this machine's folder before they are compared."""
    from bmimic.evaluation.saved_run import load_run, load_run_checkpoint

    clips = _library_clips()
    shutil.copytree(STUDY / "runs" / JOB, tmp_path / "run")
    restored = _run("bmimic.state", "restore", str(STUDY / "state" / "adaptive_hybrid-s0.pt"), "run", cwd=tmp_path,
                    lafan_dir=clips)
    assert restored.returncode == 0, restored.stderr
    monkeypatch.setenv("BMIMIC_LAFAN_DIR", str(clips))
    run = load_run(tmp_path / "run", ["device=cpu"])
    assert load_run_checkpoint(run)["iter"] == json.loads((tmp_path / "run" / "status.json").read_text())["iteration"]
