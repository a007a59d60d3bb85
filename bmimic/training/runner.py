"""The PPO training loop, in the manner of rsl-rl's runner: it loops and hands off. Its parts: the
run's tables (`bmimic.runs.record.RunRecord`), when to evaluate and checkpoint (`schedule.Schedule`),
what a checkpoint holds and the resume (`run_state`), what the sampler hears (the task's
`SamplerFeedback`); TensorBoard / W&B / console output goes through one RunLogger (logger.py).

rsl-rl's `OnPolicyRunner` builds the algorithm (models, storage, optimiser, multi-GPU set-up); the loop
itself is written here so that each iteration can (a) read the environment's statistics with a single
host transfer instead of rsl-rl's per-step `.cpu()` bookkeeping, (b) update the sampler once after the
rollout (`env.end_rollout()`, for `sampler.accounting.update_every=iteration`) and log its per-bin state,
(c) run the sampler-independent evaluation and (d) write atomic checkpoints that also hold the sampler
and RNG states, so `resume` reproduces iteration count, learning rate and sampler state.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import torch
from rsl_rl.runners import OnPolicyRunner

from bmimic.runs.folder import (
    write_status,
)
from bmimic.runs.record import RunRecord
from bmimic.runs.schema import ENV_STEPS, FAILURE_RATE, ITERATION, WALL_TIME_S, whole_clip_key
from bmimic.runtime import any_rank, torchrun_env
from bmimic.sampling import diagnostics
from bmimic.training.clip_rollouts import CLIP_ROLLOUT_COLUMNS, clip_rollouts, clips_failed, eval_mode
from bmimic.training.config import launch_end_iteration
from bmimic.training.evaluator import summarize
from bmimic.training.health import Health
from bmimic.training.logger import TAG_GROUPS, RunLogger
from bmimic.training.policy import rsl_rl_train_cfg
from bmimic.training.run_state import Checkpoint, Progress, rng_untouched
from bmimic.training.schedule import Schedule, WholeClipSchedule

if TYPE_CHECKING:
    from bmimic.training.whole_clip import WholeClipEvaluation

log = logging.getLogger(__name__)


class _Runner(OnPolicyRunner):
    """rsl-rl's runner, accepting a process group that bmimic initialised before building the env."""

    def _configure_multi_gpu(self) -> None:
        dist = torch.distributed
        if not (dist.is_available() and dist.is_initialized()):
            return super()._configure_multi_gpu()
        self.gpu_world_size = dist.get_world_size()
        self.gpu_global_rank = dist.get_rank()
        self.gpu_local_rank = torchrun_env()[2]
        self.is_distributed = self.gpu_world_size > 1
        self.cfg["multi_gpu"] = {"global_rank": self.gpu_global_rank, "local_rank": self.gpu_local_rank,
                                 "world_size": self.gpu_world_size} if self.is_distributed else None


