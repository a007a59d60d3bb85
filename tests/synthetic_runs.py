"""Synthetic run folders with planted answers, for the analysis tests.

Every run has ``NUM_BINS`` bins of ``BIN_SIZE_S`` seconds, trains for iterations 0..``last_iteration``
and is evaluated every ``EVAL_EVERY`` iterations. Bin ``b`` of a run with seed ``s`` fails at rate
``0.5 + 0.01 s`` before its planted mastery iteration and ``0.02 + 0.01 s`` from it on (always below
0.1), so the seed-mean curve of an arm crosses 0.1 exactly at the planted iteration. Overall success
(1 - mean failure over the 4 bins) is >= 0.9 exactly once every bin is mastered.

``make_sweep`` builds the planted sweep (PLANTED holds its answers):

================================  ============================  ===========================
arm                               mastery iteration of bin b    seeds
================================  ============================  ===========================
sampler=uniform                   10 (b + 1)                    0, 1 done; 2 running to 45
sampler=adaptive,sampler.gamma=0.5 5 (b + 1)                    0, 1 done; 2 failed (no tables)
sampler=adaptive,sampler.gamma=0.9 10 (b + 1), bin 3 never       0, 1 done; 2 missing
================================  ============================  ===========================
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

NUM_BINS = 4
BIN_SIZE_S = 2.0
EVAL_EVERY = 5
LAST_ITERATION = 60
STEPS_PER_ITERATION = 1000
SEGMENTS = [
    {"name": "walk", "start_s": 0.0, "end_s": 4.0, "difficulty": 0.2},
    {"name": "jump", "start_s": 4.0, "end_s": 8.0, "difficulty": 0.8},
]

UNIFORM = "sampler=uniform"
FAST = "sampler=adaptive,sampler.gamma=0.5"
SLOW = "sampler=adaptive,sampler.gamma=0.9"

PLANTED = {
    "mastery": {
        UNIFORM: [10.0, 20.0, 30.0, 40.0],
        FAST: [5.0, 10.0, 15.0, 20.0],
        SLOW: [10.0, 20.0, 30.0, np.nan],
    },
    "mastery_ratio": {FAST: [2.0, 2.0, 2.0, 2.0], SLOW: [1.0, 1.0, 1.0, 40.0 / 60.0]},
    "mastery_median": {FAST: 2.0, SLOW: 1.0},
    "never_mastered": {UNIFORM: 0, FAST: 0, SLOW: 1},
    # Time to overall success >= 0.9, per seed (iterations), and the speedups against uniform.
    "time_to_threshold": {UNIFORM: 40.0, FAST: 20.0, SLOW: np.nan},
    "speedup": {"iteration": 2.0, "env_steps": 2.0, "wall_time_s": 40.0 / (20.0 * 1.25)},
    "seconds_per_iteration": {UNIFORM: 1.0, FAST: 1.25, SLOW: 1.25},
    "failed": [f"{FAST}/seed=2"],
    "missing": [f"{SLOW}/seed=2"],
    "running": [f"{UNIFORM}/seed=2"],
}


def _failure(mastery: list[float | None], seed: int, iteration: int) -> np.ndarray:
    rates = []
    for m in mastery:
        mastered = m is not None and not np.isnan(m) and iteration >= m
        rates.append(0.02 + 0.01 * seed if mastered else 0.5 + 0.01 * seed)
    return np.array(rates)


def write_run(
    run_dir: str | Path,
    *,
    sampler: str,
    seed: int,
    overrides: list[str],
    mastery: list[float | None],
    sampler_cfg: dict | None = None,
    status: str = "done",
    last_iteration: int = LAST_ITERATION,
    seconds_per_iteration: float = 1.0,
    write_tables: bool = True,
    error: str | None = None,
) -> Path:
    """Write one complete run folder whose bin ``b`` is mastered at ``mastery[b]`` (None: never)."""
    run_dir = Path(run_dir)
    (run_dir / ".hydra").mkdir(parents=True, exist_ok=True)
    cfg = {"seed": seed, "sampler": {"name": sampler, "bin_size_seconds": BIN_SIZE_S, **(sampler_cfg or {})}}
    (run_dir / ".hydra" / "config.yaml").write_text(yaml.safe_dump(cfg))
    (run_dir / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([*overrides, f"seed={seed}"]))
    iteration = last_iteration if write_tables else 3
    (run_dir / "status.json").write_text(json.dumps(
        {"status": status, "error": error, "iteration": iteration, "updated": "2026-01-01T00:00:00+00:00"}
    ))
    (run_dir / "provenance.json").write_text(json.dumps({"git_commit": "0123abc", "git_dirty": False}))
    (run_dir / "motion_segments.json").write_text(json.dumps(SEGMENTS))
    if not write_tables:
        return run_dir

    iterations = np.arange(last_iteration + 1)
    train = pd.DataFrame({
        "iteration": iterations,
        "env_steps": iterations * STEPS_PER_ITERATION,
        "wall_time_s": iterations * seconds_per_iteration,
        "mean_episode_length": 10.0 + iterations + seed,
        "mean_reward": 0.1 * iterations,
        "episodes": 100,
        "failure_rate": [float(_failure(mastery, seed, int(i)).mean()) for i in iterations],
        "sampling_entropy": np.log(NUM_BINS),
        "top1_prob": 1.0 / NUM_BINS,
        "top1_bin": 0,
        "reward/motion_body_pos": 0.5,
        "termination/anchor_pos": 0.1,
    })
    train.to_parquet(run_dir / "train_metrics.parquet", index=False)

    eval_rows, sampler_rows = [], []
    for it in iterations:
        fail = _failure(mastery, seed, int(it))
        prob = np.full(NUM_BINS, 1.0 / NUM_BINS) if sampler == "uniform" else fail / fail.sum()
        for b in range(NUM_BINS):
            start, end = b * BIN_SIZE_S, (b + 1) * BIN_SIZE_S
            sampler_rows.append((int(it), b, start, end, 25, int(25 * fail[b]), fail[b], fail[b], prob[b]))
            if it % EVAL_EVERY == 0:
                segment = next(s["name"] for s in SEGMENTS if s["start_s"] <= start < s["end_s"])
                eval_rows.append((
                    int(it), int(it) * STEPS_PER_ITERATION, it * seconds_per_iteration, b, start, end,
                    segment, 100, int(100 * fail[b]), fail[b], 50.0, 30.0, 0.1, 0.05,
                ))
    pd.DataFrame(eval_rows, columns=[
        "iteration", "env_steps", "wall_time_s", "bin", "bin_start_s", "bin_end_s", "segment", "episodes",
        "failures", "failure_rate", "mpkpe_mm", "mpkpe_rel_mm", "anchor_ori_err_rad", "joint_pos_err_rad",
    ]).to_parquet(run_dir / "eval.parquet", index=False)
    pd.DataFrame(sampler_rows, columns=[
        "iteration", "bin", "bin_start_s", "bin_end_s", "episodes", "failures", "raw_failure_rate",
        "smoothed_failure_rate", "probability",
    ]).to_parquet(run_dir / "sampler.parquet", index=False)
    if status == "running":
        return run_dir  # metrics.json is written at the end of training
    (run_dir / "metrics.json").write_text(json.dumps({
        "final_eval_failure_rate": float(_failure(mastery, seed, last_iteration).mean()),
        "final_eval_success_rate": 1.0 - float(_failure(mastery, seed, last_iteration).mean()),
        "iterations": last_iteration + 1,
        "env_steps": int(last_iteration * STEPS_PER_ITERATION),
        "wall_time_s": last_iteration * seconds_per_iteration,
        "mean_episode_length": float(10 + last_iteration + seed),
        "max_episode_length": 500,
        "num_bins": NUM_BINS,
    }))
    return run_dir


def make_sweep(root: str | Path, name: str = "ablation") -> Path:
    """Write the planted sweep of the module docstring under ``root/name`` and return its folder."""
    sweep = Path(root) / name
    uniform = PLANTED["mastery"][UNIFORM]
    fast = PLANTED["mastery"][FAST]
    slow = [None if np.isnan(m) else m for m in PLANTED["mastery"][SLOW]]
    for seed in (0, 1, 2):
        running = seed == 2
        write_run(sweep / UNIFORM / f"seed={seed}", sampler="uniform", seed=seed, overrides=["sampler=uniform"],
                  mastery=uniform, sampler_cfg={"gamma": 0.8}, status="running" if running else "done",
                  last_iteration=45 if running else LAST_ITERATION)
    for seed in (0, 1, 2):
        failed = seed == 2
        write_run(sweep / FAST / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler=adaptive", "sampler.gamma=0.5"], mastery=fast,
                  sampler_cfg={"gamma": 0.5}, seconds_per_iteration=1.25,
                  status="failed" if failed else "done", write_tables=not failed,
                  error="RuntimeError: simulated crash" if failed else None)
    for seed in (0, 1):  # seed 2 never started: its folder is missing
        write_run(sweep / SLOW / f"seed={seed}", sampler="adaptive", seed=seed,
                  overrides=["sampler=adaptive", "sampler.gamma=0.9"], mastery=slow,
                  sampler_cfg={"gamma": 0.9}, seconds_per_iteration=1.25)
    return sweep
