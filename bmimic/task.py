"""The one composition root: from a composed config, everything a run or a tool is made of.

`build_task` builds the robot model and its resolved info, the motion at the control rate and the
bin layout over it (the config is validated against the motion); `build_training` adds the sampler
and the training environment; `build_evaluator` the sampler-independent evaluator (with
`robust=True`: domain randomisation, observation noise and pushes on); `build_whole_clip` the
whole-clip evaluation; `build_trainer` the PPO trainer with its logger. train, eval, play, bench,
export and sim2sim build through here and import no other entry point: this is the only module that
calls the constructors of TrackingEnv, the samplers, Evaluator and Trainer.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, cast

from bmimic.config import ConfigError
from bmimic.config.checks import check_motion_fit

if TYPE_CHECKING:
    import mujoco

    from bmimic.config.placement import PlacedConfig
    from bmimic.envs.tracking_env import TrackingEnv
    from bmimic.motion.motion import Motion
    from bmimic.robot.config import RobotInfo
    from bmimic.sampling.base import BinSampler
    from bmimic.sampling.bins import Layout
    from bmimic.sampling.feedback import SamplerFeedback


@dataclass
class Task:
    """What a runtime-resolved config describes, built: the robot, its motion and the bins over it."""

    cfg: PlacedConfig
    """The composed, runtime-resolved, validated config, read-only (bmimic.config.placed)."""
    device: str
    """Torch device of every tensor."""
    mjm: mujoco.MjModel
    """The robot's host model (the training environment's)."""
    robot: RobotInfo
    """Gains, limits, default pose and body indices in model order."""
    motion: Motion
    """The motion at the control rate."""
    layout: Layout
    """The bin layout of `cfg.sampler.bins` over the motion."""

    def reference(self):
        """The motion as the environment's device tensors (bmimic.motion.ReferenceMotion)."""
        from bmimic.motion.reference import ReferenceMotion

        return ReferenceMotion.for_robot(self.motion, self.robot, self.device)


@dataclass
class Training:
    """A task with its motion sampler, the sampler's feedback and the training environment."""

    task: Task
    sampler: BinSampler
    """The sampler of `cfg.sampler` over the task's bins."""
    feedback: SamplerFeedback
    """What the sampler hears of the env and of evaluations."""
    env: TrackingEnv
    """The training environment (`mode="train"`, `cfg.num_envs` worlds)."""


def build_task(cfg: PlacedConfig, device: str) -> Task:
    """Robot model, robot info, motion and bins of a runtime-resolved config that `validate` passed (the
    caller checks a config once: bmimic.job, bmimic.evaluation.saved_run); here only what needs the
    motion is checked (check_motion_fit, the motion's speeds)."""
    from bmimic.motion.library import clip_names, load_any
    from bmimic.robot import load_mjmodel, resolve_robot
    from bmimic.sampling.config import layout_for, min_motion_bin_s

    mjm = load_mjmodel(cfg=cfg.robot)
    robot = resolve_robot(cfg.robot, mjm)
    motion = load_any(cfg.motion, mjm, bin_size_s=min_motion_bin_s(cfg.sampler), lafan_dir=cfg.data.lafan_dir,
                         control_fps=1.0 / (cfg.sim.timestep_s * cfg.sim.decimation))
    check_motion_fit(cfg, motion.duration_s)
    names = clip_names(cfg.motion, motion)
    check_motion_speeds(motion, cfg.sim.max_abs_qvel, names)
    layout = layout_for(cfg.sampler, motion.num_frames, motion.fps, device=device, clip_starts=motion.clip_starts,
                        clip_names=names)
    return Task(cfg, device, mjm, robot, motion, layout)


