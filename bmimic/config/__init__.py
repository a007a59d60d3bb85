"""The schemas' registration in Hydra's ConfigStore, the resolvers, and a command line's overrides.

The top-level schema is `schema.TrainConfig`; `placement` fills this machine's values in
(resolve_runtime) and, once the config is validated, makes it read-only and typed (placed).

Each config group is a YAML file in conf/<group>/ backed by a dataclass schema registered here as
`<group>/<group>_schema` (the sampler group's: one per sampler kind, `sampler/<kind>_schema`, registered
with the sampler class, bmimic.sampling.registry); the YAML lists it first in its defaults, so a typo or a wrong type fails at
composition with Hydra's own message. Meaning (ranges, divisibility, motion length) is checked once
after composition by `bmimic.config.checks.validate`, which raises `ConfigError` with one line
naming the key.
"""

from __future__ import annotations

import contextlib
import os
import re
from pathlib import Path
from typing import Any, Sequence, cast

from hydra.core.config_store import ConfigStore
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from bmimic import BmimicError
from bmimic.config.placement import placed as placed  # re-exported: callers import both from here
from bmimic.config.placement import resolve_runtime as resolve_runtime
from bmimic.config.schema import TrainConfig as TrainConfig
from bmimic.envs.config import EnvConfig
from bmimic.motion.config import MotionConfig
from bmimic.robot.config import RobotConfig
from bmimic.sampling.config import as_dict
from bmimic.sim.config import SimConfig
from bmimic.training.config import EvalConfig, PPOConfig


class ConfigError(BmimicError):
    """A composed config whose values make no sense together."""


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
    from bmimic.cli.help_text import train_help

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


def _dotted_additions(overrides: Sequence[str]) -> list[str]:
    return [o for o in overrides if o.startswith("+") and "=" in o and "." in o.split("=", 1)[0]]


def _refuse_additions_under_null(cfg, adds: Sequence[str], set_elsewhere: Sequence[str] = ()) -> None:
    """ConfigError for the first of `adds` whose parent is null in `cfg`; a parent in `set_elsewhere` (an
    override sets it, but `cfg` was composed without that override) is left to the full composition."""
    for override in adds:
        parts = override.lstrip("+").split("=", 1)[0].split(".")
        for i in range(1, len(parts)):
            parent = ".".join(parts[:i])
            try:
                value = OmegaConf.select(cfg, parent, default=_UNSET)
            except OmegaConfBaseException as e:  # an interpolation that does not resolve (`${oc.env:UNSET}`):
                # Hydra would add under the node it stands for, still null, and fail with a bare assertion
                if parent in set_elsewhere:
                    break
                raise ConfigError(f"{override}: {parent} is an interpolation that does not resolve "
                                  f"({str(e).splitlines()[0]}), so nothing can be added under it") from None
            if value is None and parent not in set_elsewhere:
                raise ConfigError(f"{override}: {parent} is null in the config, so nothing can be added under it; "
                                  f"set {parent} itself (e.g. {parent}=[...] or {parent}={{...}})")
            if value is not _UNSET and not isinstance(value, (DictConfig, ListConfig, dict, list)):
                # a scalar (another override's value, say) takes no keys; Hydra may meet the node still
                # null and fail with a bare assertion
                raise ConfigError(f"{override}: {parent} is {value!r}, not a mapping, so nothing can be added "
                                  "under it")


def check_additions(overrides: list[str]) -> None:
    """Refuse, in one line, a `+a.b.c=v` whose parent (`a.b`) is null in the composed config: OmegaConf
    cannot add under None and fails with a bare AssertionError inside Hydra's composition (a traceback
    on the command line). Composes the config only when such a dotted addition is present. When the
    other overrides do not compose either (a wrong type elsewhere), Hydra would still meet the bare
    AssertionError first: the check then reads the chosen groups' defaults, except where an override
    sets a parent."""
    from hydra.types import RunMode

    adds = _dotted_additions(overrides)
    if not adds:
        return
    others = [o for o in overrides if o not in adds and not o.startswith("hydra")]
    groups = [o for o in others if "." not in o.split("=", 1)[0]]
    for attempt in (others, groups):
        try:
            with config_loader() as loader:
                cfg = loader.load_configuration("train", attempt, run_mode=RunMode.RUN)
        except Exception:  # noqa: BLE001 - anything else: check_overrides (or Hydra) reports it in its own words
            continue
        fallback = attempt is groups and groups != others
        # only an override that makes the parent a mapping or a list can take the addition (one that sets
        # it to '' or a number leaves OmegaConf the same bare AssertionError)
        containers = [k for k, _, v in (o.partition("=") for o in others) if v.strip().startswith(("{", "["))]
        _refuse_additions_under_null(cfg, adds, containers if fallback else ())
        return


