"""A saved run reopened: its folder and checkpoint located, its config resolved for this machine, its
task rebuilt (robot, motion, bins) as training built it. Used by eval, play and export.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Sequence

from bmimic import BmimicError
from bmimic.cli.common import first_line
from bmimic.runs import safe_read
from bmimic.runs.folder import (
    CHECKPOINTS_DIR,
    DATA_FOLDER_NAME,
    HYDRA_DIR,
    LATEST_CHECKPOINT,
    RESUMES,
    has_hydra_record,
    newest_checkpoint,
    read_json,
    read_resolved_config,
    swap_folder,
)
from bmimic.runs.folder import (
    checkpoint_label as run_checkpoint_label,
)

if TYPE_CHECKING:
    from bmimic.task import Task


class RunLoadError(BmimicError):
    """A run folder, checkpoint or override that cannot be used (one-line message)."""


def locate_run(path: str | Path) -> tuple[Path, Path]:
    """(run folder, checkpoint) for a run folder (its latest.pt) or a checkpoint file inside one. The
    checkpoint is a regular file (torch.load would block on a FIFO, read a device forever), and a run
    folder's own: one linked from outside it would be evaluated under this run's config."""
    p = Path(path).expanduser()
    if not p.exists():
        raise RunLoadError(f"{p}: no such run folder or checkpoint")
    if not p.is_dir():
        _checked_file(p, None)
    run_dir = p if p.is_dir() else p.resolve().parent.parent
    if not has_hydra_record(run_dir):
        where = "" if p.is_dir() else f" (the folder two levels above checkpoint {p.name})"
        raise RunLoadError(f"{run_dir}: not a run folder{where}: no {HYDRA_DIR}/config.yaml")
    if not p.is_dir():
        return run_dir.resolve(), p.resolve()
    checkpoint = newest_checkpoint(p)
    if checkpoint is None:
        raise RunLoadError(f"{p}: no checkpoint ({CHECKPOINTS_DIR}/{LATEST_CHECKPOINT} or model_<it>.pt) in this "
                           "run folder")
    return run_dir.resolve(), _checked_file(checkpoint, p).resolve()


def _checked_file(path: Path, run_dir: Path | None) -> Path:
    """`path` once safe_read.regular_file accepts it; RunLoadError (one line) otherwise."""
    try:
        return safe_read.regular_file(path, run_dir)
    except safe_read.UnsafeFileError as e:
        raise RunLoadError(str(e)) from None
    except OSError as e:  # a dangling link, a loop of links, no permission
        raise RunLoadError(f"{path}: cannot be opened ({e.strerror or e})") from None


def motion_option(value: str):
    """The `motion` node that the override `motion=<value>` selects: an option of conf/motion (composed as
    training composes it: lafan_folder, lafan_dance1_full, file, ...), or a path: a .csv/.npz file
    (`motion=file` with that path) or a folder of clips (`motion=library` with that `motion.folder`).
    RunLoadError (one line) for anything else."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from omegaconf import OmegaConf

    from bmimic import CONF_DIR
    from bmimic.motion.library import CLIP_SUFFIXES

    options = sorted(p.stem for p in (CONF_DIR / "motion").glob("*.yaml"))
    path = Path(value).expanduser()
    if value not in options:
        if path.is_dir():
            value, extra = "library", {"name": path.resolve().name, "folder": str(path.resolve())}
        elif path.is_file() and path.suffix.lower() in CLIP_SUFFIXES:
            value, extra = "file", {"name": path.stem, "path": str(path.resolve())}
        else:
            raise RunLoadError(f"override motion={value}: neither a motion option ({', '.join(options)}) nor a "
                               ".csv/.npz file or a folder of clips")
    else:
        extra = {}
    import bmimic.config  # noqa: F401  (registers the config schemas)

    GlobalHydra.instance().clear()  # a fresh composition, as the training command line makes it
    try:
        with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
            node = compose("train", overrides=[f"motion={value}"]).motion
    finally:
        GlobalHydra.instance().clear()
    return OmegaConf.merge(node, extra) if extra else node


