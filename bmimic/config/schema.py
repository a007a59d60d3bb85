"""The top-level config schema of `python -m bmimic.train` (conf/train.yaml): every group's schema under
its key, and the top-level values."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, List, Optional

from omegaconf import MISSING

from bmimic.envs.config import EnvConfig
from bmimic.motion.config import DataConfig, MotionConfig
from bmimic.robot.config import RobotConfig
from bmimic.sim.config import SimConfig
from bmimic.training.config import EvalConfig, PPOConfig


@dataclass
class TrainConfig:
    """Primary config of `python -m bmimic.train` (conf/train.yaml)."""

    robot: RobotConfig = MISSING
    """The robot model and its actuators (group `robot`)."""
    motion: MotionConfig = MISSING
    """The reference motion (group `motion`)."""
    sampler: Any = MISSING
    """How episode start frames are chosen (group `sampler`; each variant's schema is its sampler's,
    bmimic.sampling.registry)."""
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
    max_cpu_hours: Optional[float] = 1.0
    """On a CPU, refuse to start a run or sweep whose estimated training time (bmimic.config.budget: env steps
    at a measured CPU rate, sweep jobs summed) is over this many hours; null: no limit. GPUs are not
    limited."""
    time_limit_s: Optional[float] = None
    """Stop after the iteration during which this much training wall time has passed (then the
    final evaluation and checkpoint run as usual); null: no limit. For fixed-time budgets and queues."""
    stop_at_iteration: Optional[int] = None
    """Pause after this iteration (counted from the run's start, as max_iterations is): the final evaluation
    and checkpoint run as usual and `resume=true` continues toward max_iterations; null: no pause. Unlike
    lowering max_iterations it leaves the run's budget, and every schedule that spans it (EGM's annealing),
    as configured: for long jobs trained sitting by sitting and arms brought to equal iterations."""
    resume: Optional[str] = None
    """`true`: continue the latest run of this run_name (a sweep job: its own folder); or a run folder
    or checkpoint path. Continuing a run checks its config first and refuses any change not named in
    resume_allow_changes; a refused resume writes nothing."""
    resume_allow_changes: List[str] = field(default_factory=list)
    """Config keys (or key prefixes, e.g. `env.rewards`) a resume may change; the changes are recorded
    in the run's resumes.json. Budget and logistics keys (max_iterations, time_limit_s, device, logger,
    progress_bar, ...: bmimic.training.resume.RESUME_FREE_KEYS) never need naming."""
    logger: str = "tensorboard"
    """`tensorboard`, `wandb` (offline-capable via WANDB_MODE) or `none`."""
    wandb_project: str = "bmimic"
    """W&B project when logger=wandb."""
    progress_bar: bool = True
    """On a terminal, a tqdm progress bar with ETA; elsewhere (SLURM logs, pipes), or when false, a
    console line every few iterations (at most about 50 per run)."""
    verbose: bool = False
    """Also show Warp's start-up and kernel-module lines and rsl-rl's model printouts."""
    data: DataConfig = field(default_factory=DataConfig)
    """Where the user's motion datasets are (data.lafan_dir: the LAFAN1 G1 folder)."""
    defaults: List[Any] = field(default_factory=list)
    """Hydra defaults list (set in conf/train.yaml)."""


__all__ = ["TrainConfig"]