def build_training(cfg: PlacedConfig, device: str, task: Task | None = None) -> Training:
    """The sampler, its feedback and the training environment (`task`: build_task's result,
    when the caller has it)."""
    from bmimic.envs.config import episode_length_steps
    from bmimic.envs.tracking_env import TrackingEnv
    from bmimic.motion.library import clip_weights
    from bmimic.sampling.config import make_sampler
    from bmimic.sampling.feedback import SamplerFeedback

    task = task if task is not None else build_task(cfg, device)
    check_num_envs_fit(cfg, task.mjm, device, cfg.num_envs, cfg.ppo.num_steps_per_env)
    check_networks_fit(cfg, task.mjm, device)
    sampler = make_sampler(cfg.sampler, task.layout.num_bins, device, layout=task.layout,
                           clip_weights=clip_weights(cfg.motion))
    feedback = SamplerFeedback.from_config(cfg.sampler.accounting, sampler, task.layout, cfg.num_envs,
                                           episode_length_steps(cfg.env, cfg.sim), device=device)
    env = TrackingEnv(cfg.env, cfg.sim, task.mjm, task.robot, task.reference(), cfg.num_envs, device,
                      feedback=feedback)
    return Training(task, sampler, feedback, env)


def build_evaluator(task: Task, robust: bool = False):
    """The sampler-independent evaluator in an environment of its own (`eval.max_envs` worlds at most;
    robust: with domain randomisation, observation noise and pushes, as configured for training)."""
    from bmimic.envs.tracking_env import TrackingEnv
    from bmimic.robot import load_mjmodel
    from bmimic.training.evaluator import Evaluator

    cfg, device, layout = task.cfg, task.device, task.layout
    check_evaluation_fits(layout.num_bins, cfg.eval.episodes_per_bin)
    total = layout.num_bins * cfg.eval.episodes_per_bin
    n = max(1, min(total, cfg.eval.max_envs))
    mjm = load_mjmodel(cfg=cfg.robot)
    check_num_envs_fit(cfg, mjm, device, n, 0)
    env = TrackingEnv(cfg.env, cfg.sim, mjm, task.robot, task.reference(), n, device, mode="eval", robust=robust,
                      layout=layout)
    # No episode outlives its clip, so a longer horizon only adds steps in which nothing is alive
    # (eval.horizon_s=1e300 would loop for ever): the loop stops at the motion's length.
    horizon_s = min(float(cfg.eval.horizon_s), task.motion.duration_s + env.step_dt)
    return Evaluator(env, layout, task.motion.segments, cfg.eval.episodes_per_bin, horizon_s,
                     max_mpkpe_rel_mm=cfg.eval.max_mpkpe_rel_mm)


def build_whole_clip(task: Task):
    """The whole-clip evaluation of `eval.whole_clip` (bmimic.training.whole_clip): its conditions and
    rollouts, each condition's environment built on first use. A clip longer than
    `eval.whole_clip.max_clip_s` is refused here (ConfigError), before anything runs: never cut short."""
    from functools import partial

    import numpy as np

    from bmimic.training.clip_rollouts import clip_bounds
    from bmimic.training.whole_clip import WholeClipEvaluation

    cfg, layout = task.cfg, task.layout
    w = cfg.eval.whole_clip
    step_dt = cfg.sim.timestep_s * cfg.sim.decimation
    starts, ends = clip_bounds(layout)
    longest = int(np.argmax(ends - starts))
    length_s = (int(ends[longest] - starts[longest]) - 1) * step_dt
    if length_s > w.max_clip_s:
        name = list(getattr(layout, "clip_names", ("motion",)))[longest]
        raise ConfigError(f"eval.whole_clip.max_clip_s: clip {name!r} is {length_s:g} s long, longer than the "
                          f"{w.max_clip_s:g} s a whole-clip evaluation holds; it is refused, never cut short "
                          f"(set eval.whole_clip.max_clip_s={math.ceil(length_s)} to evaluate it)")
    return WholeClipEvaluation(partial(_whole_clip_evaluator, task), layout, list(w.conditions), int(w.rollouts),
                               seed=int(cfg.seed), device=task.device)


