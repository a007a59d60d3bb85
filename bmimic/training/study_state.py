"""A study's resumable state: a run's newest checkpoint made small enough to commit, and back.

A study that trains across sittings commits, at the end of each, one state file per job under
`docs/results/<study>/state/` beside the job's tables (`docs/results/<study>/runs/<job>/`); the next
sitting copies the tables into a run folder, `unpack`s the state into its `checkpoints/`, and continues it
with `resume=true`. The file (STATE_FORMAT, plain tensors: it loads with `weights_only=True`) holds what a
checkpoint holds (policy, critic, optimiser, sampler, RNG streams, counters, the config it trained with,
its meta) less two things:
- the worlds' state (`env`, 5.2 kB per world on the G1: ~42 MB at 8,192 worlds): the resumed run's worlds start
  afresh, as at a run's start, so a sitting boundary costs one wave of episode starts; a run continued from
  its own checkpoint (`resume=true` in its folder) keeps them and continues exactly;
- with `moments="bf16"`, the optimiser's Adam moments are stored in bfloat16 (relative error < 2**-8 per
  element above 2**-126, smaller ones may become 0; the weights stay float32): half the optimiser's bytes.
No motion data is in it (the meta holds the motion's digest, not its frames).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from bmimic import BmimicError
from bmimic.runs import safe_read
from bmimic.runs.folder import (
    DATA_FOLDER_NAME,
    checkpoint_path,
    checkpoints_dir,
    is_run_folder,
    latest_checkpoint,
    read_resolved_config,
    swap_folder,
    table_path,
)
from bmimic.runs.schema import ITERATION
from bmimic.training.checkpoints import (
    CheckpointError,
    atomic_torch_save,
    load_checkpoint_file,
    load_newest_intact,
)
from bmimic.training.resume import config_changes, flatten_config, refused_changes

STATE_FORMAT = "bmimic-state-1"
"""This version's state files; one of another `bmimic-state-N` is refused by name."""
MOMENTS = ("fp32", "bf16")
"""How the optimiser's moments are stored: exactly, or in bfloat16."""
_DROPPED = ("env",)
"""Checkpoint entries a state leaves out (see the module's docstring)."""


class StateError(BmimicError):
    """A state file that cannot be packed, read or unpacked into the run named; nothing was written."""


def pack(checkpoint: dict, moments: str = "fp32") -> dict:
    """The state of `checkpoint` (a bmimic checkpoint dict), as `save_state` writes it."""
    if moments not in MOMENTS:
        raise StateError(f"moments must be one of {', '.join(MOMENTS)}, got {moments!r}")
    state = {k: v for k, v in checkpoint.items() if k not in _DROPPED}
    state["optimizer_state_dict"] = _cast_moments(checkpoint["optimizer_state_dict"],
                                                  torch.bfloat16 if moments == "bf16" else None)
    state.update(format=STATE_FORMAT, checkpoint_format=checkpoint.get("format"), moments=moments)
    if isinstance(checkpoint.get("config"), str):  # no path of the machine it trained on (its clips' folder)
        state["config"] = json.dumps(_portable(_config(checkpoint, "checkpoint")), sort_keys=True)
    return state


def unpack(state: dict) -> dict:
    """The checkpoint dict of a packed `state` (moments back in float32; no env state)."""
    checkpoint = {k: v for k, v in state.items() if k not in ("format", "checkpoint_format", "moments")}
    checkpoint["format"] = state.get("checkpoint_format")
    checkpoint["optimizer_state_dict"] = _cast_moments(state["optimizer_state_dict"], torch.float32)
    return checkpoint


def _cast_moments(optimizer: dict, dtype: torch.dtype | None) -> dict:
    """A copy of an optimiser state dict with its floating per-parameter tensors (Adam's moments) in
    `dtype` (None: unchanged); the step counters keep theirs."""
    def cast(value: Any) -> Any:
        if dtype is not None and isinstance(value, torch.Tensor) and value.is_floating_point() and value.dim() > 0:
            return value.to(dtype)
        return value
    return {**optimizer, "state": {k: {n: cast(v) for n, v in s.items()}
                                   for k, s in optimizer.get("state", {}).items()}}


def save_state(run_dir: Path, out: Path, moments: str = "fp32") -> dict:
    """Write the state of `run_dir`'s newest intact checkpoint to `out` (atomically). `out` may only
    replace a state of the same job at an earlier or equal iteration (the study's previous sitting);
    anything else there is refused. Returns the state written."""
    run_dir, out = Path(run_dir), Path(out)
    if not is_run_folder(run_dir):
        raise StateError(f"{run_dir}: not a bmimic run folder")
    _, checkpoint, _ = load_newest_intact(checkpoints_dir(run_dir))
    state = pack(checkpoint, moments)
    if out.exists() or out.is_symlink():
        try:
            old = read_state(out)
        except StateError as e:
            raise StateError(f"{out}: exists and is not a state this command may replace ({e})") from None
        differ = _other_job(_config(old, out), _config(state, run_dir))
        if differ:
            raise StateError(f"{out}: holds another job's state (differs in {', '.join(sorted(differ)[:3])}); "
                             "name another file")
        if int(old["iter"]) > int(state["iter"]):
            raise StateError(f"{out}: holds iteration {old['iter']}, newer than {run_dir}'s {state['iter']}")
    atomic_torch_save(out, state)
    return state