@contextlib.contextmanager
def config_loader(config_dir: str | os.PathLike | None = None, config_name: str = "train"):
    """Hydra's config loader for `config_dir` (default: bmimic's conf/), initialised as for `python -m
    bmimic.train`, outside a running Hydra app."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    import bmimic.sweeping.gpu_slots  # noqa: F401  (registers the bmimic.gpu_slots resolver of the launchers)
    from bmimic import CONF_DIR

    register_configs()
    with initialize_config_dir(config_dir=str(Path(config_dir or CONF_DIR).resolve()), version_base="1.3",
                               job_name=config_name):
        yield GlobalHydra.instance().config_loader()


OWN_CONFIG_FLAGS = ("--config-path", "-cp", "--config-name", "-cn", "--config-dir", "-cd")
"""Hydra flags that point a command at another config tree: its overrides are then Hydra's to check."""


def check_overrides(argv: Sequence[str], multirun: bool | None = None, loader=None):
    """Compose conf/train.yaml with the overrides of the Hydra command line `argv` as the command will
    (Hydra's config loader, the `hydra` node included) and return the config; every refusal of Hydra's
    grammar, its config groups or the schema's keys and types raises ConfigError with one line naming
    the override and the problem (override_error), where Hydra would print its 5-7 line block and exit 1.
    `multirun` (default: whether argv has -m) composes the sweep's master config, whose swept values
    each job checks (bmimic.sweeping.jobs). Returns None for a command line that names another config tree
    (OWN_CONFIG_FLAGS: only its overrides' grammar is checked; -cp/-cn naming bmimic's own are checked as without
    them) or has a malformed flag (Hydra reports it). `loader`: a
    config loader to compose with (default: a fresh one, config_loader)."""
    from hydra.types import RunMode

    args = _hydra_args(list(argv))
    if args is None:
        return None
    if any(a == flag or a.startswith(flag + "=") for a in argv for flag in OWN_CONFIG_FLAGS) and not _own_tree(args):
        _check_grammar(list(args.overrides))  # another tree composes as Hydra's to check; the grammar is Hydra's alike
        return None
    overrides = list(args.overrides)
    if args.config_dir is not None:  # bmimic's tree with a folder of the user's: searched as Hydra's -cd does
        overrides.append(f"hydra.searchpath=[file://{os.path.abspath(args.config_dir)}]")
    multirun = args.multirun if multirun is None else multirun
    adds = _dotted_additions(overrides)
    with contextlib.nullcontext(loader) if loader is not None else config_loader() as loader:
        mode = RunMode.MULTIRUN if multirun else RunMode.RUN
        if adds:  # composed without them first: an addition under a null node is OmegaConf's bare assertion
            try:
                base = loader.load_configuration("train", [o for o in overrides if o not in adds], run_mode=mode)
            except Exception as e:  # noqa: BLE001 - Hydra's, OmegaConf's or a value's error alike: one line
                raise ConfigError(override_error(e, overrides)) from None
            _refuse_additions_under_null(base, adds)
        try:
            cfg = loader.load_configuration("train", overrides, run_mode=mode)
        except Exception as e:  # noqa: BLE001 - Hydra's, OmegaConf's or a value's error alike: one line
            raise ConfigError(override_error(e, overrides)) from None
    _refuse_record_overrides(cfg)
    return cfg


def _own_tree(args) -> bool:
    """The -cp/-cn of Hydra's parse `args` name bmimic's own tree and primary config (`-cp` of bmimic's conf/,
    `-cn train`; a -cd folder is searched beside it): its overrides are checked as without them."""
    from bmimic import CONF_DIR

    if args.config_name not in (None, "train", "train.yaml"):
        return False
    if args.config_path is None:
        return True
    text = str(args.config_path).removeprefix("file://")
    if text.startswith("pkg://"):
        return False
    path = Path(text) if os.path.isabs(text) else Path(__file__).resolve().parents[1] / text  # as Hydra's -cp
    try:
        return path.resolve() == Path(CONF_DIR).resolve()
    except (OSError, RuntimeError):
        return False


