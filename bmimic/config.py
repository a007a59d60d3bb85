"""The top-level config schema, its registration in Hydra's ConfigStore, and the one validation step.

Each config group is a YAML file in conf/<group>/ backed by a dataclass schema registered here as
`<group>/<group>_schema` (the sampler group's: one per sampler kind, `sampler/<kind>_schema`, registered
with the sampler class, bmimic.sampling.registry); the YAML lists it first in its defaults, so a typo or a wrong type fails at
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
from bmimic.envs.config import EnvConfig, EnvConfigError, check_env, foreign_term_modules  # noqa: F401
from bmimic.motion.config import DataConfig, MotionConfig
from bmimic.robot.config import RobotConfig
from bmimic.sampling.config import as_dict, sampler_config
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
    time_limit_s: Optional[float] = None
    """Stop after the iteration during which this much training wall time has passed (then the
    final evaluation and checkpoint run as usual); null: no limit. For fixed-time budgets and queues."""
    resume: Optional[str] = None
    """`true`: continue the latest run of this run_name (a sweep job: its own folder); or a run folder
    or checkpoint path. Continuing a run checks its config first and refuses any change not named in
    resume_allow_changes; a refused resume writes nothing."""
    resume_allow_changes: List[str] = field(default_factory=list)
    """Config keys (or key prefixes, e.g. `env.rewards`) a resume may change; the changes are recorded
    in the run's resumes.json. Budget and logistics keys (max_iterations, time_limit_s, device, logger,
    progress_bar, ...: bmimic.runs.RESUME_FREE_KEYS) never need naming."""
    trust_checkpoint: bool = False
    """Load a resume checkpoint with full unpickling when torch.load(weights_only=True) refuses it:
    only for checkpoints you wrote yourself (bmimic checkpoint format 1). A shared checkpoint can run
    code this way."""
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


def check_composed(cfg, choices=None) -> None:
    """The checks a composed config gets before anything runs (train and the sweep dry run): unknown
    keys (also `+` ones), NaN or infinity anywhere, the sampler group against sampler.name,
    resume_allow_changes names. `choices`: Hydra's runtime.choices (group -> option)."""
    check_known_keys(cfg)
    check_finite(cfg)
    check_sampler_choice(cfg, choices)
    check_resume_allow_changes(cfg)


def with_schema_defaults(config: dict) -> dict:
    """A plain (resolved) config with the schema's defaults for the keys it lacks, e.g. one saved by
    an earlier bmimic before an option existed; unchanged when it does not fit the schema."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        filled = OmegaConf.to_container(OmegaConf.merge(OmegaConf.structured(TrainConfig), config), resolve=True)
    except (OmegaConfBaseException, ValueError, TypeError):
        return config
    if "defaults" not in config:  # Hydra's defaults list is not part of a composed config
        filled.pop("defaults", None)
    if isinstance(filled.get("sampler"), dict):  # its variant's schema (an earlier bmimic's layout too)
        try:
            filled["sampler"] = as_dict(filled["sampler"])
        except BmimicError:
            pass
    return filled


def check_known_keys(cfg) -> None:
    """Refuse keys the schema does not have, including ones added with `+`/`++` (Hydra's force-add
    skips the struct check): `+sampler.gama=0.5` must not train a run that looks like an ablation arm.
    Free-form dicts of the schema (env term tables, term params) still take new entries."""
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    plain = OmegaConf.to_container(cfg, resolve=False) if isinstance(cfg, DictConfig) else dict(cfg)
    plain.pop("hydra", None)
    if isinstance(plain.get("sampler"), dict):
        sampler_config(plain["sampler"])  # the sampler's keys are its variant's schema's
    try:
        OmegaConf.merge(OmegaConf.structured(TrainConfig), plain)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", None) or ""
        msg = getattr(e, "msg", None) or str(e).strip().splitlines()[0]
        if "not in" in msg or "Key '" in msg:
            _fail(key or "config", f"unknown key ({msg.splitlines()[0]}); check the spelling, "
                                   "`--cfg job` prints every key")
        _fail(key or "config", msg.splitlines()[0])


def check_finite(cfg, prefix: str = "") -> None:
    """Refuse NaN and infinity anywhere in the config (every float key, lists and term params too)."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if isinstance(cfg, DictConfig) and "hydra" in cfg:
        cfg = OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"])
    tree = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, (DictConfig, ListConfig)) else cfg
    items = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, list) else ()
    for key, value in items:
        name = f"{prefix}{key}" if isinstance(key, str) else f"{prefix[:-1]}[{key}]"
        if isinstance(value, float) and not math.isfinite(value):
            _fail(name, f"must be a finite number, got {value}")
        if isinstance(value, (dict, list)):
            check_finite(value, f"{name}.")


def check_sampler_choice(cfg, choices) -> None:
    """`sampler.name` must be the sampler group's option (each conf/sampler/<name>.yaml sets
    name: <name>), so `sampler=uniform sampler.name=adaptive` cannot train another sampler than the
    run's folder and records say."""
    chosen = choices.get("sampler") if choices is not None else None
    if chosen is not None and str(cfg.sampler.name) != str(chosen):
        _fail("sampler.name", f"is {cfg.sampler.name!r} but the sampler group chose {chosen!r}; choose the "
                              f"sampler with sampler=<name>, not by overriding sampler.name")


def check_resume_allow_changes(cfg) -> None:
    """Every name in resume_allow_changes must be a config key or key prefix (a typo allows nothing)."""
    from omegaconf import OmegaConf

    from bmimic.runs import flatten_config

    keys = flatten_config({k: v for k, v in OmegaConf.to_container(cfg, resolve=False).items() if k != "hydra"})
    for name in cfg.resume_allow_changes or []:
        if not any(k == name or k.startswith(f"{name}.") for k in keys):
            _fail("resume_allow_changes", f"{name!r} is not a config key")


