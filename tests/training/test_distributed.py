"""Several ranks, one run, on the CPU (gloo): the code path torchrun takes on GPUs (NCCL).

- every rank's sampler sees every rank's episodes (all-reduced once per iteration with
  update_every=iteration, every step with update_every=step), so all ranks sample from one distribution;
- under a wall-clock budget, all ranks stop after the same iteration and the run exits cleanly;
- several nodes are the same program: two torchruns meet at a c10d endpoint (the SLURM script's
  command, its srun played on this machine), train one policy, and rank 0 alone evaluates and
  writes the run. (tests/test_ppo.py checks the ranks' PPO update against one rank's.)
"""

from __future__ import annotations

import json
import os
import re
import stat
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import torch
import torch.distributed as dist

from tests.conftest import RANKS_GROUP, REPO, TINY, cli_env, free_port, spawn_ranks

pytestmark = [pytest.mark.slow, RANKS_GROUP]
WORLD = 2


def _rank_steps_env(rank: int, out_dir: str, sampler_name: str) -> None:
    from bmimic.config import resolve_runtime
    from bmimic.runtime import seed_everything
    from bmimic.task import build_training
    from tests.conftest import compose

    cfg = compose(["motion=easy_only", "num_envs=4", "device=cpu", f"seed={rank}", f"sampler={sampler_name}"])
    resolve_runtime(cfg, "cpu")
    seed_everything(cfg.seed)  # different worlds per rank, as train.py does
    training = build_training(cfg, "cpu")
    sampler, env = training.sampler, training.env
    assert env.feedback.world_size == WORLD
    for _ in range(40):  # random actions: episodes end, and differently on each rank
        env.step(torch.randn(env.num_envs, env.num_actions))
    env.end_rollout()
    probs = sampler.probabilities().double()
    gathered = [torch.zeros_like(probs) for _ in range(WORLD)]
    dist.all_gather(gathered, probs)
    counted = torch.as_tensor(env.pop_iteration_stats()["bin_episodes"])
    torch.save({"probs": [g for g in gathered], "episodes": counted, "seg_start": env.segment_start.clone()},
               os.path.join(out_dir, f"rank{rank}.pt"))


# update_every iteration, step; egm: per-bin tracking errors, all-reduced at the end of the rollout
@pytest.mark.parametrize("sampler_name", ["adaptive", "adaptive_hybrid", "egm"])
def test_ranks_share_one_sampling_distribution(tmp_path, sampler_name):
    spawn_ranks(_rank_steps_env, (str(tmp_path), sampler_name), WORLD, tmp_path)
    r0 = torch.load(tmp_path / "rank0.pt")
    r1 = torch.load(tmp_path / "rank1.pt")
    p0, p1 = r0["probs"]
    assert torch.equal(p0, p1), (p0, p1)
    assert not torch.allclose(p0, torch.full_like(p0, 1.0 / len(p0))), "no failure reached the sampler"
    # The ranks simulated different worlds, yet counted the same (all-reduced) episodes.
    assert not torch.equal(r0["seg_start"], r1["seg_start"])
    assert torch.equal(r0["episodes"], r1["episodes"]) and r0["episodes"].sum() > 0


def test_torchrun_time_limit_stops_every_rank_at_the_same_iteration(tmp_path):
    run = tmp_path / "run"
    overrides = [a for a in TINY if not a.startswith("max_iterations")]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={WORLD}",
           "-m", "bmimic.train", *overrides, "max_iterations=1000", "time_limit_s=2", "logger=none",
           "verbose=true", f"hydra.run.dir={run}"]  # verbose: every rank logs, so each says where it stopped
    out = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600, env=cli_env())
    log = out.stdout + out.stderr
    assert out.returncode == 0, log[-4000:]
    stops = [line.split("after ")[-1] for line in log.splitlines() if "time limit of 2 s reached" in line]
    assert len(stops) == WORLD and len(set(stops)) == 1, stops  # one line per rank, same iteration
    assert log.count("eval at iteration") == 1  # rank 0 alone evaluates
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["iterations"] == int(stops[0].split()[0]) < 1000
    # Every rank's samples are counted: env steps = iterations x steps x envs x ranks.
    assert metrics["env_steps"] == metrics["iterations"] * 8 * 2 * WORLD
    assert json.loads((run / "status.json").read_text())["status"] == "done"


def test_a_torchrun_run_resumes_on_every_rank(tmp_path):
    """A run trained under torchrun continues under torchrun (the next sitting of a long run): every rank
    compares its config with the checkpoint's and restores it. Each rank seeds its worlds with seed + rank,
    which the run's config must not record, or every rank but 0 refuses the resume as a changed seed; and
    as the checkpoint holds rank 0's random state alone, each rank draws its own stream again after it."""
    run = tmp_path / "run"
    overrides = [a for a in TINY if not a.startswith("max_iterations")]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={WORLD}",
           "-m", "bmimic.train", *overrides, "logger=none", f"hydra.run.dir={run}", "seed=3", "resume=true",
           "verbose=true"]  # verbose: every rank logs
    for iterations in (2, 4):  # the first launch starts the pinned run (resume=true on an empty folder)
        out = subprocess.run([*cmd, f"max_iterations={iterations}"], cwd=tmp_path, capture_output=True, text=True,
                             timeout=600, env=cli_env())
        assert out.returncode == 0, (out.stdout + out.stderr)[-4000:]
    log = out.stdout + out.stderr
    assert log.count("resumed from") == WORLD and log.count("at iteration 2 (lr") == WORLD
    streams = sorted(re.findall(r"rank (\d): random streams reseeded from (\d+)", log))
    assert streams == [("0", str(3 + 2 * 1_000_003)), ("1", str(4 + 2 * 1_000_003))], streams
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["iterations"] == 4 and metrics["env_steps"] == 4 * 8 * 2 * WORLD
    (resume,) = json.loads((run / "resumes.json").read_text())
    assert set(resume["changes"]) == {"max_iterations"}  # the seed is the run's, on every rank
    ckpt = torch.load(run / "checkpoints" / "latest.pt", weights_only=True, map_location="cpu")
    assert json.loads(ckpt["config"])["seed"] == 3 and ckpt["iter"] == 4