def load_run_config(run_dir: Path, overrides: Sequence[str] = ()):
    """The run's composed config under the TrainConfig schema, with the overrides merged: `motion=<option
    or path>` replaces the run's motion (motion_option) first, as Hydra applies a group choice before
    values, then every dotted `key=value`."""
    import yaml
    from omegaconf import OmegaConf, open_dict
    from omegaconf.errors import OmegaConfBaseException

    from bmimic.config import READER_ENV_KEYS, TrainConfig, recorded_config
    from bmimic.config.checks import check_resolvable
    from bmimic.training.resume import flatten_config

    path = run_dir / HYDRA_DIR / "config.yaml"
    try:
        loaded = OmegaConf.create(safe_read.read_yaml_text(path))
        resolved = read_resolved_config(run_dir)
        if resolved is not None and isinstance(tree := OmegaConf.to_container(loaded, resolve=False), dict):
            # a run recorded before bmimic recorded values: its interpolations get the values it trained with
            loaded = OmegaConf.create(recorded_config(tree, resolved))
        reads_env = [k for k, v in flatten_config(OmegaConf.to_container(loaded, resolve=False)).items()
                     if isinstance(v, str) and "${oc.env:" in v and k not in READER_ENV_KEYS]
        if reads_env:
            raise RunLoadError(f"{path}: {reads_env[0]} interpolates an environment variable of whoever reads "
                               "the run (${oc.env:...}); a shared run's config must hold values: edit the file")
        cfg = OmegaConf.merge(OmegaConf.structured(TrainConfig), loaded)
    except (OmegaConfBaseException, OSError, ValueError, yaml.YAMLError) as e:
        raise RunLoadError(f"{path}: cannot be read as a bmimic config: {first_line(e)}") from None
    OmegaConf.set_struct(cfg, True)  # an override of a key that does not exist is an error, as in Hydra
    groups = [item for item in overrides if item.partition("=")[0] == "motion"]
    for item in groups[-1:]:  # the last choice wins, as on Hydra's command line
        with open_dict(cfg):
            cfg.motion = motion_option(item.partition("=")[2])
    for item in overrides:
        key, sep, _ = item.partition("=")
        if not sep or not key or key.startswith(("+", "~")):
            raise RunLoadError(f"override {item!r}: expected a dotted key=value (e.g. eval.horizon_s=3)")
        if key == "motion":
            continue
        try:
            cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist([item]))
        except OmegaConfBaseException as e:
            raise RunLoadError(f"override {item!r}: {first_line(e)}") from None
    cfg = _localised(cfg, path)
    try:
        check_resolvable(cfg)
    except BmimicError as e:
        raise RunLoadError(f"{path} with overrides {list(overrides)}: {first_line(e)}") from None
    return cfg


def _localised(cfg, path: Path):
    """`cfg` with a committed record's clips' folder (DATA_FOLDER_NAME, analysis.compact) read as this machine's:
    data.lafan_dir as overridden, else $BMIMIC_LAFAN_DIR, in every key below it (motion.folder too). Left as it
    is where neither names an absolute folder: a motion that reads no clips of it needs none."""
    from omegaconf import OmegaConf

    from bmimic.config import TrainConfig

    tree = OmegaConf.to_container(cfg, resolve=False)
    data = tree.get("data") if isinstance(tree, dict) else None
    given = data.get("lafan_dir") if isinstance(data, dict) else None  # an override, the token, or an interpolation
    explicit = isinstance(given, str) and given != DATA_FOLDER_NAME and not given.startswith("${")
    folder = str(given if explicit else os.environ.get("BMIMIC_LAFAN_DIR") or "").rstrip("/")
    if not folder.startswith("/") or swap_folder(tree, DATA_FOLDER_NAME, "") == tree:
        return cfg
    if not Path(folder).is_dir():
        raise RunLoadError(f"{path}: the run trained on the clips of {DATA_FOLDER_NAME} (a committed record), "
                           f"here {folder!r}, which is not a folder")
    localised = OmegaConf.merge(OmegaConf.structured(TrainConfig), swap_folder(tree, DATA_FOLDER_NAME, folder))
    OmegaConf.set_struct(localised, True)
    return localised