def _whole_clip_evaluator(task: Task, condition: str, per_clip: int):
    """One condition's evaluator for whole-clip rollouts: `per_clip` x clips worlds (eval.max_envs at most),
    robust for a perturbed condition, its episode limit derived so that the longest clip fits."""
    import dataclasses

    from omegaconf import OmegaConf

    from bmimic.envs.config import EnvConfig
    from bmimic.envs.tracking_env import TrackingEnv
    from bmimic.robot import load_mjmodel
    from bmimic.runs.schema import CONDITIONS
    from bmimic.training.clip_rollouts import clip_bounds
    from bmimic.training.evaluator import Evaluator

    cfg, device, layout = task.cfg, task.device, task.layout
    starts, ends = clip_bounds(layout)
    n = max(1, min(per_clip * len(starts), cfg.eval.max_envs))
    mjm = load_mjmodel(cfg=cfg.robot)
    check_num_envs_fit(cfg, mjm, device, n, 0)
    step_dt = cfg.sim.timestep_s * cfg.sim.decimation
    steps = int((ends - starts).max())  # more than the longest rollout's steps: its time-out never comes
    env_cfg = cast(EnvConfig, OmegaConf.to_object(cfg.env))
    env_cfg = dataclasses.replace(env_cfg, episode_length_s=max(float(env_cfg.episode_length_s), steps * step_dt))
    env = TrackingEnv(env_cfg, cfg.sim, mjm, task.robot, task.reference(), n, device, mode="eval",
                      robust=CONDITIONS[condition].perturbed, layout=layout)
    if env.max_episode_length < steps - 1:
        raise ConfigError(f"eval.whole_clip: the evaluation's episode limit ({env.max_episode_length} steps) is shorter "
                          f"than the longest clip ({steps - 1} steps)")
    return Evaluator(env, layout, task.motion.segments, 1, (steps - 1) * step_dt,
                     max_mpkpe_rel_mm=cfg.eval.max_mpkpe_rel_mm)


def build_trainer(training: Training, evaluator, run_dir: str | Path, is_main_rank: bool = True,
                  run_config: dict | None = None, whole_clip=None, after_evaluation: Callable | None = None):
    """The PPO trainer of `training` with the config's logger (TensorBoard, W&B or none) and console
    line; rank 0 alone logs and writes (`is_main_rank`). `run_config`: the resolved config that
    checkpoints carry; `whole_clip`: rank 0's whole-clip evaluation (build_whole_clip) or None;
    `after_evaluation(trainer, summary) -> bool`: a stopping rule after each evaluation (bmimic.race)."""
    from bmimic.training.logger import RunLogger
    from bmimic.training.runner import Trainer

    cfg = training.task.cfg
    logger = RunLogger(cfg.logger, run_dir, cfg.run_name, cfg.wandb_project,
                       progress_bar=cfg.progress_bar and is_main_rank, enabled=is_main_rank)
    return Trainer(training.env, evaluator, training.sampler, training.feedback, cfg, run_dir, training.task.device,
                   logger, is_main_rank=is_main_rank, run_config=run_config, whole_clip=whole_clip,
                   after_evaluation=after_evaluation)


def check_motion_speeds(motion, max_abs_qvel: float, clip_names=None) -> None:
    """Refuse a motion whose velocities exceed sim.max_abs_qvel: every world started on it (reference
    state initialisation) would break at once and the run would train on nothing. A library's message
    names the clip (`clip_names`, one per clip) and its time."""
    import numpy as np

    for name in ("joint_vel", "body_lin_vel_w", "body_ang_vel_w"):
        values = np.abs(getattr(motion, name))
        top = float(np.nanmax(values)) if values.size else 0.0
        if not top <= max_abs_qvel:
            where = ""
            if clip_names is not None and len(clip_names) > 1:
                frame = int(np.argmax(np.nan_to_num(values, nan=np.inf).reshape(len(values), -1).max(axis=1)))
                k = int(np.searchsorted(motion.clip_starts, frame, side="right") - 1)
                where = f" in clip {clip_names[k]} at {(frame - int(motion.clip_starts[k])) / motion.fps:.2f} s"
            raise ConfigError(f"motion: its {name} reaches {top:.3g}{where}, above sim.max_abs_qvel={max_abs_qvel:g}: "
                              "every world started on it would break (a non-physical motion, or a unit error)")


