"""Placing a composed config on this machine: the values left `auto` or null filled in for its device
(resolve_runtime), then, once validated, the config made read-only and typed (placed)."""

from __future__ import annotations

from typing import TYPE_CHECKING, cast

from omegaconf import DictConfig, OmegaConf

if TYPE_CHECKING:
    from bmimic.config.schema import TrainConfig
    from bmimic.training.config import EvalConfig, WholeClipConfig

    class _PlacedWholeClip(WholeClipConfig):
        rollouts: int

    class _PlacedEval(EvalConfig):
        episodes_per_bin: int
        whole_clip: _PlacedWholeClip

    class PlacedConfig(TrainConfig):
        """TrainConfig after resolve_runtime: the values it fills in for this machine are not null.
        The type checker's view only: at run time the config stays a (read-only) DictConfig."""

        num_envs: int
        max_iterations: int
        eval: _PlacedEval

GPU_DEFAULT_NUM_ENVS = 4096
CPU_DEFAULT_NUM_ENVS = 8
CPU_DEFAULT_MAX_ITERATIONS = 4
GPU_WHOLE_CLIP_ROLLOUTS = 128
CPU_WHOLE_CLIP_ROLLOUTS = 2


def resolve_runtime(cfg, device: str) -> None:
    """Fill the `auto`/null top-level values in place for this machine; called once before
    bmimic.config.checks.validate."""
    on_gpu = device.startswith("cuda")
    cfg.device = device
    if cfg.num_envs is None:
        cfg.num_envs = GPU_DEFAULT_NUM_ENVS if on_gpu else CPU_DEFAULT_NUM_ENVS
    if cfg.max_iterations is None:
        cfg.max_iterations = cfg.ppo.max_iterations if on_gpu else CPU_DEFAULT_MAX_ITERATIONS
    if "schedule_iterations" in cfg.sampler and cfg.sampler.schedule_iterations is None:
        cfg.sampler.schedule_iterations = cfg.max_iterations  # EGM: a schedule that spans training
    if cfg.eval.episodes_per_bin is None:
        cfg.eval.episodes_per_bin = 32 if on_gpu else 1
    if cfg.eval.whole_clip.rollouts is None:
        cfg.eval.whole_clip.rollouts = GPU_WHOLE_CLIP_ROLLOUTS if on_gpu else CPU_WHOLE_CLIP_ROLLOUTS


def placed(cfg: DictConfig) -> PlacedConfig:
    """The config from here on: read-only, and typed as its schema for everything downstream.

    At run time it stays the DictConfig that OmegaConf composed against TrainConfig (each value checked
    against the schema's type at composition, no unknown key), resolved for this machine and validated
    before this call; writing to it now raises. The type checker reads it as PlacedConfig (TrainConfig
    with resolve_runtime's values filled in), so a key that the schema lacks, read anywhere downstream,
    is an error before anything runs. Call it once, after resolve_runtime and validate."""
    OmegaConf.set_readonly(cfg, True)
    return cast("PlacedConfig", cfg)


__all__ = ["CPU_DEFAULT_MAX_ITERATIONS", "CPU_DEFAULT_NUM_ENVS", "CPU_WHOLE_CLIP_ROLLOUTS", "GPU_DEFAULT_NUM_ENVS",
           "GPU_WHOLE_CLIP_ROLLOUTS", "placed", "resolve_runtime"]
