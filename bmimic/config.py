"""The top-level config schema, its registration in Hydra's ConfigStore, and runtime resolution.

Each config group is a YAML file in conf/<group>/ backed by a dataclass schema registered here as
`<group>/<group>_schema` (the sampler group's: one per sampler kind, `sampler/<kind>_schema`, registered
with the sampler class, bmimic.sampling.registry); the YAML lists it first in its defaults, so a typo or a wrong type fails at
composition with Hydra's own message. Meaning (ranges, divisibility, motion length) is checked once
after composition by `bmimic.config_checks.validate`, which raises `ConfigError` with one line
naming the key.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, List, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from bmimic import BmimicError
from bmimic.envs.config import EnvConfig
from bmimic.motion.config import DataConfig, MotionConfig
from bmimic.robot.config import RobotConfig
from bmimic.sampling.config import as_dict
from bmimic.sim.config import SimConfig
from bmimic.training.config import EvalConfig, PPOConfig

GPU_DEFAULT_NUM_ENVS = 4096
CPU_DEFAULT_NUM_ENVS = 8
CPU_DEFAULT_MAX_ITERATIONS = 4
GPU_WHOLE_CLIP_ROLLOUTS = 128
CPU_WHOLE_CLIP_ROLLOUTS = 2


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
    max_cpu_hours: Optional[float] = 1.0
    """On a CPU, refuse to start a run or sweep whose estimated training time (bmimic.budget: env steps
    at a measured CPU rate, sweep jobs summed) is over this many hours; null: no limit. GPUs are not
    limited."""
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
    progress_bar, ...: bmimic.training.resume.RESUME_FREE_KEYS) never need naming."""
    trust_checkpoint: bool = False
    """Also read a resume checkpoint of bmimic format 1 (pickled numpy RNG state), still with
    torch.load(weights_only=True): numpy's array reconstruction is admitted, any other global refused."""
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
    """Folder name of a sweep arm: Hydra's override_dirname, or `base` when only the seed varies. A '/'
    in a value makes sub-folders, but a `.` or `..` part of one (`motion.path=../x.npz`) is spelled
    `%2E` / `%2E%2E`, so that a job's folder always lies in its arm's folder under its sweep."""
    if not override_dirname:
        return "base"
    return "/".join(part.replace(".", "%2E") if part in (".", "..") else part for part in override_dirname.split("/"))


def _train_help(*, _root_) -> str:
    """`--help`'s text (conf/train.yaml: hydra.help.template); `$` escaped for Hydra's string.Template."""
    from bmimic.cli_help import train_help

    return train_help(_root_, TrainConfig).replace("$", "$$")


if not OmegaConf.has_resolver("bmimic.arm_dir"):
    OmegaConf.register_new_resolver("bmimic.arm_dir", _arm_dir)
if not OmegaConf.has_resolver("bmimic.help"):
    OmegaConf.register_new_resolver("bmimic.help", _train_help)
register_configs()


# --------------------------------------------------------------------------------------------- runtime
_UNSET = object()


def hydra_overrides(argv: list[str]) -> list[str]:
    """The overrides of a Hydra command line (its flags and their values left out)."""
    args = _hydra_args(argv)
    return list(args.overrides) if args is not None else []


def _hydra_args(argv: list[str]):
    """Hydra's parse of a command line, or None when argparse refuses it: quietly, since Hydra prints
    that refusal when it parses the same line (printed here too, it was said twice)."""
    import contextlib
    import io

    from hydra._internal.utils import get_args_parser

    try:
        with contextlib.redirect_stderr(io.StringIO()):
            return get_args_parser().parse_args(argv)
    except SystemExit:
        return None


def check_hydra_flags(argv: list[str]) -> None:
    """Refuse, in one line, the flag combinations Hydra itself refuses with a traceback (its checks run
    outside its own error reporting): --resolve without --cfg or --help, and more than one of --run,
    -m, --cfg, --info and --shell-completion. Argparse's own errors are left to Hydra's parser."""
    args = _hydra_args(argv)
    if args is None:  # argparse's usage line follows when Hydra parses the same command line
        return
    if args.resolve and args.cfg is None and not args.help:
        raise ConfigError("--resolve: only with --cfg or --help")
    if args.run + (args.cfg is not None) + args.multirun + args.shell_completion + (args.info is not None) > 1:
        raise ConfigError("only one of --run, --multirun (-m), --cfg, --info and --shell-completion at a time")


