"""The checks a composed config gets: before anything runs (`check_composed`: unknown keys, NaN,
the sampler group, resume_allow_changes) and once resolved for this machine and its motion
(`validate`: ranges, divisibility, term functions, the sampler against the motion's length). Each
failure raises `ConfigError` with one line naming the key.
"""

from __future__ import annotations

import functools
import math
from typing import Any, cast

from bmimic.cli.extras import require_extra
from bmimic.config import ConfigError, TrainConfig
from bmimic.config.budget import optional_key
from bmimic.envs.config import EnvConfigError, check_env
from bmimic.runs.folder import check_folder_name
from bmimic.sampling.config import sampler_config
from bmimic.training.checkpoints import MAX_ITERATION

MAX_SEED = 2**31 - 1
"""Largest seed: every random stream (python, numpy, torch, warp) takes it, and so does seed + rank."""


def _fail(key: str, problem: str) -> None:
    raise ConfigError(f"{key}: {problem}")


def check_composed(cfg, choices=None, motion_files: bool = False) -> None:
    """The checks a composed config gets before anything runs (train and the sweep dry run): unknown
    keys (also `+` ones), NaN or infinity anywhere, the sampler group against sampler.name,
    resume_allow_changes names, the extra that logger=wandb needs; with `motion_files` (a launch that
    trains now, not a dry run on a machine without the data) a motion library's entries and the files of
    its folder or pattern (bmimic.motion.library.library_entries). `choices`: Hydra's runtime.choices
    (group -> option)."""
    check_present(cfg)
    check_resolvable(cfg)
    check_known_keys(cfg)
    check_finite(cfg)
    check_sampler_choice(cfg, choices)
    check_resume_allow_changes(cfg)
    if cfg.get("logger") == "wandb":
        require_extra("wandb", "logger=wandb")
    if motion_files and cfg.motion.get("source") == "library":  # its file names now, not after the set-up
        from bmimic.motion.library import library_entries

        library_entries(cfg.motion)


def check_resolvable(cfg, prefix: str = "") -> None:
    """Every value resolves (interpolations such as `${oc.env:UNSET}` included) and fits its type
    (`max_iterations=${oc.env:HOME}` is a path, not an integer)."""
    from omegaconf import DictConfig, ListConfig
    from omegaconf.errors import OmegaConfBaseException

    keys: list[Any] | range = [k for k in cfg if not (k == "hydra" and not prefix)] if isinstance(cfg, DictConfig) else \
        range(len(cfg)) if isinstance(cfg, ListConfig) else []
    for key in keys:
        name = f"{prefix}{key}" if isinstance(key, str) else f"{prefix[:-1]}[{key}]"
        try:
            value = cfg[key]
        except OmegaConfBaseException as e:
            _fail(name, f"cannot be resolved: {_omegaconf_message(e)}")
        if isinstance(value, (DictConfig, ListConfig)):
            check_resolvable(value, f"{name}.")


def _omegaconf_message(e: BaseException) -> str:
    msg = getattr(e, "msg", None) or str(e)
    return msg.strip().splitlines()[0] if msg.strip() else type(e).__name__


def check_present(cfg) -> None:
    """Every key of the schema is there: `~seed` or `~sampler` deletes a key no run can do without."""
    from dataclasses import fields

    from omegaconf import OmegaConf

    for f in fields(TrainConfig):
        if f.name != "defaults" and (f.name not in cfg or OmegaConf.is_missing(cfg, f.name)):
            _fail(f.name, f"is missing from the config (deleted with ~{f.name}?); every run needs it")


