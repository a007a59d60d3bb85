"""`python -m bmimic.bench` runs end to end on the CPU and writes its JSON."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.conftest import REPO, cli_env


@pytest.mark.slow
def test_bench_cli_on_cpu(tmp_path):
    out = tmp_path / "bench.json"
    proc = subprocess.run(
        [sys.executable, "-m", "bmimic.bench", "--envs", "2", "--iters", "1", "--device", "cpu", "--json", str(out),
         "--", "motion=easy_only", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2"],
        cwd=REPO, capture_output=True, text=True, timeout=900, env=cli_env(),
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    run = result["runs"][0]
    assert run["num_envs"] == 2 and not run["cuda_graph"]
    for key in ("physics_steps_per_s", "collect_steps_per_s", "train_steps_per_s", "collect_over_physics"):
        assert run[key] > 0, key
    assert set(run["breakdown_ms"]) >= {"physics", "observations", "rewards", "resets", "policy", "env_step_total"}
    assert 0 < run["ppo_update_s"] < run["iteration_s"]  # the update is one part of an iteration
    assert result["environment"]["torch"] and "envs | physics/s" in proc.stdout