def check_additions(overrides: list[str]) -> None:
    """Refuse, in one line, a `+a.b.c=v` whose parent (`a.b`) is null in the composed config: OmegaConf
    cannot add under None and fails with a bare AssertionError inside Hydra's composition (a traceback
    on the command line). Composes the config only when such a dotted addition is present."""
    adds = [o for o in overrides if o.startswith("+") and "=" in o and "." in o.split("=", 1)[0]]
    if not adds:
        return
    from hydra import compose, initialize_config_dir

    from bmimic import CONF_DIR

    register_configs()
    others = [o for o in overrides if o not in adds and not o.startswith("hydra")]
    # When the other overrides do not compose (a wrong type elsewhere), Hydra would still meet the bare
    # AssertionError first: the check then reads the chosen groups' defaults, except where an override sets a parent.
    groups, set_keys = [o for o in others if "." not in o.split("=", 1)[0]], {o.split("=", 1)[0] for o in others}
    cfg = None
    for attempt in (others, groups):
        try:
            with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
                cfg = compose("train", overrides=attempt)
            break
        except Exception:  # noqa: BLE001 - anything else: Hydra reports it in its own words when it composes
            continue
    if cfg is None:
        return
    fallback = attempt is groups and groups != others
    for override in adds:
        parts = override.lstrip("+").split("=", 1)[0].split(".")
        for i in range(1, len(parts)):
            parent = ".".join(parts[:i])
            try:
                value = OmegaConf.select(cfg, parent, default=_UNSET)
            except OmegaConfBaseException:  # an interpolation that does not resolve (`${oc.env:UNSET}`): its
                break  # own error, in Hydra's or validate's words, not a traceback here
            if value is None and not (fallback and parent in set_keys):
                raise ConfigError(f"{override}: {parent} is null in the config, so nothing can be added under it; "
                                  f"set {parent} itself (e.g. {parent}=[...] or {parent}={{...}})")


def resolve_runtime(cfg, device: str) -> None:
    """Fill the `auto`/null top-level values in place for this machine; called once before
    bmimic.config_checks.validate."""
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


def with_schema_defaults(config: dict) -> dict:
    """A plain (resolved) config with the schema's defaults for the keys it lacks, e.g. one saved by
    an earlier bmimic before an option existed; unchanged when it does not fit the schema."""
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



READER_ENV_KEYS = ("data.lafan_dir",)
"""Keys whose ${oc.env:...} is meant to be the reader's (the LAFAN1 folder on this machine): the run
record keeps them as written."""


def interpolated_keys(tree: Any, prefix: str = "") -> list[str]:
    """Dotted keys of the leaves (a list counts as one) of a plain container written with `${...}`
    (OmegaConf.to_container(cfg, resolve=False)), READER_ENV_KEYS aside."""
    if isinstance(tree, dict):
        return [k for key, value in tree.items() for k in interpolated_keys(value, f"{prefix}{key}.")]
    key = prefix[:-1]
    return [key] if key and "${" in str(tree) and key not in READER_ENV_KEYS else []


def recorded_config(composed: dict, resolved: dict) -> dict:
    """The config a run records (.hydra/config.yaml): `composed` (as composed, `auto`/null values kept)
    with each interpolation (`seed=${oc.env:SLURM_ARRAY_TASK_ID}`, `seed=${num_envs}`) replaced by the
    value it had when the run trained (`resolved`: the runtime-resolved config), READER_ENV_KEYS aside.
    The tools that read the run (eval, the report) then see its values, not the reader's environment."""
    import copy

    out = copy.deepcopy(composed)
    for key in interpolated_keys(composed):
        *parents, leaf = key.split(".")
        source, target = resolved, out
        for part in parents:
            source, target = (source or {}).get(part) if isinstance(source, dict) else None, target[part]
        if isinstance(source, dict) and leaf in source:
            target[leaf] = copy.deepcopy(source[leaf])
    return out