def check_known_keys(cfg) -> None:
    """Refuse keys the schema does not have, including ones added with `+`/`++` (Hydra's force-add
    skips the struct check): `+sampler.gama=0.5` must not train a run that looks like an ablation arm.
    Free-form dicts of the schema (env term tables, term params) still take new entries."""
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    plain = cast(dict, OmegaConf.to_container(cfg, resolve=False)) if isinstance(cfg, DictConfig) else dict(cfg)
    plain.pop("hydra", None)
    if isinstance(plain.get("sampler"), dict):
        sampler_config(plain["sampler"])  # the sampler's keys are its variant's schema's
    try:
        OmegaConf.merge(_train_schema(), plain)  # (merge copies its first argument: the cached schema stays)
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", None) or ""
        msg = getattr(e, "msg", None) or str(e).strip().splitlines()[0]
        if "not in" in msg or "Key '" in msg:
            _fail(key or "config", f"unknown key ({msg.splitlines()[0]}); check the spelling, "
                                   "`--cfg job` prints every key")
        _fail(key or "config", msg.splitlines()[0])


@functools.lru_cache(maxsize=1)
def _train_schema():
    """The TrainConfig schema as a config node, built once per process (~0.15 s each time)."""
    from omegaconf import OmegaConf

    return OmegaConf.structured(TrainConfig)


def check_finite(cfg, prefix: str = "") -> None:
    """Refuse NaN and infinity anywhere in the config (every float key, lists and term params too)."""
    from omegaconf import DictConfig, ListConfig, OmegaConf

    if isinstance(cfg, DictConfig) and "hydra" in cfg:
        cfg = OmegaConf.masked_copy(cfg, [str(k) for k in cfg if k != "hydra"])
    tree = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, (DictConfig, ListConfig)) else cfg
    items: Any = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, list) else ()
    for key, value in items:
        name = f"{prefix}{key}" if isinstance(key, str) else f"{prefix[:-1]}[{key}]"
        if isinstance(value, float) and not math.isfinite(value):
            _fail(name, f"must be a finite number, got {value}")
        if isinstance(value, (dict, list)):
            check_finite(value, f"{name}.")


def check_sampler_choice(cfg, choices) -> None:
    """`sampler.name` must be the sampler group's option (each conf/sampler/<name>.yaml is named
    <name>: its schema's default or its own `name:`), so `sampler=uniform sampler.name=adaptive` cannot train another sampler than the
    run's folder and records say."""
    chosen = choices.get("sampler") if choices is not None else None
    if chosen is not None and str(cfg.sampler.name) != str(chosen):
        _fail("sampler.name", f"is {cfg.sampler.name!r} but the sampler group chose {chosen!r}; choose the "
                              f"sampler with sampler=<name>, not by overriding sampler.name")


def check_resume_allow_changes(cfg) -> None:
    """Every name in resume_allow_changes must be a config key or key prefix (a typo allows nothing)."""
    from omegaconf import OmegaConf

    from bmimic.training.resume import flatten_config

    keys = flatten_config({k: v for k, v in cast(dict, OmegaConf.to_container(cfg, resolve=False)).items() if k != "hydra"})
    for name in cfg.resume_allow_changes or []:
        if not any(k == name or k.startswith(f"{name}.") for k in keys):
            _fail("resume_allow_changes", f"{name!r} is not a config key")


def check_seed(cfg) -> None:
    """The seed is an integer every random stream takes (the one check a sweep's seeds need apart)."""
    if isinstance(cfg.seed, bool) or not 0 <= cfg.seed <= MAX_SEED:
        _fail("seed", f"must be an integer in [0, {MAX_SEED}], got {cfg.seed}")


