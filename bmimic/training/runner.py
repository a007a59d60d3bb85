"""The PPO training loop: rsl-rl-lib's PPO (as `GraphPPO`, see ppo.py), this project's tables,
evaluation and checkpoints; TensorBoard / W&B / console output goes through one RunLogger (logger.py).

rsl-rl's `OnPolicyRunner` builds the algorithm (models, storage, optimiser, multi-GPU set-up); the loop
itself is written here so that each iteration can (a) read the environment's statistics with a single
host transfer instead of rsl-rl's per-step `.cpu()` bookkeeping, (b) update the sampler once after the
rollout (`env.end_rollout()`, for `sampler.accounting.update_every=iteration`) and log its per-bin state,
(c) run the sampler-independent evaluation and (d) write atomic checkpoints that also hold the sampler
and RNG states, so `resume` reproduces iteration count, learning rate and sampler state.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pandas as pd
import torch
from rsl_rl.runners import OnPolicyRunner

from bmimic import BmimicError
from bmimic.run_folder import (
    atomic_write_parquet,
    checkpoint_path,
    checkpoints_dir,
    latest_checkpoint,
    table_path,
    write_status,
)
from bmimic.runtime import any_rank, rng_state, set_rng_state
from bmimic.sampling import diagnostics
from bmimic.training.checkpoints import (
    CHECKPOINT_FORMAT,
    CheckpointMismatchError,
    atomic_torch_save,
    load_checkpoint_file,
    mismatch_detail,
    motion_meta,
)
from bmimic.training.clip_rollouts import CLIP_ROLLOUT_COLUMNS, clip_rollouts, clips_failed, eval_mode
from bmimic.training.evaluation import summarize
from bmimic.training.health import Health
from bmimic.training.logger import RunLogger
from bmimic.training.policy import rsl_rl_train_cfg
from bmimic.training.resume import key_allowed

log = logging.getLogger(__name__)


class _Runner(OnPolicyRunner):
    """rsl-rl's runner, accepting a process group that bmimic initialised before building the env."""

    def _configure_multi_gpu(self) -> None:
        dist = torch.distributed
        if not (dist.is_available() and dist.is_initialized()):
            return super()._configure_multi_gpu()
        self.gpu_world_size = dist.get_world_size()
        self.gpu_global_rank = dist.get_rank()
        self.gpu_local_rank = int(os.getenv("LOCAL_RANK", "0"))
        self.is_distributed = self.gpu_world_size > 1
        self.cfg["multi_gpu"] = {"global_rank": self.gpu_global_rank, "local_rank": self.gpu_local_rank,
                                 "world_size": self.gpu_world_size} if self.is_distributed else None


@dataclass
class Progress:
    """Counters a checkpoint carries so a resumed run continues them."""

    iteration: int = 0
    env_steps: int = 0
    wall_time_s: float = 0.0
    last_eval: dict = field(default_factory=dict)


_SOFT_META = {"num_envs": "num_envs", "motion_frames": "motion", "motion_fps": "motion", "motion_sha256": "motion"}
"""Checkpoint meta a resume may change when resume_allow_changes names the config key on the right."""