def read_state(path: Path) -> dict:
    """A state file, read with `weights_only=True` and checked; StateError (one line) otherwise."""
    path = Path(path)
    if path.is_symlink() or (path.exists() and not path.is_file()):
        raise StateError(f"{path}: not a regular file")
    try:
        state = load_checkpoint_file(path)
    except CheckpointError as e:
        raise StateError(str(e)) from None
    fmt = state.get("format")
    if fmt != STATE_FORMAT:
        newer = isinstance(fmt, str) and fmt.startswith("bmimic-state-")
        raise StateError(f"{path}: format {str(fmt)[:40]!r} " + (
            f"is not this bmimic's {STATE_FORMAT} (a newer bmimic wrote it?)" if newer
            else f"is not a bmimic state ({STATE_FORMAT}); a checkpoint goes to resume=, not here"))
    if state.get("moments") not in MOMENTS or "optimizer_state_dict" not in state:
        raise StateError(f"{path}: damaged state (no optimiser state or unknown moments "
                         f"{str(state.get('moments'))[:20]!r})")
    return state


def restore_state(state_path: Path, run_dir: Path) -> Path:
    """Write the checkpoint of the state at `state_path` into `run_dir` (a copy of the job's committed
    record: its config and tables) as checkpoints/model_<it>.pt and latest.pt, so that `resume=true` in
    `run_dir` continues the job. Refused, with nothing written, when the run folder already holds a
    checkpoint, trained another job (a result-changing config key differs), or its tables end before the
    state's iteration. Returns the latest.pt written."""
    state = read_state(state_path)
    run_dir = Path(run_dir)
    if not is_run_folder(run_dir):
        raise StateError(f"{run_dir}: not a bmimic run folder (copy the job's committed record there first)")
    record_config = read_resolved_config(run_dir)
    if record_config is None:
        raise StateError(f"{run_dir}: no readable resolved_config.json to compare the state with")
    differ = _other_job(_config(state, state_path), _portable(record_config))
    if differ:
        shown = ", ".join(f"{k} ({v[0]!r} -> {v[1]!r})" for k, v in sorted(differ.items())[:3])
        raise StateError(f"{state_path}: trained another job than {run_dir} ({shown})")
    iteration = int(state["iter"])
    last = _last_trained(run_dir)
    if last is None or last + 1 < iteration:
        raise StateError(f"{state_path}: at iteration {iteration}, but {run_dir}'s train_metrics end at "
                         f"{'no iteration' if last is None else last + 1}: restore the record of the same sitting")
    latest = latest_checkpoint(run_dir)
    if any(p.exists() or p.is_symlink() for p in (latest, checkpoint_path(run_dir, iteration))):
        raise StateError(f"{run_dir}: already holds a checkpoint ({latest.name}); a state is restored into a "
                         "run folder without one")
    checkpoint = unpack(state)
    checkpoint["config"] = json.dumps(_localised(_config(state, state_path), state_path), sort_keys=True)
    atomic_torch_save(checkpoint_path(run_dir, iteration), checkpoint)
    atomic_torch_save(latest, checkpoint)
    return latest


def _other_job(old: dict, new: dict) -> dict:
    """{key: (old, new)} of the keys that a resume would refuse to change (the job's own: not its budget,
    its logistics or its launch), among those `old` records: empty when `new` continues the same job."""
    recorded = flatten_config(old)
    changes = {k: v for k, v in config_changes(old, new).items() if k in recorded}
    return {k: changes[k] for k in refused_changes(changes, ())}


def _portable(config: dict) -> dict:
    """`config` as a committed record holds it (analysis.compact): its absolute data.lafan_dir, wherever it
    appears, as DATA_FOLDER_NAME."""
    folder = (config.get("data") or {}).get("lafan_dir")
    if not isinstance(folder, str) or not folder.startswith("/") or folder == "/":
        return config
    return swap_folder(config, folder.rstrip("/"), DATA_FOLDER_NAME)


def _localised(config: dict, path: Path) -> dict:
    """A portable `config` with DATA_FOLDER_NAME back as this machine's clips' folder ($BMIMIC_LAFAN_DIR,
    as data.lafan_dir defaults to), so that the resume compares it with the launch's like any checkpoint."""
    if (config.get("data") or {}).get("lafan_dir") != DATA_FOLDER_NAME:
        return config
    folder = os.environ.get("BMIMIC_LAFAN_DIR", "").rstrip("/")
    if not folder.startswith("/") or not Path(folder).is_dir():
        raise StateError(f"{path}: trained on the clips of $BMIMIC_LAFAN_DIR; set it to that folder here (an absolute "
                         f"path, got {folder or 'nothing'!r})")
    return swap_folder(config, DATA_FOLDER_NAME, folder)


def _last_trained(run_dir: Path) -> int | None:
    """The last iteration of the run's train_metrics table (None: none readable)."""
    import pandas as pd

    try:
        path = safe_read.regular_file(table_path(run_dir, "train_metrics"), run_dir)  # never a FIFO or device
        iterations = pd.read_parquet(path, columns=[ITERATION])[ITERATION]
    except Exception:  # noqa: BLE001 - absent or damaged: the record cannot carry the state
        return None
    return int(iterations.max()) if len(iterations) else None


def _config(state: dict, path: str | os.PathLike) -> dict:
    """The resolved config a state's checkpoint trained with."""
    text = state.get("config")
    try:
        config = json.loads(text) if isinstance(text, str) else None
    except ValueError:
        config = None
    if not isinstance(config, dict):
        raise StateError(f"{path}: records no readable config of the run it was trained in")
    return config


__all__ = ["MOMENTS", "STATE_FORMAT", "StateError", "pack", "read_state", "restore_state", "save_state", "unpack"]
