"""The top-level config schema, its registration in Hydra's ConfigStore, and the one validation step.

Each config group is a YAML file in conf/<group>/ backed by a dataclass schema registered here as
`<group>/<group>_schema`; the YAML lists it first in its defaults, so a typo or a wrong type fails at
composition with Hydra's own message. Meaning (ranges, divisibility, motion length) is checked once
after composition by `validate`, which raises `ConfigError` with one line naming the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf

from bmimic import BmimicError
from bmimic.envs.config import EnvConfig
from bmimic.motion.config import DataConfig, MotionConfig
from bmimic.robot.config import RobotConfig
from bmimic.sampling.config import SamplerConfig
from bmimic.sim.config import SimConfig
from bmimic.training.config import EvalConfig, PPOConfig

GPU_DEFAULT_NUM_ENVS = 4096
CPU_DEFAULT_NUM_ENVS = 8
CPU_DEFAULT_MAX_ITERATIONS = 4


class ConfigError(BmimicError):
    """A composed config whose values make no sense together."""


@dataclass
class TrainConfig:
    """Primary config of `python -m bmimic.train` (conf/train.yaml)."""

    robot: RobotConfig = MISSING
    """The robot model and its actuators (group `robot`)."""
    motion: MotionConfig = MISSING
    """The reference motion (group `motion`)."""
    sampler: SamplerConfig = MISSING
    """How episode start frames are chosen (group `sampler`)."""
    ppo: PPOConfig = MISSING
    """PPO hyperparameters (group `ppo`)."""
    sim: SimConfig = MISSING
    """Physics options (group `sim`)."""
    env: EnvConfig = MISSING
    """The tracking MDP's terms (group `env`)."""
    eval: EvalConfig = MISSING
    """Sampler-independent evaluation during training (group `eval`)."""
    seed: int = 0
    """Derives every random stream: torch, numpy, python, warp and the motion sampler."""
    device: str = "auto"
    """`auto` (cuda when present, else cpu), `cpu`, `cuda` or `cuda:N`."""
    num_envs: Optional[int] = None
    """Parallel worlds; null: 4096 on a GPU, 8 on a CPU (smoke scale)."""
    max_iterations: Optional[int] = None
    """PPO iterations; null: ppo.max_iterations on a GPU, 4 on a CPU (smoke scale)."""
    run_name: str = "default"
    """Single runs go to outputs/runs/<run_name>/<timestamp>/."""
    sweep_name: str = "default"
    """Multirun jobs go to outputs/sweeps/<sweep_name>/<overrides>/seed=<seed>/."""
    time_limit_s: Optional[float] = None
    """Stop after the iteration during which this much training wall time has passed (then the
    final evaluation and checkpoint run as usual); null: no limit. For fixed-time budgets and queues."""
    resume: Optional[str] = None
    """`true`: continue the latest run with this run folder layout; or a checkpoint path."""
    logger: str = "tensorboard"
    """`tensorboard`, `wandb` (offline-capable via WANDB_MODE) or `none`."""
    wandb_project: str = "bmimic"
    """W&B project when logger=wandb."""
    progress_bar: bool = True
    """Show a tqdm progress bar with ETA (off in non-interactive logs if you prefer)."""
    verbose: bool = False
    """Also show Warp's start-up and kernel-module lines and rsl-rl's model printouts."""
    data: DataConfig = field(default_factory=DataConfig)
    """Where the user's motion datasets are (data.lafan_dir: the LAFAN1 G1 folder)."""
    defaults: List[Any] = field(default_factory=list)
    """Hydra defaults list (set in conf/train.yaml)."""


def register_configs() -> None:
    """Register every schema in Hydra's ConfigStore (idempotent)."""
    cs = ConfigStore.instance()
    cs.store(name="train_schema", node=TrainConfig)
    cs.store(group="robot", name="robot_schema", node=RobotConfig)
    cs.store(group="motion", name="motion_schema", node=MotionConfig)
    cs.store(group="sampler", name="sampler_schema", node=SamplerConfig)
    cs.store(group="ppo", name="ppo_schema", node=PPOConfig)
    cs.store(group="sim", name="sim_schema", node=SimConfig)
    cs.store(group="env", name="env_schema", node=EnvConfig)
    cs.store(group="eval", name="eval_schema", node=EvalConfig)


def _arm_dir(override_dirname: str) -> str:
    """Folder name of a sweep arm: Hydra's override_dirname, or `base` when only the seed varies."""
    return override_dirname if override_dirname else "base"


def _train_help(*, _root_) -> str:
    """`--help`'s text (conf/train.yaml: hydra.help.template); `$` escaped for Hydra's string.Template."""
    from bmimic.cli_help import train_help

    return train_help(_root_).replace("$", "$$")


if not OmegaConf.has_resolver("bmimic.arm_dir"):
    OmegaConf.register_new_resolver("bmimic.arm_dir", _arm_dir)
if not OmegaConf.has_resolver("bmimic.help"):
    OmegaConf.register_new_resolver("bmimic.help", _train_help)
register_configs()


# --------------------------------------------------------------------------------------------- runtime
def resolve_runtime(cfg, device: str) -> None:
    """Fill the `auto`/null top-level values in place for this machine; called once before validate."""
    on_gpu = device.startswith("cuda")
    cfg.device = device
    if cfg.num_envs is None:
        cfg.num_envs = GPU_DEFAULT_NUM_ENVS if on_gpu else CPU_DEFAULT_NUM_ENVS
    if cfg.max_iterations is None:
        cfg.max_iterations = cfg.ppo.max_iterations if on_gpu else CPU_DEFAULT_MAX_ITERATIONS
    if cfg.eval.episodes_per_bin is None:
        cfg.eval.episodes_per_bin = 32 if on_gpu else 1