class Trainer:
    """Owns the rsl-rl algorithm, the env, the evaluator and the run folder's tables. Nothing is written
    into the run folder until `learn` (or `evaluate`, `checkpoint.save`) runs, so a resume refused by
    `checkpoint.load` leaves the folder as it was."""

    def __init__(self, env, evaluator, sampler, feedback, cfg, run_dir: str | os.PathLike, device: str,
                 logger: RunLogger, is_main_rank: bool = True, run_config: dict | None = None,
                 whole_clip: WholeClipEvaluation | None = None,
                 after_evaluation: Callable[[Trainer, dict], bool] | None = None) -> None:
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
        self.fresh_worlds = True
        """The worlds start where the sampler puts them, not where a checkpoint left them (run_state)."""
        self.record = RunRecord(self.run_dir, enabled=is_main_rank)
        """The run's tables (train_metrics, sampler, eval, clip_eval): rows, resume truncation, flushes."""
        self.total_resets = {"nonfinite_resets": 0, "out_of_bounds_resets": 0}
        self.overflow_world_steps = 0
        """World-steps whose contact or constraint buffers overflowed, over the run (metrics.json)."""
        self.checkpoint = Checkpoint(self)
        """Its checkpoint: meta, state, save, load (bmimic.training.run_state)."""
        # A stopping rule after each evaluation (its summary -> True: stop; bmimic.race), when learn()
        # began (time.time()) and the wall time the evaluations took.
        self.after_evaluation = after_evaluation
        self.learn_started_unix_s: float | None = None
        self.eval_time_s = 0.0
        self.health = Health(env.num_envs * self.ppo_cfg.num_steps_per_env)
        self.schedule = Schedule(cfg.eval.every_iters, self.ppo_cfg.save_interval)
        w = cfg.eval.whole_clip
        self.whole_clip = whole_clip
        """The whole-clip evaluation (bmimic.training.whole_clip.WholeClipEvaluation; rank 0, when configured)."""
        self.whole_clip_schedule = WholeClipSchedule(w.every_iters, w.max_share, w.after_success)
        self.last_whole_clip: tuple[int, dict] | None = None
        """(iteration, summary) of the latest whole-clip evaluation of this process."""
        self._whole_clip_s: float | None = None  # how long the latest one took
        self.interrupted = False  # learn() stopped early on a signal (bmimic.training.interrupts)
        self.signals = None  # learn()'s StopSignals: a signal ends an evaluation at once (StopNow)

    # ------------------------------------------------------------------ tables
    def flush_tables(self) -> None:
        """Write the run's tables (rank 0 only: the record of another rank writes nothing)."""
        self.record.flush()

    # ------------------------------------------------------------------ evaluation
    def evaluate(self) -> dict:
        """Evaluate the current policy (eval.parquet row, logged); returns the summary."""
        t0 = time.perf_counter()
        with rng_untouched(), self._at_once(), eval_mode(self.alg.get_policy()) as policy:
            per_bin = self.evaluator.evaluate(policy, self.progress.iteration, self.progress.env_steps,
                                              self.progress.wall_time_s)
        self.record.append("eval", per_bin)
        self.flush_tables()  # evaluations are the expensive rows: never lose them to an interruption
        self.eval_time_s += time.perf_counter() - t0
        summary = summarize(per_bin)
        self.progress.last_eval = summary
        self.logger.evaluation(self.progress.iteration, summary)
        return summary

    def evaluate_whole_clip(self) -> dict:
        """Evaluate whole clips with the current policy (whole_clip*.parquet rows, logged); returns the summary."""
        whole_clip = self.whole_clip
        assert whole_clip is not None, "no whole-clip evaluation is configured"
        t0 = time.perf_counter()
        with eval_mode(self.alg.get_policy()) as policy:
            result = whole_clip.evaluate(policy)
        p = self.progress
        keys = {ITERATION: p.iteration, ENV_STEPS: p.env_steps}
        self.record.append("whole_clip", result.clips.assign(**keys, **{WALL_TIME_S: p.wall_time_s})[
            [ITERATION, ENV_STEPS, WALL_TIME_S, *result.clips.columns]])
        for name, table in (("whole_clip_survival", result.survival), ("whole_clip_failures", result.failures)):
            self.record.append(name, table.assign(**keys)[[ITERATION, ENV_STEPS, *table.columns]])
        self.flush_tables()
        self._whole_clip_s = time.perf_counter() - t0
        self.eval_time_s += self._whole_clip_s
        self.last_whole_clip = (p.iteration, result.summary)
        self.logger.whole_clip(p.iteration, result.summary)
        log.info("whole clips at iteration %d (%.0f s): %s", p.iteration, self._whole_clip_s, ", ".join(
            f"{c} {result.summary[whole_clip_key(c, 'completed')]}/{result.summary[whole_clip_key(c, 'rollouts')]}"
            for c in whole_clip.conditions))
        return result.summary

    def _whole_clip_due(self, summary: dict) -> bool:
        """After a window evaluation (its `summary`): whether the whole-clip schedule asks for one now."""
        if self.whole_clip is None:
            return False
        sched = self.whole_clip_schedule
        sched.opened = sched.opened or bool(self.record.rows("whole_clip"))  # a resumed run had opened it
        estimate = self._whole_clip_s
        if estimate is None:  # none yet: the window evaluation's time per step (both latency-bound on a GPU)
            estimate = self.evaluator.seconds_per_step * self.whole_clip.steps() * len(self.whole_clip.conditions)
            estimate = estimate if math.isfinite(estimate) else 0.0
        elapsed = time.time() - (self.learn_started_unix_s or time.time())
        return sched.due(self.progress.iteration, float(summary.get("eval_success_rate", math.nan)),
                         self.eval_time_s, elapsed, estimate)

    def _clip_outcomes(self, max_s: float | None) -> torch.Tensor:
        """Rank 0, for a sampler that learns from clip outcomes (phc, protomotions): one rollout per clip
        from its first frame (clip_rollouts; a row of clip_eval.parquet each); [C] > 0 where one failed."""
        with rng_untouched(), self._at_once(), eval_mode(self.alg.get_policy()) as policy:
            rows = clip_rollouts(self.evaluator, policy, max_s)
        p = self.progress
        self.record.append("clip_eval", rows.assign(**{ITERATION: p.iteration, ENV_STEPS: p.env_steps})[
            [ITERATION, ENV_STEPS, *CLIP_ROLLOUT_COLUMNS]])
        self.flush_tables()
        log.info("clip rollouts at iteration %d: %d of %d clips failed", p.iteration, rows.failed.sum(), len(rows))
        return clips_failed(rows, self.env.layout.num_clips)

    def _at_once(self):
        """An evaluation ends at once on a stop signal (StopNow): it has nothing to save midway."""
        return self.signals.at_once() if self.signals is not None else contextlib.nullcontext()

    # ------------------------------------------------------------------ the loop
    def learn(self, signals=None) -> None:
        """Train from the current iteration to `max_iterations` (or to `stop_at_iteration`, or until
        `time_limit_s` of training, or until a stop was requested of `signals`
        (training.interrupts.StopSignals): `interrupted` is then True)."""
        env, alg, cfg = self.env, self.alg, self.cfg
        self.signals = signals
        time_limit_s = cfg.time_limit_s
        if self.ppo_cfg.init_at_random_ep_len and self.fresh_worlds:
            # (also after a resume whose worlds start afresh: their time-outs would otherwise fall together)
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
        stop_it = launch_end_iteration(end_it, cfg.stop_at_iteration)  # a pause; the budget stays end_it
        self.logger.start(start_it, stop_it)
        self.learn_started_unix_s = time.time()
        for it in range(start_it, stop_it):
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
            done = self.progress.iteration == stop_it or out_of_time
            self._record_iteration(it, losses, t1 - t0, t2 - t1, steps_per_it, last=done)
            stop = self._evaluate_and_checkpoint(last=done)
            if out_of_time:
                log.info("time limit of %.0f s reached after %d iterations", time_limit_s, self.progress.iteration)
            elif done and stop_it < end_it:
                log.info("paused at iteration %d (stop_at_iteration); resume=true continues it to %d",
                         stop_it, end_it)
            if out_of_time or stop:
                break
            if not done and signals is not None and any_rank(signals.requested, self.device):
                self.interrupted = True
                break
        self.logger.end()

    def _evaluate_and_checkpoint(self, last: bool) -> bool:
        """After an iteration, as scheduled: the evaluation (rank 0) and the sampler's evaluation feedback
        (every rank), a checkpoint, then the stopping rule (`after_evaluation`; True: stop). The rule comes
        last so that it sees this iteration's checkpoint: the race's native judge evaluates its ONNX export."""
        it, summary = self.progress.iteration, None
        evaluates = self.schedule.evaluates(it)
        if evaluates:
            if self.is_main:
                summary = self.evaluate()
                if self._whole_clip_due(summary):
                    summary = {**summary, **self.evaluate_whole_clip()}
            self.feedback.after_evaluation(self._clip_outcomes, self.schedule.eval_every)
        if self.is_main and self.schedule.checkpoints(it, last):
            self.checkpoint.save()
            write_status(self.run_dir, "running", it)
        if not evaluates or self.after_evaluation is None:
            return False
        stop = summary is not None and bool(self.after_evaluation(self, summary))
        if self.runner.is_distributed:
            # Rank 0 alone evaluates and decides (bmimic.race); every rank stops after the same iteration.
            stop = any_rank(stop, self.device)
        return stop

    def _record_iteration(self, it: int, losses: dict, collect_s: float, learn_s: float, steps: int,
                       last: bool = False) -> dict:
        stats = self.env.pop_iteration_stats()
        s = diagnostics.summary(self.sampler, torch.as_tensor(stats["bin_episodes"]),
                                torch.as_tensor(stats["bin_failures"]), total_episodes=stats["episodes"])
        row = {
            ITERATION: it,
            ENV_STEPS: self.progress.env_steps,
            WALL_TIME_S: self.progress.wall_time_s,
            "mean_episode_length": stats["mean_episode_length"],
            "mean_reward": stats["mean_episode_reward"],
            "episodes": stats["episodes"],
            FAILURE_RATE: stats["failures"] / stats["episodes"] if stats["episodes"] else math.nan,
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
        row.update((k, v) for k, v in stats.items() if k.partition("/")[0] in TAG_GROUPS)  # reward/, termination/, ...
        for key in self.total_resets:
            self.total_resets[key] += int(stats[key])
        self.overflow_world_steps += int(stats["overflow_worlds"])
        self.record.append("train_metrics", row)
        self.health.check(it, row, self.ppo_cfg.learning_rate, self.runner.is_distributed, self.device)
        sampler_table = it % self._sampler_every == 0 or last
        if sampler_table:
            self.record.append("sampler", diagnostics.bin_table(
                it, self.env.layout, torch.as_tensor(stats["bin_episodes"]), torch.as_tensor(stats["bin_failures"]),
                self.sampler))
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

