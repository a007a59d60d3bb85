"""Synthetic run folders with planted answers, for the analysis tests.

Every run has ``NUM_BINS`` bins of ``BIN_SIZE_S`` seconds, trains for iterations 0..``last_iteration``
and is evaluated every ``EVAL_EVERY`` iterations (and at its last iteration). Bin ``b`` of a run with
seed ``s`` fails at rate ``0.5 + 0.01 (s mod 5)`` before its planted mastery iteration and
``0.02 + 0.01 (s mod 5)`` from it on (always below 0.1 and staying there), so every seed masters the
bin exactly at the planted iteration. Overall success (1 - mean failure over the 4 bins) is >= 0.9
exactly once every bin is mastered.

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


EPISODES_PER_BIN = 100
"""Evaluation episodes started per bin; each stays in its start bin, so visits equal starts and the
overall failure (failed episodes / episodes) is the mean of the planted per-bin rates."""


def _failure(mastery: list[float | None], seed: int, iteration: int) -> np.ndarray:
    rates = []
    for m in mastery:
        mastered = m is not None and not np.isnan(m) and iteration >= m
        level = 0.01 * (seed % 5)  # seeds differ a little, always on their side of the 0.1 threshold
        rates.append(0.02 + level if mastered else 0.5 + level)
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
    eval_every: int = EVAL_EVERY,
    old_eval: bool = False,
    truncated_bins: tuple[int, ...] = (),
    clips: list[str] | None = None,
    sampler_episodes: list[int] | None = None,
    machine: str = "Test GPU",
    segments: list[dict] | None = None,
    bin_size_s: float = BIN_SIZE_S,
) -> Path:
    """Write one complete run folder whose bin ``b`` is mastered at ``mastery[b]`` (None: never).

    ``old_eval`` writes eval.parquet as before per-visit accounting (``episodes`` per start bin, no
    ``visits``/``horizon_truncated``); ``truncated_bins`` are flagged horizon-truncated with no episode
    tracked through them, so they never count as mastered. ``clips`` names each bin's clip (a motion
    library: eval.parquet and sampler.parquet get a `clip` column); ``sampler_episodes`` replaces the 25
    training starts per bin in sampler.parquet (and sets the sampling probabilities in proportion).
    ``machine`` is the GPU name provenance.json records. The run has ``len(mastery)`` bins (``NUM_BINS``
    in the planted sweeps) of ``bin_size_s`` seconds; ``segments`` replaces ``SEGMENTS`` (they must cover
    every bin).
    """
    run_dir = Path(run_dir)
    (run_dir / ".hydra").mkdir(parents=True, exist_ok=True)
    cfg = {"seed": seed, "sampler": {"name": sampler, "bin_size_seconds": bin_size_s, **(sampler_cfg or {})}}
    (run_dir / ".hydra" / "config.yaml").write_text(yaml.safe_dump(cfg))
    (run_dir / ".hydra" / "overrides.yaml").write_text(yaml.safe_dump([*overrides, f"seed={seed}"]))
    iteration = last_iteration if write_tables else 3
    (run_dir / "status.json").write_text(json.dumps(
        {"status": status, "error": error, "iteration": iteration, "updated": "2026-01-01T00:00:00+00:00"}
    ))
    (run_dir / "provenance.json").write_text(json.dumps({"git_commit": "0123abc", "git_dirty": False,
                                                         "gpu": {"name": machine, "count": 1}}))
    segments = SEGMENTS if segments is None else segments
    num_bins = len(mastery)
    (run_dir / "motion_segments.json").write_text(json.dumps(segments))
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
        "sampling_entropy": np.log(num_bins),
        "top1_prob": 1.0 / num_bins,
        "top1_bin": 0,
        "reward/motion_body_pos": 0.5,
        "termination/anchor_pos": 0.1,
    })
    train.to_parquet(run_dir / "train_metrics.parquet", index=False)

    eval_rows, sampler_rows = [], []
    for it in iterations:
        fail = _failure(mastery, seed, int(it))
        prob = np.full(num_bins, 1.0 / num_bins) if sampler == "uniform" else fail / fail.sum()
        if sampler_episodes is not None:
            prob = np.asarray(sampler_episodes, dtype=float) / sum(sampler_episodes)
        for b in range(num_bins):
            start, end = b * bin_size_s, (b + 1) * bin_size_s
            starts = 25 if sampler_episodes is None else sampler_episodes[b]
            sampler_rows.append((int(it), b, start, end, starts, int(starts * fail[b]), fail[b], fail[b], prob[b]))
            if it % eval_every == 0 or it == last_iteration:
                segment = next(s["name"] for s in segments if s["start_s"] <= start < s["end_s"])
                visits = EPISODES_PER_BIN
                truncated = b in truncated_bins
                eval_rows.append((
                    int(it), int(it) * STEPS_PER_ITERATION, it * seconds_per_iteration, b, start, end,
                    segment, visits, round(fail[b] * visits), fail[b], EPISODES_PER_BIN,
                    round(fail[b] * EPISODES_PER_BIN),
                    truncated, 0 if truncated else EPISODES_PER_BIN, 50.0, 30.0, 0.1, 0.05,
                ))
    eval_df = pd.DataFrame(eval_rows, columns=[
        "iteration", "env_steps", "wall_time_s", "bin", "bin_start_s", "bin_end_s", "segment", "visits",
        "failures", "failure_rate", "start_episodes", "start_failures", "horizon_truncated", "tracked_through",
        "mpkpe_mm", "mpkpe_rel_mm", "anchor_ori_err_rad", "joint_pos_err_rad",
    ])
    if clips is not None:
        eval_df.insert(7, "clip", [clips[b] for b in eval_df["bin"]])
    if old_eval:
        eval_df = eval_df.drop(columns=["visits", "start_failures", "horizon_truncated", "tracked_through"]).rename(
            columns={"start_episodes": "episodes"})
    eval_df.to_parquet(run_dir / "eval.parquet", index=False)
    sampler_df = pd.DataFrame(sampler_rows, columns=[
        "iteration", "bin", "bin_start_s", "bin_end_s", "episodes", "failures", "raw_failure_rate",
        "smoothed_failure_rate", "probability",
    ])
    if clips is not None:
        sampler_df.insert(2, "clip", [clips[b] for b in sampler_df["bin"]])
    sampler_df.to_parquet(run_dir / "sampler.parquet", index=False)
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
        "num_bins": num_bins,
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


def make_speedup_sweep(root: str | Path, n_seeds: int = 10, ratio: float = 2.0, rng_seed: int = 0,
                       name: str = "speedup") -> Path:
    """Two arms of ``n_seeds`` seeds each: ``sampler=uniform`` masters bin ``b`` at about 20 (b + 1)
    iterations and ``sampler=adaptive`` at about 20 (b + 1) / ratio, each seed scaled by its own factor
    drawn from U(0.75, 1.3) (so seeds differ and the ratio of the arms' medians is about ``ratio``),
    rounded to the evaluation grid of EVAL_EVERY iterations. Runs end at iteration 150."""
    rng = np.random.default_rng(rng_seed)
    sweep = Path(root) / name
    for sampler, scale in (("uniform", 1.0), ("adaptive", 1.0 / ratio)):
        for seed in range(n_seeds):
            f = rng.uniform(0.75, 1.3)
            mastery = [float(EVAL_EVERY * np.ceil(20.0 * (b + 1) * scale * f / EVAL_EVERY)) for b in range(NUM_BINS)]
            write_run(sweep / f"sampler={sampler}" / f"seed={seed}", sampler=sampler, seed=seed,
                      overrides=[f"sampler={sampler}"], mastery=mastery, last_iteration=150)
    return sweep


WIDE_ARMS = ("uniform", "adaptive", "adaptive_hybrid", "beyondmimic", "egm", "gmt", "phc")
"""The arms of the wide study: as many as the peer-sampler study has."""


def make_wide_study(root: str | Path, num_bins: int = 200, seeds: int = 2, last_iteration: int = 60,
                    eval_every: int = EVAL_EVERY, spike: float = 0.9, never: int = 10,
                    name: str = "wide") -> Path:
    """A study the size of a real one, for the figures: ``len(WIDE_ARMS)`` arms of ``seeds`` seeds on
    ``num_bins`` bins (ten named segments), bin b mastered at an iteration that grows with b (arm by arm
    a little sooner). In the ``beyondmimic`` arm one bin (the middle one) draws ``spike`` of the
    sampling probability at every logged iteration, as a spiky sampler does, so that one bright bin
    would set a shared colour scale. The last ``never`` bins are never mastered by ``uniform`` (the
    baseline) and ``phc``: their per-bin speedups are lower bounds for the other arms and not estimable
    for ``phc``. With ``last_iteration`` 3 and ``eval_every`` 100 it is a smoke study: four
    iterations, evaluated at 0 and 3."""
    sweep = Path(root) / name
    length = num_bins * BIN_SIZE_S
    segments = [{"name": f"segment_{k}_of_the_motion", "start_s": length * k / 10, "end_s": length * (k + 1) / 10,
                 "difficulty": k / 10} for k in range(10)]
    segments[-1]["end_s"] = length + 1.0  # the last bin's start lies inside
    for a, arm in enumerate(WIDE_ARMS):
        for seed in range(seeds):
            mastery = [None if arm in ("uniform", "phc") and b >= num_bins - never else
                       float(max(1, last_iteration * (b + 1) / (num_bins + 1) * (1 - 0.05 * a))) for b in range(num_bins)]
            run = write_run(sweep / f"sampler={arm}" / f"seed={seed}", sampler=arm, seed=seed,
                            overrides=[f"sampler={arm}"], mastery=mastery, last_iteration=last_iteration,
                            eval_every=eval_every, segments=segments)
            if arm == "beyondmimic":
                samp = pd.read_parquet(run / "sampler.parquet")
                mid = samp["bin"] == num_bins // 2
                samp["probability"] = np.where(mid, spike, (1 - spike) / (num_bins - 1))
                samp.to_parquet(run / "sampler.parquet", index=False)
    return sweep


KNOB_REFERENCE = "sampler=adaptive"
KNOB_UNIFORM = "sampler=uniform"
KNOB_LEVELS = {  # arm folder -> (knob, value, mastery of bins 0-3)
    "sampler.gamma=0.5,sampler=adaptive": ("sampler.gamma", 0.5, [5.0, 10.0, 15.0, 20.0]),
    "sampler.gamma=1.0,sampler=adaptive": ("sampler.gamma", 1.0, [10.0, 20.0, 30.0, 40.0]),
    "sampler.lambda_uniform=0.4,sampler=adaptive": ("sampler.lambda_uniform", 0.4, [15.0, 30.0, 45.0, 60.0]),
}
"""The planted knob study (make_knob_study): the reference masters bin b at 10 (b + 1) and uniform at
20 (b + 1), so overall success reaches 0.9 at iteration 40 and 80; gamma 0.5 at 20 (x2 the reference,
x4 uniform), gamma 1.0 at 40 (x1), lambda_uniform 0.4 at 60 (x0.667)."""


def make_knob_study(root: str | Path, name: str = "knobs") -> Path:
    """A one-knob-at-a-time study (sweeps/sensitivity_dance1.yaml's shape): the reference and uniform
    with seeds 0-4 (launched with ``+sweep=<name>``), each level of KNOB_LEVELS with seeds 0-2 (``+sweep=
    <name>_<knob>``), every run to iteration 100; every folder sits under ``motion=m,`` (an override all
    arms share)."""
    sweep = Path(root) / name
    reference = {"gamma": 0.9, "lambda_uniform": 0.1}
    arms = {KNOB_REFERENCE: ("adaptive", reference, [10.0, 20.0, 30.0, 40.0], 5),
            KNOB_UNIFORM: ("uniform", reference, [20.0, 40.0, 60.0, 80.0], 5)}
    for arm, (knob, value, mastery) in KNOB_LEVELS.items():
        arms[arm] = ("adaptive", {**reference, knob.removeprefix("sampler."): value}, mastery, 3)
    for arm, (sampler, cfg, mastery, seeds) in arms.items():
        # As launched: the baselines from the study's file, each knob's levels from the knob's own file.
        knob = KNOB_LEVELS[arm][0].removeprefix("sampler.") if arm in KNOB_LEVELS else None
        overrides = ["motion=m", *arm.split(","), f"+sweep={name}_{knob}" if knob else f"+sweep={name}"]
        for seed in range(seeds):
            write_run(sweep / f"motion=m,{arm}" / f"seed={seed}", sampler=sampler, seed=seed, overrides=overrides,
                      mastery=mastery, sampler_cfg=cfg, last_iteration=100)
    return sweep