def check_num_envs_fit(cfg, mjm, device: str, num_worlds: int, rollout_steps: int) -> None:
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
        _fail("num_envs", f"{num_worlds} worlds need about {_gib(need)} ({per_world / 1024:.0f} KiB per world: "
                          f"physics {physics / 1024:.0f} KiB, rollout {rollout / 1024:.0f} KiB, temporaries), but "
                          f"{device} has {_gib(free)} free; about {max(int(free // per_world), 0)} fit")


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
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        import os

        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


def validate(cfg, motion_duration_s: float | None = None) -> None:
    """Check the meaning of a composed, runtime-resolved config; raise ConfigError naming the key."""
    from bmimic.sampling.config import validate_sampler_config

    check_known_keys(cfg)
    check_finite(cfg)
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
    if ppo.num_learning_epochs < 1:
        _fail("ppo.num_learning_epochs", f"must be >= 1, got {ppo.num_learning_epochs}")
    for key in ("clip_param", "max_grad_norm", "init_noise_std", "desired_kl"):
        if getattr(ppo, key) <= 0:
            _fail(f"ppo.{key}", f"must be > 0, got {getattr(ppo, key)}")
    for key in ("entropy_coef", "value_loss_coef"):
        if getattr(ppo, key) < 0:
            _fail(f"ppo.{key}", f"must be >= 0, got {getattr(ppo, key)}")
    for key in ("actor_hidden_dims", "critic_hidden_dims"):
        dims = list(getattr(ppo, key))
        if any(d < 1 for d in dims):
            _fail(f"ppo.{key}", f"layer sizes must be >= 1, got {dims}")
    if ppo.activation not in _ACTIVATIONS:
        _fail("ppo.activation", f"must be one of {', '.join(_ACTIVATIONS)}, got {ppo.activation!r}")
    if ppo.noise_std_type not in ("scalar", "log"):
        _fail("ppo.noise_std_type", f"must be scalar or log, got {ppo.noise_std_type!r}")
    for key in ("run_name", "sweep_name"):
        name = str(cfg[key])
        if not name or "/" in name or "\\" in name or name in (".", "..") or name != name.strip():
            _fail(key, f"must be a plain folder name (no '/', not empty, '.' or '..'), got {name!r}")
    if cfg.sim.timestep_s <= 0:
        _fail("sim.timestep_s", f"must be > 0, got {cfg.sim.timestep_s}")
    if cfg.sim.decimation < 1:
        _fail("sim.decimation", f"must be >= 1, got {cfg.sim.decimation}")
    for key in ("nconmax", "njmax", "iterations", "ls_iterations"):
        if getattr(cfg.sim, key) < 1:
            _fail(f"sim.{key}", f"must be >= 1, got {getattr(cfg.sim, key)}")
    for key in ("max_abs_qvel", "max_root_distance_m"):
        if getattr(cfg.sim, key) <= 0:
            _fail(f"sim.{key}", f"must be > 0, got {getattr(cfg.sim, key)}")
    if cfg.env.max_abs_step_reward <= 0:
        _fail("env.max_abs_step_reward", f"must be > 0, got {cfg.env.max_abs_step_reward}")
    if cfg.env.episode_length_s <= 0:
        _fail("env.episode_length_s", f"must be > 0, got {cfg.env.episode_length_s}")
    step_dt = cfg.sim.timestep_s * cfg.sim.decimation
    if cfg.env.episode_length_s < step_dt:
        _fail("env.episode_length_s", f"is shorter than one control step ({step_dt} s)")
    if cfg.eval.every_iters < 0:
        _fail("eval.every_iters", f"must be >= 0, got {cfg.eval.every_iters}")
    if cfg.eval.horizon_s <= 0:
        _fail("eval.horizon_s", f"must be > 0, got {cfg.eval.horizon_s}")
    if cfg.eval.episodes_per_bin is not None and cfg.eval.episodes_per_bin < 1:
        _fail("eval.episodes_per_bin", f"must be >= 1, got {cfg.eval.episodes_per_bin}")
    if cfg.eval.max_mpkpe_rel_mm is not None and not cfg.eval.max_mpkpe_rel_mm > 0:
        _fail("eval.max_mpkpe_rel_mm", f"must be > 0 or null, got {cfg.eval.max_mpkpe_rel_mm}")
    if cfg.eval.max_envs < 1:
        _fail("eval.max_envs", f"must be >= 1, got {cfg.eval.max_envs}")
    if cfg.time_limit_s is not None and cfg.time_limit_s <= 0:
        _fail("time_limit_s", f"must be > 0 or null, got {cfg.time_limit_s}")
    if cfg.logger not in ("tensorboard", "wandb", "none"):
        _fail("logger", f"must be tensorboard, wandb or none, got {cfg.logger!r}")
    try:
        check_env(cfg.env)
    except EnvConfigError as e:
        raise ConfigError(str(e)) from None
    if motion_duration_s is not None:
        if not math.isfinite(motion_duration_s) or motion_duration_s <= 0:
            _fail("motion", f"has no duration ({motion_duration_s} s)")
        validate_sampler_config(cfg.sampler, motion_duration_s)


_ACTIVATIONS = ("elu", "selu", "relu", "crelu", "lrelu", "tanh", "sigmoid", "softplus", "gelu", "swish", "mish",
                "identity")
"""rsl-rl-lib 5.5's activation names (rsl_rl.utils.resolve_nn_activation)."""
