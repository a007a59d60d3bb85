"""Checkpoint files: the format, the safe reader and the atomic writer.

Checkpoints are read only with `torch.load(weights_only=True)`: loading a shared checkpoint never
runs code. Where they lie and what they are called is bmimic.runs.folder's business.
"""

from __future__ import annotations

import os
import pickle
import re
from pathlib import Path
from typing import Any

from bmimic import BmimicError
from bmimic.runs import safe_read
from bmimic.runs.folder import LATEST_CHECKPOINT, atomic_write, checkpoint_files

CHECKPOINT_FORMAT = "bmimic-checkpoint-2"
"""Tensors and plain values only: readable with torch.load(weights_only=True)."""
MAX_ITERATION = 10**9
"""Largest iteration a checkpoint may name (it becomes file and folder names: model_<it>)."""


class CheckpointError(BmimicError):
    """A checkpoint that cannot be read (missing, truncated, not a torch file)."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint whose pickle names a global that could run code; always refused."""


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> Path:
    """torch.save `obj` to `path` atomically."""
    import torch

    return atomic_write(path, lambda tmp: torch.save(obj, tmp))


def load_checkpoint_file(path: str | os.PathLike, map_location: str = "cpu",
                         within: str | os.PathLike | None = None) -> dict:
    """The checkpoint dict at `path`, read with `weights_only=True` (nothing in it can run code), once
    it is a regular file (and, with `within`, its run folder's own: safe_read.regular_file), since
    torch.load would block on a FIFO and read a device forever. Raises CheckpointError /
    UnsafeCheckpointError with one line."""
    import torch

    path = Path(path)
    try:
        safe_read.regular_file(path, within)
    except FileNotFoundError:
        raise CheckpointError(f"{path}: no such checkpoint file") from None
    except safe_read.UnsafeFileError as e:
        raise CheckpointError(str(e)) from None
    except OSError as e:
        raise CheckpointError(f"{path}: cannot be opened ({e.strerror or e})") from None
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        found = re.search(r"GLOBAL ([\w.]+)", str(e))
        if found is None:  # not a pickle of plain data at all (a text file, a foreign format)
            raise CheckpointError(f"{path}: not a readable torch checkpoint (not a pickle of plain data)") from None
        raise UnsafeCheckpointError(
            f"{path}: refused: its pickle needs the global {found.group(1)}, which loading would run as code "
            f"(a bmimic checkpoint holds tensors and plain values only, {CHECKPOINT_FORMAT})") from None
    except Exception as e:  # noqa: BLE001 - truncated zip, empty file, not a torch file, I/O error
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({_first_line(e)})") from None
    if not isinstance(state, dict) or "actor_state_dict" not in state:
        raise CheckpointError(f"{path}: not an rsl-rl/bmimic checkpoint (no actor_state_dict)")
    it = state.get("iter", 0)
    if isinstance(it, bool) or not isinstance(it, int) or not 0 <= it <= MAX_ITERATION:
        raise CheckpointError(f"{path}: its iteration 'iter' must be an integer in [0, {MAX_ITERATION}], "
                              f"got {str(it)[:40]!r}")
    _check_weights(path, state)
    return state


def _check_weights(path: Path, state: dict) -> None:
    """The networks' tensors are weights a policy can run: a weight or bias of floating dtype (an integer
    one was cast back silently by load_state_dict, giving another policy), and every floating value finite
    (NaN weights evaluated to NaN errors and 100% failure, exit 0; a resume trained on them and blamed the
    learning rate). Issue 77's second round."""
    import torch

    for part in ("actor_state_dict", "critic_state_dict"):
        weights = state.get(part)
        if weights is None:
            continue
        if not isinstance(weights, dict):
            raise CheckpointError(f"{path}: {part} is not a dict of tensors")
        for name, t in weights.items():
            if not isinstance(t, torch.Tensor):
                raise CheckpointError(f"{path}: {part}[{str(name)[:60]!r}] is not a tensor")
            if str(name).endswith(("weight", "bias")) and not t.is_floating_point():
                raise CheckpointError(f"{path}: {part}[{name!r}] is {t.dtype}, not a floating-point weight")
            if t.is_floating_point() and not bool(torch.isfinite(t).all()):
                raise CheckpointError(f"{path}: {part}[{name!r}] holds NaN or infinite values; "
                                      "its policy cannot be evaluated or trained on")


def _first_line(e: BaseException) -> str:
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(e)).strip()
    return text.splitlines()[0][:200] if text else type(e).__name__


def load_newest_intact(ckpt_dir: Path) -> tuple[Path, dict, str]:
    """(path, state, note) of the newest checkpoint in `ckpt_dir` that reads; `note` says which
    damaged files were passed over. A checkpoint refused as unsafe is never passed over."""
    damaged = []
    for path in checkpoint_files(ckpt_dir):
        try:
            state = load_checkpoint_file(path, "cpu", within=Path(ckpt_dir).parent)  # the run's own
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
