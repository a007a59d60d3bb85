"""`python -m bmimic.bench` runs end to end on the CPU and writes its JSON."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import pytest

from tests.conftest import RANKS_GROUP, REPO, cli_env


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
    assert (run["sampler"], run["motion"]) == ("adaptive", "easy_only")  # what was timed, not only how fast
    # Structure only: every measurement is there and is a positive, finite number. Speed itself is
    # what benchmarks measure (docs/benchmarks.md); timings taken on a shared CI machine prove nothing.
    for key in ("physics_steps_per_s", "collect_steps_per_s", "train_steps_per_s", "collect_over_physics",
                "ppo_update_s", "iteration_s"):
        assert math.isfinite(run[key]) and run[key] > 0, key
    assert set(run["breakdown_ms"]) >= {"physics", "observations", "rewards", "resets", "policy", "env_step_total"}
    assert all(math.isfinite(v) and v >= 0 for v in run["breakdown_ms"].values())
    assert result["environment"]["torch"]
    assert "git_commit" in result["environment"] and "git_dirty" in result["environment"]
    lines = proc.stdout.splitlines()
    header = lines.index("envs | physics/s | collect/s | train/s | b/a | c/a | GiB")
    assert lines[header + 1].split(" | ")[0] == "2" and len(lines[header + 1].split(" | ")) == 7
    assert any(line.startswith("PPO iteration at 2 envs: ") for line in lines)
    assert any(line.startswith("breakdown at 2 envs (ms per env step): physics ") for line in lines)


def test_multigpu_rows_merge_and_scale_against_one_gpu(tmp_path):
    from bmimic.bench import merge_multigpu_rows

    path = tmp_path / "multigpu.json"
    rows = merge_multigpu_rows(path, [{"gpus": 2, "num_envs_per_gpu": 4096, "env_steps_per_s": 760.0}])
    assert rows == [{"gpus": 2, "num_envs_per_gpu": 4096, "env_steps_per_s": 760.0, "scaling": None}]
    merge_multigpu_rows(path, [{"gpus": 1, "num_envs_per_gpu": 4096, "env_steps_per_s": 400.0},
                               {"gpus": 1, "num_envs_per_gpu": 8192, "env_steps_per_s": 500.0}])
    # A repeated measurement replaces its row; scaling is against the 1-GPU row of the same envs per GPU.
    rows = merge_multigpu_rows(path, [{"gpus": 4, "num_envs_per_gpu": 4096, "env_steps_per_s": 1440.0},
                                      {"gpus": 2, "num_envs_per_gpu": 4096, "env_steps_per_s": 780.0}])
    assert rows == json.loads(path.read_text())
    assert [(r["gpus"], r["num_envs_per_gpu"], r["scaling"]) for r in rows] == [
        (1, 4096, 1.0), (2, 4096, 1.95), (4, 4096, 3.6), (1, 8192, 1.0)]
    assert set(rows[0]) == {"gpus", "num_envs_per_gpu", "env_steps_per_s", "scaling"}


@pytest.mark.parametrize("value", ["Infinity", "NaN", "-Infinity", "1e999"])
def test_multigpu_json_with_a_number_that_is_not_finite_is_refused_untouched(tmp_path, capsys, value):
    """Issue 77: `Infinity` passed the `> 0` check, was written back as null, and the next read refused it."""
    from bmimic import BmimicError
    from bmimic.bench import main, merge_multigpu_rows, read_multigpu_rows

    path = tmp_path / "multigpu.json"
    text = f'[{{"gpus": 1, "num_envs_per_gpu": 2, "env_steps_per_s": {value}, "scaling": 1.0}}]'
    path.write_text(text)
    with pytest.raises(BmimicError, match="not finite"):
        read_multigpu_rows(path)
    assert main(["--multigpu-json", str(path), "--device", "cpu", "--envs", "2", "--iters", "1"]) == 2
    (line,) = capsys.readouterr().err.strip().splitlines()
    assert line.startswith(f"error: {path}: ") and "not finite" in line
    assert path.read_text() == text
    # and a measurement that is not a positive finite rate is never written (JSON would hold null)
    fresh = tmp_path / "fresh.json"
    with pytest.raises(BmimicError, match="not a positive finite rate"):
        merge_multigpu_rows(fresh, [{"gpus": 2, "num_envs_per_gpu": 2, "env_steps_per_s": math.inf}])
    assert not fresh.exists()


@pytest.mark.slow
@pytest.mark.parametrize("text", ["{not json", '{"gpus": 1}', '[{"gpus": 0, "num_envs_per_gpu": 2, '
                                  '"env_steps_per_s": 1.0, "scaling": null}]'])
def test_multigpu_json_that_is_not_a_row_list_is_refused_untouched(tmp_path, text):
    path = tmp_path / "multigpu.json"
    path.write_text(text)
    proc = subprocess.run([sys.executable, "-m", "bmimic.bench", "--multigpu-json", str(path), "--device", "cpu"],
                          cwd=tmp_path, capture_output=True, text=True, timeout=300, env=cli_env())
    assert proc.returncode == 2
    (line,) = proc.stderr.strip().splitlines()
    assert line.startswith(f"error: {path}: ")
    assert path.read_text() == text


@RANKS_GROUP
@pytest.mark.slow
def test_multigpu_json_from_two_ranks_and_one(tmp_path):
    """The benchmark under torchrun (2 CPU ranks, gloo), then alone: one row each, scaled to the 1-rank row."""
    path = tmp_path / "multigpu.json"
    bench = ["-m", "bmimic.bench", "--device", "cpu", "--envs", "2", "--iters", "1", "--multigpu-json", str(path),
             "--", "motion=easy_only", "ppo.num_steps_per_env=4", "ppo.num_mini_batches=2"]
    for launcher in (["-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2"], []):
        proc = subprocess.run([sys.executable, *launcher, *bench], cwd=tmp_path, capture_output=True, text=True,
                              timeout=600, env=cli_env())
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-3000:]
    rows = json.loads(path.read_text())
    assert [(r["gpus"], r["num_envs_per_gpu"]) for r in rows] == [(1, 2), (2, 2)]
    assert all(math.isfinite(r["env_steps_per_s"]) and r["env_steps_per_s"] > 0 for r in rows)
    assert rows[0]["scaling"] == 1.0
    assert rows[1]["scaling"] == pytest.approx(rows[1]["env_steps_per_s"] / rows[0]["env_steps_per_s"])
