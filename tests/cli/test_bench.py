"""`python -m bmimic.bench` runs end to end on the CPU and writes its JSON."""

from __future__ import annotations

import json
import math
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
    # Structure only: every measurement is there and is a positive, finite number. Speed itself is
    # what benchmarks measure (docs/benchmarks.md); timings taken on a shared CI machine prove nothing.
    for key in ("physics_steps_per_s", "collect_steps_per_s", "train_steps_per_s", "collect_over_physics",
                "ppo_update_s", "iteration_s"):
        assert math.isfinite(run[key]) and run[key] > 0, key
    assert set(run["breakdown_ms"]) >= {"physics", "observations", "rewards", "resets", "policy", "env_step_total"}
    assert all(math.isfinite(v) and v >= 0 for v in run["breakdown_ms"].values())
    assert result["environment"]["torch"]
    lines = proc.stdout.splitlines()
    header = lines.index("envs | physics/s | collect/s | train/s | b/a | c/a | GiB")
    assert lines[header + 1].split(" | ")[0] == "2" and len(lines[header + 1].split(" | ")) == 7
    assert any(line.startswith("PPO iteration at 2 envs: ") for line in lines)
    assert any(line.startswith("breakdown at 2 envs (ms per env step): physics ") for line in lines)