def anchor_relative_paths(cfg, run_dir: Path) -> None:
    """Relative input paths (motion.path, robot.mjcf_path, data.lafan_dir) were relative to the directory
    training was started in; resolve them against it (from .hydra/hydra.yaml) when they do not exist from here."""
    from omegaconf import OmegaConf

    try:
        launch_dir = Path(OmegaConf.create(safe_read.read_yaml_text(run_dir / HYDRA_DIR / "hydra.yaml")).hydra.runtime.cwd)
    except Exception:  # no hydra.yaml (a hand-made run folder): paths stay relative to here
        return
    for group, key in (("motion", "path"), ("motion", "folder"), ("robot", "mjcf_path"), ("data", "lafan_dir")):
        value = (cfg.get(group) or {}).get(key)
        if value and not Path(value).expanduser().is_absolute() and not Path(value).exists():
            if (launch_dir / value).exists():
                cfg[group][key] = str(launch_dir / value)


TASK_KEYS = ("robot", "motion", "env", "sim.timestep_s", "sim.decimation", "sampler.bins", "sampler.bin_size_seconds",
             "ppo.actor_hidden_dims", "ppo.critic_hidden_dims", "ppo.activation")
"""Config keys (and prefixes) a checkpoint must share with the run it is evaluated in: the robot, its
motion, the MDP, the control rate, the bins and the networks."""


@dataclass
class LoadedRun:
    """A run's config resolved for this machine, with its task rebuilt from it."""

    run_dir: Path
    """The run folder."""
    checkpoint: Path
    """The checkpoint file to use."""
    task: Task
    """The run's config (composed, runtime-resolved, overrides applied), device, robot, motion and bins."""
    overrides: tuple[str, ...] = ()
    """The dotted overrides given on the command line."""


def load_run(path: str | Path, overrides: Sequence[str] = (), trust: bool = False) -> LoadedRun:
    """Locate the run, reload and resolve its config, rebuild robot, motion and bins like training.

    A run folder may come from someone else: a config whose terms import modules outside bmimic
    (`func: package.module:function`) is refused unless `trust` (--trust-checkpoint)."""
    from bmimic.config import placed, resolve_runtime
    from bmimic.config.checks import validate
    from bmimic.envs.config import foreign_term_modules
    from bmimic.runtime import resolve_device, use_cpu_threads
    from bmimic.task import build_task

    run_dir, checkpoint = locate_run(path)
    cfg = load_run_config(run_dir, overrides)
    foreign = foreign_term_modules(cfg.env)
    if foreign and not trust:
        raise RunLoadError(f"{run_dir}: its config imports {', '.join(foreign)} (code outside bmimic) for env "
                           "terms; pass --trust-checkpoint if you trust this run folder")
    anchor_relative_paths(cfg, run_dir)
    device = resolve_device(cfg.device)
    use_cpu_threads(device)
    resolve_runtime(cfg, device)
    validate(cfg)
    return LoadedRun(run_dir, checkpoint, build_task(placed(cfg), device), tuple(overrides))