def test_torchrun_eval_driven_sampler_learns_rank_zeros_evaluation(tmp_path):
    """phc under torchrun: rank 0 runs the clip rollouts, every rank's sampler gets their outcome (a
    broadcast every rank joins; a rank left out would hang the run), and the checkpoint holds the
    failure counts."""
    run = tmp_path / "run"
    overrides = [a for a in TINY if not a.startswith("motion=")]
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc_per_node={WORLD}",
           "-m", "bmimic.train", *overrides, "motion=builtin_library", "sampler=phc", "eval.every_iters=1",
           "eval.episodes_per_bin=1", "sampler.rollout_max_s=0.5", "logger=none", f"hydra.run.dir={run}"]
    out = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600, env=cli_env())
    log = out.stdout + out.stderr
    assert out.returncode == 0, log[-4000:]
    # Only rank 0 prints: one start-up block, one sampler line, one closing line and its next steps.
    assert log.count("run folder") == 1 and log.count("sampler phc (PHCSampler)") == 1, log[-4000:]
    assert log.count("done: ") == 1 and log.count("next: bmimic-eval") == 1 and "rank 1 done" not in log
    rollouts = pd.read_parquet(run / "clip_eval.parquet")  # rank 0's clip rollouts
    failed_evals = rollouts.groupby("clip_name")["failed"].sum()
    ckpt = torch.load(run / "checkpoints" / "latest.pt", weights_only=True, map_location="cpu")
    counts = ckpt["sampler"]["state"]["failures"][:3].tolist()
    # the clips in the library's order; 2 evaluations (iterations 1 and 2) reached the sampler
    assert counts == [float(failed_evals.get(c, 0)) for c in ("graded_s0", "graded_s1", "easy_s2")]


# srun on one machine: the command once per "node", side by side, each node's output and exit
# status in its own file (SLURM would start one task on each node of the job).
SRUN = """#!/bin/bash
while [[ "$1" == --* ]]; do shift; done
pids=()
for ((node = 0; node < SLURM_JOB_NUM_NODES; node++)); do
    ( SLURM_NODEID=$node "$@" > "$NODE_LOGS/node$node.log" 2>&1; echo $? > "$NODE_LOGS/node$node.rc" ) &
    pids+=($!)
done
for pid in "${pids[@]}"; do wait "$pid"; done
"""


def test_two_nodes_meet_at_a_c10d_endpoint_through_the_slurm_script(tmp_path):
    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name, text in (("srun", SRUN), ("scontrol", "#!/bin/bash\necho localhost\necho localhost\n")):
        (stubs / name).write_text(text)
        (stubs / name).chmod(stat.S_IRWXU)
    env = cli_env()
    env.update(PATH=os.pathsep.join([str(stubs), str(Path(sys.executable).parent), env.get("PATH", "")]),
               SLURM_JOB_ID="4242", SLURM_JOB_NUM_NODES="2", SLURM_JOB_NODELIST="node[1-2]", GPUS_PER_NODE="1",
               RDZV_PORT=str(free_port()), NODE_LOGS=str(tmp_path))
    # verbose: every rank logs (rank 1's closing line is compared below); by default only rank 0 prints.
    out = subprocess.run(["bash", str(REPO / "sweeps" / "slurm_multinode.sh"), *TINY, "logger=none", "verbose=true"],
                         cwd=tmp_path,
                         capture_output=True, text=True, timeout=600, env=env)
    logs = [(tmp_path / f"node{n}.log").read_text() if (tmp_path / f"node{n}.log").exists() else "" for n in (0, 1)]
    assert out.returncode == 0, out.stderr[-2000:]
    for n in (0, 1):  # each node's torchrun exited 0
        assert (tmp_path / f"node{n}.rc").read_text().strip() == "0", logs[n][-4000:]
    log = "\n".join(logs)
    assert len(re.findall(r"envs +2 per rank, 2 ranks", log)) == 1, log[-4000:]  # one world: a rank per node
    runs = [p for p in (tmp_path / "outputs").rglob("*") if p.is_dir() and p.parent.parent.name == "runs"]
    assert [p.relative_to(tmp_path).as_posix() for p in runs] == ["outputs/runs/default/slurm-4242"]
    run = runs[0]
    metrics = json.loads((run / "metrics.json").read_text())
    assert json.loads((run / "status.json").read_text())["status"] == "done"
    assert metrics["iterations"] == 2 and metrics["env_steps"] == 2 * 8 * 2 * WORLD
    # Rank 0 alone evaluated (once, at the end); rank 1 ended with the same iterations, env steps
    # and learning rate as the run rank 0 wrote.
    assert log.count("eval at iteration 2:") == 1 and len(re.findall(r"^done: 2 iterations", log, re.M)) == 1
    done = re.findall(r"rank (\d+) done: (\d+) iterations, (\d+) env steps, learning rate (\S+)", log)
    assert len(done) == 1 and done[0][0] == "1", done
    assert (int(done[0][1]), int(done[0][2])) == (metrics["iterations"], metrics["env_steps"])
    train = pd.read_parquet(run / "train_metrics.parquet")
    assert float(done[0][3]) == pytest.approx(train["learning_rate"].iloc[-1], rel=1e-6)
    assert pd.read_parquet(run / "eval.parquet")["iteration"].unique().tolist() == [2]