def _fail(key: str, problem: str) -> None:
    raise ConfigError(f"{key}: {problem}")


def validate(cfg, motion_duration_s: float | None = None) -> None:
    """Check the meaning of a composed, runtime-resolved config; raise ConfigError naming the key."""
    from bmimic.sampling.config import validate_sampler_config

    if cfg.num_envs is None or cfg.num_envs < 1:
        _fail("num_envs", f"must be >= 1, got {cfg.num_envs}")
    if cfg.max_iterations is None or cfg.max_iterations < 0:
        _fail("max_iterations", f"must be >= 0, got {cfg.max_iterations}")
    ppo = cfg.ppo
    if ppo.num_steps_per_env < 1:
        _fail("ppo.num_steps_per_env", f"must be >= 1, got {ppo.num_steps_per_env}")
    if ppo.num_mini_batches < 1:
        _fail("ppo.num_mini_batches", f"must be >= 1, got {ppo.num_mini_batches}")
    batch = cfg.num_envs * ppo.num_steps_per_env
    if batch % ppo.num_mini_batches:
        _fail(
            "ppo.num_mini_batches",
            f"num_envs * ppo.num_steps_per_env = {cfg.num_envs} * {ppo.num_steps_per_env} = {batch} "
            f"is not divisible by ppo.num_mini_batches = {ppo.num_mini_batches}",
        )
    if not 0 < ppo.gamma <= 1:
        _fail("ppo.gamma", f"must be in (0, 1], got {ppo.gamma}")
    if not 0 <= ppo.lam <= 1:
        _fail("ppo.lam", f"must be in [0, 1], got {ppo.lam}")
    if ppo.learning_rate <= 0:
        _fail("ppo.learning_rate", f"must be > 0, got {ppo.learning_rate}")
    if ppo.schedule not in ("adaptive", "fixed"):
        _fail("ppo.schedule", f"must be adaptive or fixed, got {ppo.schedule!r}")
    if ppo.float32_matmul_precision not in ("highest", "high", "medium"):
        _fail("ppo.float32_matmul_precision", f"must be highest, high or medium, got {ppo.float32_matmul_precision!r}")
    if ppo.save_interval < 1:
        _fail("ppo.save_interval", f"must be >= 1, got {ppo.save_interval}")
    if cfg.sim.timestep_s <= 0:
        _fail("sim.timestep_s", f"must be > 0, got {cfg.sim.timestep_s}")
    if cfg.sim.decimation < 1:
        _fail("sim.decimation", f"must be >= 1, got {cfg.sim.decimation}")
    for key in ("nconmax", "njmax", "iterations", "ls_iterations"):
        if getattr(cfg.sim, key) < 1:
            _fail(f"sim.{key}", f"must be >= 1, got {getattr(cfg.sim, key)}")
    if cfg.env.episode_length_s <= 0:
        _fail("env.episode_length_s", f"must be > 0, got {cfg.env.episode_length_s}")
    step_dt = cfg.sim.timestep_s * cfg.sim.decimation
    if cfg.env.episode_length_s < step_dt:
        _fail("env.episode_length_s", f"is shorter than one control step ({step_dt} s)")
    lo, hi = cfg.env.randomization.friction_range
    if not 0 < lo <= hi:
        _fail("env.randomization.friction_range", f"must satisfy 0 < low <= high, got [{lo}, {hi}]")
    if cfg.eval.every_iters < 0:
        _fail("eval.every_iters", f"must be >= 0, got {cfg.eval.every_iters}")
    if cfg.eval.horizon_s <= 0:
        _fail("eval.horizon_s", f"must be > 0, got {cfg.eval.horizon_s}")
    if cfg.eval.episodes_per_bin is not None and cfg.eval.episodes_per_bin < 1:
        _fail("eval.episodes_per_bin", f"must be >= 1, got {cfg.eval.episodes_per_bin}")
    if cfg.eval.max_mpkpe_rel_mm is not None and not cfg.eval.max_mpkpe_rel_mm > 0:
        _fail("eval.max_mpkpe_rel_mm", f"must be > 0 or null, got {cfg.eval.max_mpkpe_rel_mm}")
    if cfg.time_limit_s is not None and cfg.time_limit_s <= 0:
        _fail("time_limit_s", f"must be > 0 or null, got {cfg.time_limit_s}")
    if cfg.logger not in ("tensorboard", "wandb", "none"):
        _fail("logger", f"must be tensorboard, wandb or none, got {cfg.logger!r}")
    _validate_terms(cfg.env)
    if motion_duration_s is not None:
        if not math.isfinite(motion_duration_s) or motion_duration_s <= 0:
            _fail("motion", f"has no duration ({motion_duration_s} s)")
        validate_sampler_config(cfg.sampler, motion_duration_s)


def _validate_terms(env_cfg) -> None:
    from bmimic.envs.mdp import resolve_term

    groups = {
        "env.policy_observations": ("observations", env_cfg.policy_observations),
        "env.critic_observations": ("observations", env_cfg.critic_observations),
        "env.rewards": ("rewards", env_cfg.rewards),
        "env.terminations": ("terminations", env_cfg.terminations),
    }
    for prefix, (kind, terms) in groups.items():
        for name, term in terms.items():
            try:
                resolve_term(kind, term.func)
            except LookupError as e:
                _fail(f"{prefix}.{name}.func", str(e))
    if not env_cfg.policy_observations:
        _fail("env.policy_observations", "is empty; the policy needs at least one observation term")