def validate(cfg, motion_duration_s: float | None = None, composed_checked: bool = False) -> None:
    """Check the meaning of a composed, runtime-resolved config; raise ConfigError naming the key.
    `composed_checked`: check_composed already passed on this config before its runtime values were
    filled in, so its keys and values need no second look (the sweep dry run checks many jobs)."""
    from bmimic.sampling.config import validate_sampler_config

    if not composed_checked:
        check_present(cfg)
        check_resolvable(cfg)
        check_known_keys(cfg)
        check_finite(cfg)
    check_seed(cfg)
    if cfg.num_envs is None or cfg.num_envs < 1:
        _fail("num_envs", f"must be >= 1, got {cfg.num_envs}")
    if cfg.max_iterations is None or not 0 <= cfg.max_iterations <= MAX_ITERATION:
        _fail("max_iterations", f"must be in [0, {MAX_ITERATION}], got {cfg.max_iterations}")
    stop_at = optional_key(cfg, "stop_at_iteration")
    if stop_at is not None and not 1 <= stop_at <= MAX_ITERATION:
        _fail("stop_at_iteration", f"must be in [1, {MAX_ITERATION}] or null, got {stop_at}")
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
        if not dims or any(d < 1 for d in dims):
            _fail(f"ppo.{key}", f"needs at least one layer, each of size >= 1, got {dims}")
    if ppo.activation not in _ACTIVATIONS:
        _fail("ppo.activation", f"must be one of {', '.join(_ACTIVATIONS)}, got {ppo.activation!r}")
    if ppo.noise_std_type not in ("scalar", "log"):
        _fail("ppo.noise_std_type", f"must be scalar or log, got {ppo.noise_std_type!r}")
    for key in ("run_name", "sweep_name"):
        problem = check_folder_name(key, cfg[key])
        if problem:
            raise ConfigError(problem)
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
    if cfg.env.episode_length_s / step_dt > MAX_ITERATION:
        _fail("env.episode_length_s", f"{cfg.env.episode_length_s:g} s is more than {MAX_ITERATION:.0e} control steps "
              f"of sim.timestep_s x sim.decimation = {step_dt:g} s")
    if cfg.eval.every_iters < 0:
        _fail("eval.every_iters", f"must be >= 0, got {cfg.eval.every_iters}")
    if cfg.eval.every_iters == 0 and _learns_from_evaluations(getattr(cfg.sampler, "kind", None)):
        _fail("eval.every_iters", f"is 0, but sampler={cfg.sampler.name} learns from the periodic evaluation "
              "(set eval.every_iters >= 1)")
    if cfg.eval.horizon_s <= 0:
        _fail("eval.horizon_s", f"must be > 0, got {cfg.eval.horizon_s}")
    if cfg.eval.episodes_per_bin is not None and cfg.eval.episodes_per_bin < 1:
        _fail("eval.episodes_per_bin", f"must be >= 1, got {cfg.eval.episodes_per_bin}")
    if cfg.eval.max_mpkpe_rel_mm is not None and not cfg.eval.max_mpkpe_rel_mm > 0:
        _fail("eval.max_mpkpe_rel_mm", f"must be > 0 or null, got {cfg.eval.max_mpkpe_rel_mm}")
    if cfg.eval.max_envs < 1:
        _fail("eval.max_envs", f"must be >= 1, got {cfg.eval.max_envs}")
    check_whole_clip(cfg.eval, step_dt)
    if cfg.time_limit_s is not None and cfg.time_limit_s <= 0:
        _fail("time_limit_s", f"must be > 0 or null, got {cfg.time_limit_s}")
    if cfg.logger not in ("tensorboard", "wandb", "none"):
        _fail("logger", f"must be tensorboard, wandb or none, got {cfg.logger!r}")
    try:
        check_env(cfg.env)
    except EnvConfigError as e:
        raise ConfigError(str(e)) from None
    if motion_duration_s is not None:
        check_motion_fit(cfg, motion_duration_s)
    else:
        validate_sampler_config(cfg.sampler)  # without a motion: all but the bins' fit


def check_motion_fit(cfg, motion_duration_s: float) -> None:
    """What `validate` leaves until the motion is read: the motion has a duration and the sampler's bins
    fit it (bmimic.task.build_task, on a config that `validate` passed)."""
    from bmimic.sampling.config import validate_sampler_config

    if not math.isfinite(motion_duration_s) or motion_duration_s <= 0:
        _fail("motion", f"has no duration ({motion_duration_s} s)")
    validate_sampler_config(cfg.sampler, motion_duration_s)


