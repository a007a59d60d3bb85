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