# --------------------------------------------------------------------------------------------- memory
def check_num_envs_fit(cfg: PlacedConfig, mjm, device: str, num_worlds: int, rollout_steps: int) -> None:
    """Refuse `num_worlds` that would not fit in the device's free memory, before allocating them.

    The estimate per world is the MuJoCo-Warp state (measured on the host for one extra world) plus
    the rollout storage (`rollout_steps` x observations, actions and scalars, observations taken as
    16 floats per degree of freedom, about the G1's 446) plus as much again for the step's
    temporaries: rough, but it tells 10 million worlds from 10 thousand before anything is allocated.
    """
    from bmimic.sim.simulator import physics_bytes_per_world

    physics = physics_bytes_per_world(mjm, cfg.sim)
    rollout = rollout_steps * (16 * mjm.nv + 4 * mjm.nu + 8) * 4
    per_world = 2 * physics + rollout
    need = per_world * num_worlds
    free = free_memory_bytes(device)
    if free is not None and need > free:
        raise ConfigError(
            f"num_envs: {num_worlds} worlds need about {_gib(need)} ({per_world / 1024:.0f} KiB per world: "
            f"physics {physics / 1024:.0f} KiB, rollout {rollout / 1024:.0f} KiB, temporaries), but "
            f"{device} has {_gib(free)} free; about {max(int(free // per_world), 0)} fit")


def check_networks_fit(cfg: PlacedConfig, mjm, device: str) -> None:
    """Refuse actor and critic layer sizes whose parameters would not fit in the device's free memory,
    before building them: weights, gradients and Adam's two moments (4 floats per parameter) plus a
    mini-batch's activations, inputs taken as 16 floats per degree of freedom (as check_num_envs_fit)."""
    inputs, outputs = 16 * mjm.nv, mjm.nu
    batch = cfg.num_envs * cfg.ppo.num_steps_per_env // max(cfg.ppo.num_mini_batches, 1)
    need, worst = 0, ""
    for key, out in (("actor_hidden_dims", outputs), ("critic_hidden_dims", 1)):
        sizes = [inputs, *[int(d) for d in getattr(cfg.ppo, key)], out]
        params = sum(a * b + b for a, b in zip(sizes[:-1], sizes[1:]))
        need_here = 16 * params + 3 * 4 * batch * sum(sizes)
        need += need_here
        worst = key if need_here * 2 >= need else worst
    free = free_memory_bytes(device)
    if free is not None and need > free:
        raise ConfigError(f"ppo.{worst}: the actor and critic networks need about {_gib(need)} (parameters, "
                          f"gradients, Adam moments and activations), but {device} has {_gib(free)} free; "
                          f"choose smaller layers (ppo.actor_hidden_dims={list(cfg.ppo.actor_hidden_dims)}, "
                          f"ppo.critic_hidden_dims={list(cfg.ppo.critic_hidden_dims)})")


def check_evaluation_fits(num_bins: int, episodes_per_bin: int, key: str = "eval.episodes_per_bin") -> None:
    """Refuse an evaluation whose episode table (one row of about 40 numbers per episode, plus its
    start frames) would not fit in host memory: `--episodes-per-bin 100000000` must not run for days."""
    episodes = num_bins * episodes_per_bin
    need = episodes * 48 * 8
    free = free_memory_bytes("cpu")
    if free is not None and need > free // 2:
        raise ConfigError(f"{key}: {num_bins} bins x {episodes_per_bin} episodes = {episodes} "
                          f"episodes need about {_gib(need)} for their rows alone, more than half of the "
                          f"{_gib(free)} free; about {max(int(free // 2 // (48 * 8 * num_bins)), 1)} per bin fit")


def _gib(n: float) -> str:
    return f"{n / 2**40:.1f} TiB" if n >= 2**40 else f"{n / 2**30:.1f} GiB"


def free_memory_bytes(device: str) -> int | None:
    """Free memory of a torch device (CPU: MemAvailable of /proc/meminfo); None when unknown."""
    if device.startswith("cuda"):
        import torch

        try:
            return int(torch.cuda.mem_get_info(torch.device(device))[0])
        except (RuntimeError, AssertionError):
            return None
    from bmimic.runtime import available_memory_bytes

    return available_memory_bytes()
