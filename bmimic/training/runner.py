"""The PPO training loop: rsl-rl-lib's PPO (as `GraphPPO`, see ppo.py), this project's logging,
evaluation and checkpoints.

rsl-rl's `OnPolicyRunner` builds the algorithm (models, storage, optimiser, multi-GPU set-up); the
loop itself is written here so that each iteration can (a) read the environment's statistics with a
single host transfer instead of rsl-rl's per-step `.cpu()` bookkeeping, (b) update the sampler once
after the rollout (`env.end_rollout()`, for `sampler.accounting.update_every=iteration`) and log its per-bin
state, (c) run the sampler-independent evaluation and (d) write atomic checkpoints that also hold
the sampler and RNG states, so `resume` reproduces iteration count, learning rate and sampler state.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd
import torch
from rsl_rl.runners import OnPolicyRunner

from bmimic import BmimicError
from bmimic.runs import (
    CHECKPOINT_FORMAT,
    atomic_torch_save,
    atomic_write_parquet,
    key_allowed,
    load_checkpoint_file,
    rng_state,
    set_rng_state,
    write_status,
)
from bmimic.sampling import diagnostics
from bmimic.training.evaluation import summarize

log = logging.getLogger(__name__)


def rsl_rl_train_cfg(ppo, run_name: str) -> dict:
    """The rsl-rl-lib 5.5 `train_cfg` dict for a PPOConfig."""
    return {
        "num_steps_per_env": ppo.num_steps_per_env,
        "save_interval": ppo.save_interval,
        "obs_groups": {"actor": ["policy"], "critic": list(ppo.critic_obs_groups)},
        "run_name": run_name,
        "check_for_nan": False,  # a host sync per step; the env resets non-finite worlds itself
        "torch_compile_mode": ppo.torch_compile_mode,
        "logger": "tensorboard",
        "algorithm": {
            "class_name": "bmimic.training.ppo:GraphPPO",
            "cuda_graphs": ppo.cuda_graphs,
            "learning_rate": ppo.learning_rate,
            "num_learning_epochs": ppo.num_learning_epochs,
            "num_mini_batches": ppo.num_mini_batches,
            "schedule": ppo.schedule,
            "desired_kl": ppo.desired_kl,
            "clip_param": ppo.clip_param,
            "entropy_coef": ppo.entropy_coef,
            "value_loss_coef": ppo.value_loss_coef,
            "use_clipped_value_loss": ppo.use_clipped_value_loss,
            "gamma": ppo.gamma,
            "lam": ppo.lam,
            "max_grad_norm": ppo.max_grad_norm,
            "normalize_advantage_per_mini_batch": ppo.normalize_advantage_per_mini_batch,
            "rnd_cfg": None,
            "symmetry_cfg": None,
        },
        "actor": {
            "class_name": "MLPModel",
            "hidden_dims": list(ppo.actor_hidden_dims),
            "activation": ppo.activation,
            "obs_normalization": ppo.obs_normalization,
            "distribution_cfg": {
                "class_name": "GaussianDistribution",
                "init_std": ppo.init_noise_std,
                "std_type": ppo.noise_std_type,
            },
        },
        "critic": {
            "class_name": "MLPModel",
            "hidden_dims": list(ppo.critic_hidden_dims),
            "activation": ppo.activation,
            "obs_normalization": ppo.obs_normalization,
        },
    }


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


class CheckpointMismatchError(BmimicError):
    """A checkpoint that does not fit the environment, sampler or networks built from this config."""


class Trainer:
    """Owns the rsl-rl algorithm, the env, the evaluator and the run folder's tables.

    Nothing is written into the run folder until `learn` (or `evaluate`, `save_checkpoint`) runs, so
    a resume refused by `restore` leaves the folder as it was.
    """

    def __init__(self, env, evaluator, sampler, ppo_cfg, run_dir: str | os.PathLike, device: str,
                 run_name: str, eval_every_iters: int, sampler_log_every: int | None = None,
                 logger: str = "tensorboard", wandb_project: str = "bmimic", progress_bar: bool = True,
                 export_onnx: bool = True, is_main_rank: bool = True, run_config: dict | None = None) -> None:
        self.env = env
        self.evaluator = evaluator
        self.sampler = sampler
        self.ppo_cfg = ppo_cfg
        self.run_dir = Path(run_dir)
        self.device = device
        self.eval_every_iters = eval_every_iters
        # sampler.log_every (null: decided in learn() from the number of bins and iterations).
        self.sampler_log_every = sampler_log_every
        self._sampler_every = 1
        self.progress_bar = progress_bar
        self.export_onnx_enabled = export_onnx
        self.is_main = is_main_rank
        torch.set_float32_matmul_precision(ppo_cfg.float32_matmul_precision)
        self.runner = _Runner(env, rsl_rl_train_cfg(ppo_cfg, run_name), log_dir=None, device=device)
        self.alg = self.runner.alg
        self.progress = Progress()
        self.train_rows: list[dict] = []
        self.sampler_rows: list[pd.DataFrame] = []
        self.eval_rows: list[pd.DataFrame] = []
        self.run_config = run_config
        if logger == "wandb":
            try:
                import wandb  # noqa: F401  (fail at start-up, not at the first logged scalar)
            except ImportError:
                raise BmimicError("logger=wandb needs the wandb package: pip install wandb") from None
        self._writer_args = (logger, wandb_project, run_name) if self.is_main else None
        self.writer = None  # opened by open_writer(), once the run folder may be written
        self.ckpt_dir = self.run_dir / "checkpoints"
        self.total_resets = {"nonfinite_resets": 0, "out_of_bounds_resets": 0}

    # ------------------------------------------------------------------ logging back-ends
    def open_writer(self) -> None:
        """Open the TensorBoard / W&B writer (idempotent); the first write into the run folder."""
        if self._writer_args is not None and self.writer is None:
            self.writer = self._make_writer(*self._writer_args)
            self._writer_args = None

    def _make_writer(self, logger: str, project: str, run_name: str):
        if logger == "none":
            return None
        if logger == "wandb":
            import wandb

            return _WandbWriter(wandb.init(project=project, name=run_name, dir=str(self.run_dir)))
        from torch.utils.tensorboard import SummaryWriter

        return SummaryWriter(log_dir=str(self.run_dir / "tensorboard"), flush_secs=30)

    # ------------------------------------------------------------------ checkpoints
    def meta(self) -> dict:
        """What a checkpoint must match to be loaded into this trainer (plain values)."""
        obs = self.env.get_observations()
        motion = self.env.reference.motion
        digest = hashlib.sha256(motion.joint_pos.tobytes())
        digest.update(motion.body_pos_w.tobytes())
        return {
            "num_envs": int(self.env.num_envs),
            "num_actions": int(self.env.num_actions),
            "obs_dims": {k: int(v.shape[-1]) for k, v in obs.items()},
            "sampler_kind": str(self.sampler.state_dict().get("kind")),
            "num_bins": int(self.env.layout.num_bins),
            "motion_frames": int(motion.num_frames),
            "motion_fps": float(motion.fps),
            "motion_sha256": digest.hexdigest()[:16],
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
        it = self.progress.iteration
        path = self.ckpt_dir / f"model_{it}.pt"
        # Tables first: a checkpoint must never be ahead of the rows a resume keeps.
        self.flush_tables()
        state = self.checkpoint_state()
        atomic_torch_save(path, state)
        atomic_torch_save(self.ckpt_dir / "latest.pt", state)
        if self.export_onnx_enabled:
            from bmimic.training.export import export_checkpoint_onnx

            try:  # policy_<it>.onnx and the BeyondMimic-compatible motion_policy_<it>.onnx
                export_checkpoint_onnx(self.alg.get_policy(), self.env, self.ckpt_dir, it)
            except Exception as e:  # export must never cost a training run
                log.warning("ONNX export failed at iteration %d: %s", it, e)
        return path

    def load_checkpoint(self, path: str | os.PathLike, trust: bool = False) -> None:
        """Read a checkpoint (weights_only unless `trust`) and `restore` it."""
        self.restore(load_checkpoint_file(path, "cpu", trust), path)

    def restore(self, state: dict, path: str | os.PathLike = "checkpoint", allowed: tuple | list = ()) -> None:
        """Load networks, optimiser, counters, sampler and RNG states; reads the run's tables but
        writes nothing. Raises CheckpointMismatchError (one line) when the checkpoint does not fit.

        `allowed` (resume_allow_changes) may accept another num_envs or motion; observation and
        action sizes, sampler kind and bins must match (the networks and sampler state depend on them)."""
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
            lines = [x.strip() for x in str(e).splitlines() if x.strip()]
            detail = lines[1] if len(lines) > 1 else (lines[0] if lines else type(e).__name__)
            raise CheckpointMismatchError(f"{path}: its networks do not fit this config: {detail}") from None
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
    def _table_path(self, name: str) -> Path:
        return self.run_dir / f"{name}.parquet"

    def _truncate_tables(self, iteration: int) -> None:
        """On resume, keep only rows of iterations the checkpoint had completed."""
        for name, rows in (("train_metrics", self.train_rows), ("sampler", self.sampler_rows), ("eval", self.eval_rows)):
            path = self._table_path(name)
            if path.exists():
                try:
                    df = pd.read_parquet(path)
                except Exception as e:  # noqa: BLE001 - any reader error: the table is damaged
                    raise CheckpointMismatchError(
                        f"{path}: cannot be read ({type(e).__name__}); move it aside to resume without its "
                        "rows") from None
                df = df[df["iteration"] <= iteration] if name == "eval" else df[df["iteration"] < iteration]
                if name == "train_metrics":
                    self.train_rows.extend(df.to_dict("records"))
                else:
                    rows.append(df)

    def flush_tables(self) -> None:
        if not self.is_main:
            return
        if self.train_rows:
            atomic_write_parquet(self._table_path("train_metrics"), pd.DataFrame(self.train_rows))
        if self.sampler_rows:
            atomic_write_parquet(self._table_path("sampler"), pd.concat(self.sampler_rows, ignore_index=True))
        if self.eval_rows:
            atomic_write_parquet(self._table_path("eval"), pd.concat(self.eval_rows, ignore_index=True))

    # ------------------------------------------------------------------ evaluation
    def evaluate(self) -> dict:
        policy = self.alg.get_policy()
        was_training = policy.training
        policy.eval()
        per_bin = self.evaluator.evaluate(policy, self.progress.iteration, self.progress.env_steps, self.progress.wall_time_s)
        if was_training:
            policy.train()
        self.eval_rows.append(per_bin)
        self.flush_tables()  # evaluations are the expensive rows: never lose them to an interruption
        summary = summarize(per_bin)
        self.progress.last_eval = summary
        self.open_writer()
        if self.writer is not None:
            for k, v in summary.items():
                self.writer.add_scalar(f"Eval/{k}", v, self.progress.iteration)
        log.info(
            "eval at iteration %d: failure rate %.3f, bins mastered %.2f, MPKPE %.1f mm",
            self.progress.iteration, summary["eval_failure_rate"], summary["eval_bins_mastered_frac"],
            summary["eval_mpkpe_mm"],
        )
        return summary

    # ------------------------------------------------------------------ the loop
    def learn(self, num_iterations: int, init_at_random_ep_len: bool, time_limit_s: float | None = None) -> None:
        env, alg = self.env, self.alg
        self.open_writer()
        if init_at_random_ep_len and self.progress.iteration == 0:
            # In place: the environment's captured CUDA graphs hold this buffer's address.
            env.episode_length_buf.copy_(torch.randint_like(env.episode_length_buf, high=int(env.max_episode_length)))
        obs = env.get_observations().to(self.device)
        alg.train_mode()
        if self.runner.is_distributed:
            alg.broadcast_parameters()
        start_it = self.progress.iteration
        end_it = num_iterations
        steps_per_it = self.ppo_cfg.num_steps_per_env * env.num_envs * self.runner.gpu_world_size
        self._sampler_every = diagnostics.log_every(self.sampler_log_every, env.layout.num_bins, end_it)
        if self.sampler_log_every is None and self._sampler_every > 1:
            log.info("sampler.parquet: %d bins x %d iterations, so one table every %d iterations and at the last "
                     "(sampler.log_every=null keeps it under about %.0e rows)", env.layout.num_bins, end_it,
                     self._sampler_every, diagnostics.MAX_SAMPLER_ROWS)
        bar = None
        if self.progress_bar and self.is_main and end_it > start_it:
            from tqdm import tqdm

            bar = tqdm(total=end_it, initial=start_it, desc="train", unit="it", dynamic_ncols=True)
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
            out_of_time = time_limit_s is not None and self.progress.wall_time_s >= time_limit_s
            if self.runner.is_distributed and time_limit_s is not None:
                # Every rank stops after the same iteration (ranks' clocks differ; a rank that went
                # on alone would wait forever in the next collective).
                flag = torch.tensor(float(out_of_time), device=self.device)
                torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
                out_of_time = bool(flag.item())
            done = self.progress.iteration == end_it or out_of_time
            row = self._log_iteration(it, losses, t1 - t0, t2 - t1, steps_per_it, last=done)
            if bar is not None:
                bar.update(1)
                resets = sum(self.total_resets.values())
                bar.set_postfix(ep_len=f"{row['mean_episode_length']:.0f}", reward=f"{row['mean_reward']:.2f}",
                                fps=f"{row['fps']:.0f}", **({"broken_worlds": int(resets)} if resets else {}))
            if self.is_main and (self.eval_every_iters and self.progress.iteration % self.eval_every_iters == 0):
                self.evaluate()
            if self.is_main and (self.progress.iteration % self.ppo_cfg.save_interval == 0 and not done):
                self.save_checkpoint()
                write_status(self.run_dir, "running", self.progress.iteration)
            if out_of_time:
                log.info("time limit of %.0f s reached after %d iterations", time_limit_s, self.progress.iteration)
                break
        if bar is not None:
            bar.close()

    def _log_iteration(self, it: int, losses: dict, collect_s: float, learn_s: float, steps: int,
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
        broken = stats["nonfinite_resets"] + stats["out_of_bounds_resets"]
        for key in self.total_resets:
            self.total_resets[key] += int(stats[key])
        if broken > 0:
            log.warning("iteration %d: reset %d broken world-steps (%d non-finite, %d beyond sim.max_abs_qvel / "
                        "sim.max_root_distance_m / env.max_abs_step_reward); %d so far", it, int(broken),
                        int(stats["nonfinite_resets"]), int(stats["out_of_bounds_resets"]),
                        sum(self.total_resets.values()))
        if stats["overflow_worlds"] > 0:
            log.warning("iteration %d: %d world-steps overflowed the contact/constraint buffers; raise "
                        "sim.nconmax / sim.njmax", it, int(stats["overflow_worlds"]))
        self.train_rows.append(row)
        sampler_table = it % self._sampler_every == 0 or last
        if sampler_table:
            self.sampler_rows.append(
                diagnostics.bin_table(it, self.env.layout, torch.as_tensor(stats["bin_episodes"]),
                                      torch.as_tensor(stats["bin_failures"]), self.sampler)
            )
        if self.writer is not None:
            self._write_scalars(it, row, sampler_table)
        if not self.progress_bar and self.is_main and (it % 10 == 0):
            log.info("it %d: episode length %.1f, reward %.3f, failure rate %.3f, lr %.1e, %.0f steps/s", it,
                     row["mean_episode_length"], row["mean_reward"], row["failure_rate"], row["learning_rate"],
                     row["fps"])
        return row

    def _write_scalars(self, it: int, row: dict, sampler_histogram: bool = False) -> None:
        w = self.writer
        names = {
            "mean_episode_length": "Train/mean_episode_length", "mean_reward": "Train/mean_reward",
            "failure_rate": "Train/failure_rate", "episodes": "Train/episodes",
            "sampling_entropy": "Sampler/entropy", "top1_prob": "Sampler/top1_prob", "top1_bin": "Sampler/top1_bin",
            "fps": "Perf/total_fps", "collection_time_s": "Perf/collection_time", "learning_time_s": "Perf/learning_time",
            "learning_rate": "Loss/learning_rate", "action_std": "Policy/mean_std",
            "nonfinite_resets": "Sim/nonfinite_resets", "out_of_bounds_resets": "Sim/out_of_bounds_resets",
            "overflow_worlds": "Sim/overflow_worlds",
        }
        for k, v in row.items():
            if isinstance(v, float) and math.isnan(v):
                continue
            tag = names.get(k)
            if tag is None and "/" in k:
                prefix, name = k.split("/", 1)
                tag = {"loss": "Loss", "reward": "Episode_Reward", "termination": "Episode_Termination",
                       "metrics": "Metrics"}[prefix] + "/" + name
            if tag is not None:
                w.add_scalar(tag, v, it)
        if sampler_histogram and hasattr(w, "add_histogram_raw"):
            probs = self.sampler.probabilities().detach().cpu().double().numpy()
            edges = self.env.layout.edges_s.cpu().numpy()
            w.add_histogram_raw(
                "Sampler/probability_over_time_s", min=float(edges[0]), max=float(edges[-1]), num=len(probs),
                sum=float((probs * edges[:-1]).sum()), sum_squares=float((probs * edges[:-1] ** 2).sum()),
                bucket_limits=edges[1:].tolist(), bucket_counts=probs.tolist(), global_step=it,
            )

    def close(self) -> None:
        self.flush_tables()
        self.alg.release_graphs()  # before destroy_process_group: graphs may hold NCCL calls
        if self.writer is not None:
            self.writer.close()


def _count(value) -> float:
    """A counter from a table row (absent or NaN in rows written before the column existed: 0)."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        return 0.0
    return 0.0 if math.isnan(value) else value


class _WandbWriter:
    """The subset of SummaryWriter the trainer uses, over a W&B run (offline with WANDB_MODE=offline)."""

    def __init__(self, run) -> None:
        self.run = run

    def add_scalar(self, tag: str, value: float, step: int) -> None:
        self.run.log({tag: value}, step=step)

    def close(self) -> None:
        self.run.finish()