def load_run_checkpoint(run: LoadedRun) -> dict:
    """The run's checkpoint (weights-only), checked to belong to the run: its own config and meta
    (bmimic checkpoint format 2) must agree with the run's on the TASK_KEYS and the motion, except
    where a command-line override names the key. A checkpoint copied from another run would otherwise
    be evaluated on this run's motion without a word."""
    from bmimic.training.checkpoints import load_checkpoint_file, motion_meta
    from bmimic.training.resume import config_changes, key_allowed

    state = load_checkpoint_file(run.checkpoint, run.task.device)
    named = [o.partition("=")[0] for o in run.overrides]
    allowed = [*named, *accepted_changes(run.run_dir)]
    differ = []
    try:
        own = safe_read.parse_json(state["config"]) if isinstance(state.get("config"), str) else None
    except ValueError:
        own = None
    ours = read_resolved_config(run.run_dir)
    folder = str(run.task.cfg.data.lafan_dir or "").rstrip("/")
    if folder.startswith("/"):  # a committed record names the clips' folder DATA_FOLDER_NAME, a restored
        own, ours = (swap_folder(c, DATA_FOLDER_NAME, folder) for c in (own, ours))  # state this machine's
    if isinstance(own, dict) and ours is not None:
        differ += [f"{k} ({a} -> {b})" for k, (a, b) in config_changes(own, ours).items()
                   if key_allowed(k, TASK_KEYS) and not key_allowed(k, allowed)]
    meta = state.get("meta")
    if isinstance(meta, dict) and not any(k == "motion" or k.startswith("motion.") for k in named):
        current = {**motion_meta(run.task.motion), "num_bins": int(run.task.layout.num_bins)}
        differ += [f"meta {k} ({meta[k]} -> {v})" for k, v in current.items() if k in meta and meta[k] != v]
    if differ:
        raise RunLoadError(f"{run.checkpoint}: was trained with another task than the run {run.run_dir}: "
                           f"{'; '.join(differ[:4])}{'; ...' if len(differ) > 4 else ''}; evaluate it in its own "
                           "run folder (or name those keys as overrides to evaluate it on this run's settings)")
    return state


def accepted_changes(run_dir: Path) -> list[str]:
    """Config keys a resume of the run accepted (resumes.json): its older checkpoints differ in them."""
    history = read_json(Path(run_dir) / RESUMES, default=[])
    return [k for entry in history if isinstance(entry, dict) for k in (entry.get("changes") or {})]


def checkpoint_label(checkpoint: Path, state: dict) -> str:
    """Folder name of a checkpoint's results: its stem; latest.pt is named after its iteration."""
    if checkpoint.name == LATEST_CHECKPOINT and "iter" in state:
        return run_checkpoint_label(int(state["iter"]))
    return checkpoint.stem


def trained_on(run: LoadedRun, state: dict) -> bool | None:
    """Whether the run's task motion is the one the checkpoint was trained on (its meta's digest); None
    for a checkpoint without meta (an older format)."""
    from bmimic.training.checkpoints import motion_meta

    meta = state.get("meta")
    if not isinstance(meta, dict) or "motion_sha256" not in meta:
        return None
    return motion_meta(run.task.motion)["motion_sha256"] == meta["motion_sha256"]


def evaluation_label(run: LoadedRun, state: dict) -> str:
    """Folder name of an evaluation's results: checkpoint_label, and for a motion the checkpoint was not
    trained on (`motion=...`) `<label>_on_<motion name>-<digest>`, so that it never replaces the evaluation
    on the training motion (which sim2sim's gap compares against)."""
    import re

    from bmimic.training.checkpoints import motion_meta

    label = checkpoint_label(run.checkpoint, state)
    seen = trained_on(run, state)
    if seen or (seen is None and not any(o.partition("=")[0].startswith("motion") for o in run.overrides)):
        return label
    name = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(run.task.cfg.motion.name)).strip("._") or "motion"
    return f"{label}_on_{name}-{motion_meta(run.task.motion)['motion_sha256'][:8]}"


def evaluation_record(run: LoadedRun, state: dict, overrides: Sequence[str]) -> dict:
    """What an evaluation summary says of where it comes from: the checkpoint, its iteration and env
    steps, the run, motion, seed and device, the overrides, when, and the results' label."""
    import datetime as _dt

    from bmimic.runs.schema import ENV_STEPS, ITERATION

    cfg = run.task.cfg
    progress = state.get("progress") or {}
    return {
        "checkpoint": str(run.checkpoint),
        ITERATION: int(state.get("iter", -1)),
        ENV_STEPS: int(progress.get(ENV_STEPS, -1)),
        "run_dir": str(run.run_dir),
        "motion": str(cfg.motion.name),
        "seed": int(cfg.seed),
        "device": run.task.device,
        "overrides": list(overrides),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "motion_clips": list(getattr(run.task.layout, "clip_names", ())),
        "trained_on_motion": trained_on(run, state),  # False: a motion the policy never saw (generalisation)
        "label": evaluation_label(run, state),
    }