def check_whole_clip(eval_cfg: Any, step_dt: float) -> None:
    """The eval.whole_clip keys (bmimic.training.config.WholeClipConfig), one line naming the first bad one."""
    from bmimic.runs.schema import WHOLE_CLIP_CONDITIONS

    w = eval_cfg.whole_clip
    if w.rollouts is not None and w.rollouts < 1:
        _fail("eval.whole_clip.rollouts", f"must be >= 1, got {w.rollouts}")
    conditions = list(w.conditions or [])
    unknown = [c for c in conditions if c not in WHOLE_CLIP_CONDITIONS]
    if unknown or not conditions or len(set(conditions)) != len(conditions):
        what = f"unknown condition {unknown[0]!r}" if unknown else "must name each condition once" if conditions else (
            "names no condition")
        _fail("eval.whole_clip.conditions", f"{what} (known: {', '.join(WHOLE_CLIP_CONDITIONS)}), got {conditions}")
    if w.every_iters < 0:
        _fail("eval.whole_clip.every_iters", f"must be >= 0, got {w.every_iters}")
    if w.every_iters and (not eval_cfg.every_iters or w.every_iters % eval_cfg.every_iters):
        _fail("eval.whole_clip.every_iters", f"must be a multiple of eval.every_iters={eval_cfg.every_iters} (it runs "
              f"right after that window evaluation), got {w.every_iters}")
    for key in ("max_share", "after_success"):
        value = getattr(w, key)
        if value is not None and not 0 < value <= 1:
            _fail(f"eval.whole_clip.{key}", f"must be in (0, 1] or null, got {value}")
    if not 0 < w.max_clip_s <= MAX_ITERATION * step_dt:
        _fail("eval.whole_clip.max_clip_s", f"must be > 0 s and at most {MAX_ITERATION:.0e} control steps, got "
              f"{w.max_clip_s}")


def advisories(cfg: Any) -> list[str]:
    """Lines worth a warning in a config that validates: settings that are legal but make a run
    measure less than its user likely meant (call after the runtime defaults are resolved)."""
    notes = []
    every, budget = cfg.eval.every_iters, cfg.max_iterations
    if _learns_from_evaluations(getattr(cfg.sampler, "kind", None)) and budget is not None and every >= budget > 0:
        notes.append(f"sampler={cfg.sampler.name} learns only from the periodic evaluation, which runs every "
                     f"eval.every_iters={every} iterations: with max_iterations={budget} it starts every "
                     "episode uniformly for the whole run")
    return notes


def _learns_from_evaluations(kind: Any) -> bool:
    """Whether the registered sampler `kind` declares a signal delivered after each periodic evaluation
    (phc, protomotions: clip outcomes)."""
    from bmimic.sampling.config import sampler_class
    from bmimic.sampling.registry import SAMPLERS
    from bmimic.sampling.signals import learns_from_evaluations

    return kind in SAMPLERS and learns_from_evaluations(sampler_class(kind))


_ACTIVATIONS = ("elu", "selu", "relu", "crelu", "lrelu", "tanh", "sigmoid", "softplus", "gelu", "swish", "mish",
                "identity")
"""rsl-rl-lib 5.5's activation names (rsl_rl.utils.resolve_nn_activation)."""


def check_evaluates(cfg, cpu_default: bool) -> None:
    """A race (training with a stopping rule after each periodic evaluation) needs one within its budget,
    else it would train and have nothing to time: on a CPU the smoke-scale max_iterations=4 is below the
    race's every-100 evaluations (`cpu_default`: that budget came from the CPU default). ConfigError."""
    every, budget = int(cfg.eval.every_iters), int(cfg.max_iterations)
    if not 0 < every <= budget:
        where = " (the smoke-scale default on a CPU)" if cpu_default else ""
        raise ConfigError(f"a race times evaluations, and with max_iterations={budget}{where} and eval.every_iters="
                          f"{every} none would run; set max_iterations >= eval.every_iters >= 1 (on a CPU with "
                          "max_cpu_hours=<h>), or train with bmimic-train instead")
