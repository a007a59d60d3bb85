"""Checkpoint files: the format, the safe reader and the atomic writer.

Checkpoints are read only with `torch.load(weights_only=True)`: loading a shared checkpoint never
runs code, trusted or not (a trusted format-1 file only widens the allowlist by numpy's array
reconstruction). Where they lie and what they are called is bmimic.runs.folder's business.
"""

from __future__ import annotations

import os
import pickle
import re
from pathlib import Path
from typing import Any

from bmimic import BmimicError
from bmimic.runs.folder import LATEST_CHECKPOINT, atomic_write, checkpoint_files

CHECKPOINT_FORMAT = "bmimic-checkpoint-2"
"""Tensors and plain values only: readable with torch.load(weights_only=True)."""
MAX_ITERATION = 10**9
"""Largest iteration a checkpoint may name (it becomes file and folder names: model_<it>)."""
LEGACY_CHECKPOINT_FORMATS = ("bmimic-checkpoint-1",)
"""Written by earlier bmimic versions with pickled numpy RNG states: they load only when trusted."""
LEGACY_GLOBALS = ("numpy.dtype", "numpy.ndarray", "numpy._core.multiarray._reconstruct",
                  "numpy.core.multiarray._reconstruct", "numpy.dtypes.UInt32DType")
"""The globals a format-1 checkpoint's numpy RNG state needs: they rebuild arrays and run no code."""


class CheckpointError(BmimicError):
    """A checkpoint that cannot be read (missing, truncated, not a torch file)."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint whose pickle names a global that could run code; refused unless trusted."""


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> Path:
    """torch.save `obj` to `path` atomically."""
    import torch

    return atomic_write(path, lambda tmp: torch.save(obj, tmp))


def load_checkpoint_file(path: str | os.PathLike, map_location: str = "cpu", trust: bool = False) -> dict:
    """The checkpoint dict at `path`, read with `weights_only=True` (nothing in it can run code).

    `trust=True` (`--trust-checkpoint`, `trust_checkpoint=true`) reads a file refused for its globals
    when they are all LEGACY_GLOBALS (format-1 checkpoints of earlier bmimic versions), still with
    `weights_only=True`. Raises CheckpointError / UnsafeCheckpointError with one line.
    """
    import torch

    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: no such checkpoint file")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        found = re.search(r"GLOBAL ([\w.]+)", str(e))
        if found is None:  # not a pickle of plain data at all (a text file, a foreign format)
            raise CheckpointError(f"{path}: not a readable torch checkpoint (not a pickle of plain data)") from None
        if not trust:
            raise UnsafeCheckpointError(
                f"{path}: refused: its pickle needs the global {found.group(1)}, which loading would run as "
                "code; if you wrote this checkpoint yourself (bmimic before checkpoint format 2), load it "
                "with --trust-checkpoint (eval, play) or trust_checkpoint=true (train resume)") from None
        state = _load_legacy(path, map_location)
    except Exception as e:  # noqa: BLE001 - truncated zip, empty file, not a torch file, I/O error
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({_first_line(e)})") from None
    if not isinstance(state, dict) or "actor_state_dict" not in state:
        raise CheckpointError(f"{path}: not an rsl-rl/bmimic checkpoint (no actor_state_dict)")
    it = state.get("iter", 0)
    if isinstance(it, bool) or not isinstance(it, int) or not 0 <= it <= MAX_ITERATION:
        raise CheckpointError(f"{path}: its iteration 'iter' must be an integer in [0, {MAX_ITERATION}], "
                              f"got {str(it)[:40]!r}")
    return state


def _load_legacy(path: Path, map_location: str) -> dict:
    """A trusted file refused for its globals, read with weights_only=True and LEGACY_GLOBALS allowed;
    a file needing any other global is refused even when trusted."""
    import importlib

    import torch

    try:
        needed = torch.serialization.get_unsafe_globals_in_checkpoint(path)
    except Exception as e:  # noqa: BLE001 - any reader failure is "cannot read this file"
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({_first_line(e)})") from None
    other = sorted(set(needed) - set(LEGACY_GLOBALS))
    if other:
        raise UnsafeCheckpointError(f"{path}: refused even with trust: its pickle needs {', '.join(other)}, which "
                                    "no bmimic checkpoint contains and loading would run as code")
    allowed = []  # all of them: the dtype classes are asked for only while loading
    for name in LEGACY_GLOBALS:
        module, _, attr = name.rpartition(".")
        try:
            allowed.append(getattr(importlib.import_module(module), attr))
        except (ImportError, AttributeError):  # numpy 1 has no numpy._core, numpy 2 warns on numpy.core
            continue
    try:
        with torch.serialization.safe_globals(allowed):
            return torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # noqa: BLE001 - any reader failure is "cannot read this file"
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({_first_line(e)})") from None


def _first_line(e: BaseException) -> str:
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(e)).strip()
    return text.splitlines()[0][:200] if text else type(e).__name__


def load_newest_intact(ckpt_dir: Path, trust: bool = False) -> tuple[Path, dict, str]:
    """(path, state, note) of the newest checkpoint in `ckpt_dir` that reads; `note` says which
    damaged files were passed over. A checkpoint refused as unsafe is never passed over."""
    damaged = []
    for path in checkpoint_files(ckpt_dir):
        try:
            state = load_checkpoint_file(path, "cpu", trust)
        except UnsafeCheckpointError:
            raise
        except CheckpointError as e:
            damaged.append(f"{path.name} ({str(e).split('(', 1)[-1].rstrip(')')})")
            continue
        note = (f"{', '.join(damaged)} could not be read; resuming from {path.name}, the newest intact "
                "checkpoint") if damaged else ""
        return path, state, note
    what = f" ({'; '.join(damaged)})" if damaged else ""
    raise CheckpointError(f"{ckpt_dir}: no readable checkpoint{what}")


def is_latest(path: Path) -> bool:
    """`path` is a run's latest.pt (a copy of its newest model_<it>.pt), not a numbered checkpoint."""
    return Path(path).name == LATEST_CHECKPOINT


def motion_meta(motion) -> dict:
    """What a checkpoint records of the motion it was trained on (its `meta`): frames, rate and a
    digest of the joint and body positions."""
    import hashlib

    digest = hashlib.sha256(motion.joint_pos.tobytes())
    digest.update(motion.body_pos_w.tobytes())
    return {"motion_frames": int(motion.num_frames), "motion_fps": float(motion.fps),
            "motion_sha256": digest.hexdigest()[:16]}


class CheckpointMismatchError(BmimicError):
    """A checkpoint that does not fit the environment, sampler or networks built from this config."""


def mismatch_detail(e: BaseException) -> str:
    """The first concrete line of a load_state_dict error (which parameter, which shapes)."""
    lines = [x.strip() for x in str(e).splitlines() if x.strip()]
    return lines[1] if len(lines) > 1 else (lines[0] if lines else type(e).__name__)