def _check_grammar(overrides: list[str]) -> None:
    """ConfigError (one line) for an override Hydra's grammar cannot parse, whatever tree it composes in."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        OverridesParser.create().parse_overrides(overrides)
    except Exception as e:  # noqa: BLE001 - Hydra's OverrideParseException and relatives: one line
        raise ConfigError(override_error(e, overrides)) from None


def _refuse_record_overrides(cfg) -> None:
    """The two Hydra settings that keep a run's record its own are not overridable: Hydra's output subdir
    (Hydra would rewrite .hydra/ of the run a launch names before bmimic's checks run, even one they
    refuse) and the launch guard (which refuses a launch into a folder or run it does not own)."""
    hydra = cfg.get("hydra") or {}
    if hydra.get("output_subdir") is not None:
        raise ConfigError(f"hydra.output_subdir={hydra.get('output_subdir')}: bmimic writes a run's launch record "
                          "(.hydra/) itself, once, into a new run; Hydra's copy would rewrite an existing run's record "
                          "before any check: leave it out")
    if "launch_guard" not in (hydra.get("callbacks") or {}):
        raise ConfigError("hydra.callbacks.launch_guard: the launch guard cannot be removed (it keeps a launch "
                          "from writing into a run or a folder it does not own)")


def override_error(e: BaseException, overrides: Sequence[str] = ()) -> str:
    """One line naming the override (or key) and the problem, for an error Hydra or OmegaConf raised
    while composing `overrides`: an unknown key (never Hydra's `+key` suggestion, which bmimic refuses
    as an unknown key too), a value of the wrong type, an unknown group option, an override Hydra's
    grammar cannot parse (a non-ASCII value must be quoted)."""
    from hydra.errors import MissingConfigException, OverrideParseException
    from omegaconf.errors import ConfigAttributeError, ConfigKeyError, OmegaConfBaseException

    from bmimic.cli.help_text import SCHEMA_SUFFIX

    text = str(e).strip()
    lines = [line.strip() for line in text.splitlines() if line.strip()]
    if isinstance(e, OverrideParseException):
        override = str(getattr(e, "override", "") or "")
        if any(ord(c) > 127 for c in override):
            key, _, value = override.partition("=")
            return (f"{override}: Hydra's override grammar takes a value with non-ASCII characters only in quotes: "
                    f"\"{key}='{value}'\" (the outer quotes are the shell's)")
        problem = lines[0] if lines else type(e).__name__
        return f"{override or 'override'}: not a valid override: {problem} (https://hydra.cc/docs/advanced/override_grammar/basic/)"
    if isinstance(e, MissingConfigException) and getattr(e, "options", None) is not None:
        group, _, option = str(e.missing_cfg_file or "").rpartition("/")
        options = sorted(o for o in e.options or () if not o.endswith(SCHEMA_SUFFIX))
        return f"{group}={option}: no such option of the config group {group}; options: {', '.join(options)}"
    if isinstance(e, MissingConfigException):  # its further lines are Hydra's search path
        return lines[0] if lines else type(e).__name__
    ambiguous = re.match(r"Ambiguous value for argument '(([^=']+)=([^']*))'", text)
    if ambiguous:
        override, key, value = ambiguous.groups()
        return (f"{override}: several values: a list is {key}=[{value}], a string {key}='{value}', a sweep over them "
                "needs -m")
    cause = e.__cause__ if isinstance(e.__cause__, OmegaConfBaseException) else e
    if isinstance(cause, OmegaConfBaseException):
        key = getattr(cause, "full_key", None) or ""
        msg = (getattr(cause, "msg", None) or str(cause)).strip().splitlines()
        problem = msg[0] if msg else type(cause).__name__
        if isinstance(cause, (ConfigAttributeError, ConfigKeyError)) and "not in" in problem:
            return f"{key or 'config'}: unknown key ({problem}); check the spelling, `--cfg job` prints every key"
        given = next((o for o in overrides if o.split("=", 1)[0].lstrip("+~") == key), None)
        return f"{given or key or 'config'}: {problem}"
    return "; ".join(lines) if lines else type(e).__name__


def with_schema_defaults(config: dict) -> dict:
    """A plain (resolved) config with the schema's defaults for the keys it lacks, e.g. one saved by
    an earlier bmimic before an option existed; unchanged when it does not fit the schema."""
    try:
        filled = cast(dict, OmegaConf.to_container(OmegaConf.merge(OmegaConf.structured(TrainConfig), config),
                                                   resolve=True))
    except (OmegaConfBaseException, ValueError, TypeError):
        return config
    if "defaults" not in config:  # Hydra's defaults list is not part of a composed config
        filled.pop("defaults", None)
    if isinstance(filled.get("sampler"), dict):  # its variant's schema
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
        source: Any = resolved
        target = out
        for part in parents:
            source, target = (source or {}).get(part) if isinstance(source, dict) else None, target[part]
        if isinstance(source, dict) and leaf in source:
            target[leaf] = copy.deepcopy(source[leaf])
    return out