class Trainer:
    """Owns the rsl-rl algorithm, the env, the evaluator and the run folder's tables. Nothing is written
    into the run folder until `learn` (or `evaluate`, `save_checkpoint`) runs, so a resume refused by
    `restore` leaves the folder as it was."""

    def __init__(self, env, evaluator, sampler, feedback, cfg, run_dir: str | os.PathLike, device: str,
                 logger: RunLogger, is_main_rank: bool = True, run_config: dict | None = None) -> None:
        self.env = env
        self.evaluator = evaluator
        self.sampler = sampler
        self.feedback = feedback
        """The sampler's feedback (bmimic.sampling.feedback): told after each periodic evaluation."""
        self.cfg = cfg
        """The run's runtime-resolved config: ppo, eval.every_iters, sampler.log_every and the budget."""
        self.ppo_cfg = cfg.ppo
        self.run_dir = Path(run_dir)
        self.device = device
        self.logger = logger
        self.is_main = is_main_rank
        self.run_config = run_config
        """The resolved config as plain values, stored in every checkpoint (None: not stored)."""
        self._sampler_every = 1
        torch.set_float32_matmul_precision(self.ppo_cfg.float32_matmul_precision)
        self.runner = _Runner(env, rsl_rl_train_cfg(self.ppo_cfg, cfg.run_name), log_dir=None, device=device)
        self.alg = self.runner.alg
        self.progress = Progress()
        self.train_rows: list[dict] = []
        self.sampler_rows: list[pd.DataFrame] = []
        self.eval_rows: list[pd.DataFrame] = []
        self.clip_eval_rows: list[pd.DataFrame] = []
        self.total_resets = {"nonfinite_resets": 0, "out_of_bounds_resets": 0}
        # A stopping rule after each evaluation (its summary -> True: stop; bmimic.race), when learn()
        # began (time.time()) and the wall time the evaluations took.
        self.after_evaluation: Callable[[Trainer, dict], bool] | None = None
        self.learn_started_unix_s: float | None = None
        self.eval_time_s = 0.0
        self.health = Health(env.num_envs * self.ppo_cfg.num_steps_per_env)
        self.interrupted = False  # learn() stopped early on a signal (bmimic.training.interrupts)

    # ------------------------------------------------------------------ checkpoints
    def meta(self) -> dict:
        """What a checkpoint must match to be loaded into this trainer (plain values)."""
        obs = self.env.get_observations()
        return {
            "num_envs": int(self.env.num_envs),
            "num_actions": int(self.env.num_actions),
            "obs_dims": {k: int(v.shape[-1]) for k, v in obs.items()},
            "sampler_kind": str(self.sampler.state_dict().get("kind")),
            "num_bins": int(self.env.layout.num_bins),
            **motion_meta(self.env.reference.motion),
        }

    def checkpoint_state(self) -> dict:
        """Tensors and plain values only (CHECKPOINT_FORMAT): loads with torch.load(weights_only=True)."""
        state = self.alg.save()
        progress = vars(self.progress).copy()
        progress["last_eval"] = {str(k): float(v) for k, v in self.progress.last_eval.items()}
        state.update(
            iter=int(self.progress.iteration),
            progress=progress,
            sampler=self.sampler.state_dict(),
            rng=rng_state(),
            format=CHECKPOINT_FORMAT,
            meta=self.meta(),
            config=json.dumps(self.run_config, sort_keys=True, default=str) if self.run_config else None,
        )
        return state

    def save_checkpoint(self) -> Path:
        """Write model_<it>.pt and latest.pt (tables first) and their ONNX exports."""
        from bmimic.training.export import export_checkpoint_onnx

        it = self.progress.iteration
        path = checkpoint_path(self.run_dir, it)
        # Tables first (never behind a checkpoint), latest.pt first (never older than a model_<it>.pt).
        self.flush_tables()
        state = self.checkpoint_state()
        atomic_torch_save(latest_checkpoint(self.run_dir), state)
        atomic_torch_save(path, state)
        try:  # policy_<it>.onnx and the BeyondMimic-compatible motion_policy_<it>.onnx
            export_checkpoint_onnx(self.alg.get_policy(), self.env, checkpoints_dir(self.run_dir), it)
        except Exception as e:  # export must never cost a training run
            log.warning("ONNX export failed at iteration %d: %s", it, e)
        return path

    def load_checkpoint(self, path: str | os.PathLike, trust: bool = False) -> None:
        """Read a checkpoint (weights_only unless `trust`) and `restore` it."""
        self.restore(load_checkpoint_file(path, "cpu", trust), path)

    def restore(self, state: dict, path: str | os.PathLike = "checkpoint", allowed: tuple | list = ()) -> None:
        """Load networks, optimiser, counters, sampler and RNG states; reads the run's tables but writes
        nothing; CheckpointMismatchError (one line) when it does not fit. `allowed` (resume_allow_changes)
        may accept another num_envs or motion; observation and action sizes, sampler kind and bins must
        match (the networks and sampler state depend on them)."""
        saved = state.get("meta")
        if isinstance(saved, dict):
            own = self.meta()
            soft = {k: cfg_key for k, cfg_key in _SOFT_META.items() if key_allowed(cfg_key, allowed)}
            differ = [f"{k} {saved[k]} -> {own[k]}" for k in own
                      if k in saved and saved[k] != own[k] and k not in soft]
            if differ:
                raise CheckpointMismatchError(f"{path}: does not fit this run: {'; '.join(differ)}")
        try:
            self.alg.load(state, None, strict=True)
        except (RuntimeError, KeyError, ValueError, TypeError) as e:
            raise CheckpointMismatchError(f"{path}: its networks do not fit this config: {mismatch_detail(e)}") from None
        try:
            self.sampler.load_state_dict(state["sampler"])
            self.progress = Progress(**state["progress"])
            set_rng_state(state["rng"])
        except BmimicError as e:
            raise CheckpointMismatchError(f"{path}: {e}") from None
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise CheckpointMismatchError(f"{path}: malformed checkpoint ({type(e).__name__}: {e})") from None
        self.runner.current_learning_iteration = self.progress.iteration
        self._truncate_tables(self.progress.iteration)
        for key in self.total_resets:
            self.total_resets[key] = int(sum(_count(r.get(key)) for r in self.train_rows))
        log.info("resumed from %s at iteration %d (lr %.2e)", path, self.progress.iteration, self.alg.learning_rate)

    # ------------------------------------------------------------------ tables
    def _truncate_tables(self, iteration: int) -> None:
        """On resume, keep only rows of iterations the checkpoint had completed."""
        for name, rows in (("train_metrics", self.train_rows), ("sampler", self.sampler_rows), ("eval", self.eval_rows),
                           ("clip_eval", self.clip_eval_rows)):
            path = table_path(self.run_dir, name)
            if path.exists():
                try:
                    df = pd.read_parquet(path)
                except Exception as e:  # noqa: BLE001 - any reader error: the table is damaged
                    raise CheckpointMismatchError(
                        f"{path}: cannot be read ({type(e).__name__}); move it aside to resume without its "
                        "rows") from None
                if "iteration" not in df:
                    raise CheckpointMismatchError(f"{path}: has no iteration column; move it aside to resume "
                                                  "without its rows")
                df = df[df["iteration"] <= iteration] if "eval" in name else df[df["iteration"] < iteration]
                if name == "train_metrics":
                    self.train_rows.extend(df.to_dict("records"))
                else:
                    rows.append(df)

    def flush_tables(self) -> None:
        """Write the run's tables (rank 0 only)."""
        if not self.is_main:
            return
        if self.train_rows:
            atomic_write_parquet(table_path(self.run_dir, "train_metrics"), pd.DataFrame(self.train_rows))
        for name, rows in (("sampler", self.sampler_rows), ("eval", self.eval_rows), ("clip_eval", self.clip_eval_rows)):
            if rows:
                atomic_write_parquet(table_path(self.run_dir, name), pd.concat(rows, ignore_index=True))

    # ------------------------------------------------------------------ evaluation
    def evaluate(self) -> dict:
        """Evaluate the current policy (eval.parquet row, logged); returns the summary."""
        t0 = time.perf_counter()
        with eval_mode(self.alg.get_policy()) as policy:
            per_bin = self.evaluator.evaluate(policy, self.progress.iteration, self.progress.env_steps,
                                              self.progress.wall_time_s)
        self.eval_rows.append(per_bin)
        self.flush_tables()  # evaluations are the expensive rows: never lose them to an interruption
        self.eval_time_s += time.perf_counter() - t0
        summary = summarize(per_bin)
        self.progress.last_eval = summary
        self.logger.evaluation(self.progress.iteration, summary)
        return summary

    def _clip_outcomes(self, max_s: float | None) -> torch.Tensor:
        """Rank 0, for a sampler that learns from clip outcomes (phc, protomotions): one rollout per clip
        from its first frame (clip_rollouts; a row of clip_eval.parquet each); [C] > 0 where one failed."""
        with eval_mode(self.alg.get_policy()) as policy:
            rows = clip_rollouts(self.evaluator, policy, max_s)
        p = self.progress
        self.clip_eval_rows.append(rows.assign(iteration=p.iteration, env_steps=p.env_steps)[
            ["iteration", "env_steps", *CLIP_ROLLOUT_COLUMNS]])
        self.flush_tables()
        log.info("clip rollouts at iteration %d: %d of %d clips failed", p.iteration, rows.failed.sum(), len(rows))
        return clips_failed(rows, self.env.layout.num_clips)

    # ------------------------------------------------------------------ the loop
    def learn(self, signals=None) -> None:
        """Train from the current iteration to `max_iterations` (or until `time_limit_s` of training, or
        until a stop was requested of `signals` (training.interrupts.StopSignals): `interrupted` is then True)."""
        env, alg, cfg = self.env, self.alg, self.cfg
        time_limit_s = cfg.time_limit_s
        if self.ppo_cfg.init_at_random_ep_len and self.progress.iteration == 0:
            # In place: the environment's captured CUDA graphs hold this buffer's address.
            env.episode_length_buf.copy_(torch.randint_like(env.episode_length_buf, high=int(env.max_episode_length)))
        obs = env.get_observations().to(self.device)
        alg.train_mode()
        if self.runner.is_distributed:
            alg.broadcast_parameters()
        start_it = self.progress.iteration
        end_it = cfg.max_iterations
        steps_per_it = self.ppo_cfg.num_steps_per_env * env.num_envs * self.runner.gpu_world_size
        self._sampler_every = diagnostics.log_every(cfg.sampler.log_every, env.layout.num_bins, end_it)
        if cfg.sampler.log_every is None and self._sampler_every > 1:
            log.info("sampler.parquet: %d bins x %d iterations, so one table every %d iterations and at the last "
                     "(sampler.log_every=null keeps it under about %.0e rows)", env.layout.num_bins, end_it,
                     self._sampler_every, diagnostics.MAX_SAMPLER_ROWS)
        self.logger.start(start_it, end_it)
        if self.after_evaluation is not None and self.runner.is_distributed:
            raise BmimicError("a stopping rule after evaluations (bmimic.race) runs in a single process, not under torchrun")
        self.learn_started_unix_s = time.time()
        for it in range(start_it, end_it):
            t0 = time.perf_counter()
            with torch.inference_mode():
                for _ in range(self.ppo_cfg.num_steps_per_env):
                    actions = alg.act(obs)
                    obs, rewards, dones, extras = env.step(actions.to(env.device))
                    obs, rewards, dones = obs.to(self.device), rewards.to(self.device), dones.to(self.device)
                    alg.process_env_step(obs, rewards, dones, extras)
                # The design's runner hook: one sampler update with every episode of the rollout
                # (sampler.accounting.update_every=iteration; a no-op when the env updates it every step).
                env.end_rollout()
                t1 = time.perf_counter()
                alg.compute_returns(obs)
            losses = alg.update()
            t2 = time.perf_counter()
            self.progress.iteration = it + 1
            self.progress.env_steps += steps_per_it
            self.progress.wall_time_s += t2 - t0
            out_of_time = time_limit_s is not None and any_rank(self.progress.wall_time_s >= time_limit_s, self.device)
            done = self.progress.iteration == end_it or out_of_time
            self._record_iteration(it, losses, t1 - t0, t2 - t1, steps_per_it, last=done)
            every = cfg.eval.every_iters
            stop = False
            if every and self.progress.iteration % every == 0:
                if self.is_main:
                    summary = self.evaluate()
                    stop = self.after_evaluation is not None and bool(self.after_evaluation(self, summary))
                self.feedback.after_evaluation(self._clip_outcomes, every)
            if self.is_main and (self.progress.iteration % self.ppo_cfg.save_interval == 0 and not done):
                self.save_checkpoint()
                write_status(self.run_dir, "running", self.progress.iteration)
            if out_of_time:
                log.info("time limit of %.0f s reached after %d iterations", time_limit_s, self.progress.iteration)
            if out_of_time or stop:
                break
            if not done and signals is not None and any_rank(signals.requested, self.device):
                self.interrupted = True
                break
        self.logger.end()

    def _record_iteration(self, it: int, losses: dict, collect_s: float, learn_s: float, steps: int,
                       last: bool = False) -> dict:
        stats = self.env.pop_iteration_stats()
        s = diagnostics.summary(self.sampler, torch.as_tensor(stats["bin_episodes"]),
                                torch.as_tensor(stats["bin_failures"]), total_episodes=stats["episodes"])
        row = {
            "iteration": it,
            "env_steps": self.progress.env_steps,
            "wall_time_s": self.progress.wall_time_s,
            "mean_episode_length": stats["mean_episode_length"],
            "mean_reward": stats["mean_episode_reward"],
            "episodes": stats["episodes"],
            "failure_rate": stats["failures"] / stats["episodes"] if stats["episodes"] else math.nan,
            "sampling_entropy": s["sampling_entropy"],
            "top1_prob": s["top1_prob"],
            "top1_bin": s["top1_bin"],
            "fps": steps / max(collect_s + learn_s, 1e-9),
            "collection_time_s": collect_s,
            "learning_time_s": learn_s,
            "learning_rate": float(self.alg.learning_rate),
            "action_std": float(self.alg.action_std().mean()),
            "nonfinite_resets": stats["nonfinite_resets"],
            "out_of_bounds_resets": stats["out_of_bounds_resets"],
            "overflow_worlds": stats["overflow_worlds"],
        }
        for k, v in losses.items():
            row[f"loss/{k}"] = float(v)
        for k, v in stats.items():
            if k.startswith("Episode_Reward/"):
                row["reward/" + k.split("/", 1)[1]] = v
            elif k.startswith("Episode_Termination/"):
                row["termination/" + k.split("/", 1)[1]] = v
            elif k.startswith("Metrics/"):
                row["metrics/" + k.split("/", 1)[1]] = v
        for key in self.total_resets:
            self.total_resets[key] += int(stats[key])
        self.train_rows.append(row)
        self.health.check(it, row, self.ppo_cfg.learning_rate, self.runner.is_distributed, self.device)
        sampler_table = it % self._sampler_every == 0 or last
        if sampler_table:
            self.sampler_rows.append(
                diagnostics.bin_table(it, self.env.layout, torch.as_tensor(stats["bin_episodes"]),
                                      torch.as_tensor(stats["bin_failures"]), self.sampler)
            )
        self.logger.iteration(it, row, sum(self.total_resets.values()),
                              *((self.sampler, self.env.layout) if sampler_table else ()))
        return row

    def close(self) -> None:
        """Write the tables, then (even when that fails) release the CUDA graphs and close the logger."""
        try:
            self.flush_tables()
        finally:
            self.alg.release_graphs()  # before destroy_process_group: graphs may hold NCCL calls
            self.logger.close()


def _count(value) -> float:
    """A counter from a table row (absent or NaN in rows written before the column existed: 0)."""
    try:
        return 0.0 if math.isnan(value := float(value)) else value
    except (TypeError, ValueError):
        return 0.0

