"""Several ranks, one run, on the CPU (gloo): the code path torchrun takes on GPUs (NCCL).

- every rank's sampler sees every rank's episodes (all-reduced once per iteration with
  update_every=iteration, every step with update_every=step), so all ranks sample from one distribution;
- under a wall-clock budget, all ranks stop after the same iteration and the run exits cleanly.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

from tests.conftest import TINY, cli_env

pytestmark = pytest.mark.slow
WORLD = 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rank_steps_env(rank: int, port: int, out_dir: str, sampler_name: str) -> None:
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=WORLD)
    try:
        from bmimic.config import resolve_runtime
        from bmimic.runtime import seed_everything
        from bmimic.task import build_training
        from tests.conftest import compose

        cfg = compose(["motion=easy_only", "num_envs=4", "device=cpu", f"seed={rank}", f"sampler={sampler_name}"])
        resolve_runtime(cfg, "cpu")
        seed_everything(cfg.seed)  # different worlds per rank, as train.py does
        training = build_training(cfg, "cpu")
        sampler, env = training.sampler, training.env
        assert env.world_size == WORLD
        for _ in range(40):  # random actions: episodes end, and differently on each rank
            env.step(torch.randn(env.num_envs, env.num_actions))
        env.end_rollout()
        probs = sampler.probabilities().double()
        gathered = [torch.zeros_like(probs) for _ in range(WORLD)]
        dist.all_gather(gathered, probs)
        counted = torch.as_tensor(env.pop_iteration_stats()["bin_episodes"])
        torch.save({"probs": [g for g in gathered], "episodes": counted, "seg_start": env.segment_start.clone()},
                   os.path.join(out_dir, f"rank{rank}.pt"))
    finally:
        dist.destroy_process_group()


@pytest.mark.parametrize("sampler_name", ["adaptive", "adaptive_hybrid"])  # update_every iteration, step
def test_ranks_share_one_sampling_distribution(tmp_path, sampler_name):
    mp.spawn(_rank_steps_env, args=(_free_port(), str(tmp_path), sampler_name), nprocs=WORLD, join=True)
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
           f"hydra.run.dir={run}"]
    out = subprocess.run(cmd, cwd=tmp_path, capture_output=True, text=True, timeout=600, env=cli_env())
    log = out.stdout + out.stderr
    assert out.returncode == 0, log[-4000:]
    stops = [line.split("after ")[-1] for line in log.splitlines() if "time limit of 2 s reached" in line]
    assert len(stops) == WORLD and len(set(stops)) == 1, stops  # one line per rank, same iteration
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["iterations"] == int(stops[0].split()[0]) < 1000
    # Every rank's samples are counted: env steps = iterations x steps x envs x ranks.
    assert metrics["env_steps"] == metrics["iterations"] * 8 * 2 * WORLD
    assert json.loads((run / "status.json").read_text())["status"] == "done"
