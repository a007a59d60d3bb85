"""Run folders, provenance, status files, atomic writes, device resolution and seeding.

Everything a run writes goes through `atomic_write_*` (temp file in the same folder + os.replace),
so an interrupted run never leaves a half-written checkpoint, table or status file behind.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import random
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------------- atomic I/O
def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> None:
    """Call `write(tmp_path)` and move the result onto `path` in one rename.

    The temp file ends in `path`'s own suffix (`.play.mp4.tmp-x1y2.mp4`): writers that choose the
    format by extension (imageio's FFMPEG writer) accept it.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    def _w(tmp: str) -> None:
        with open(tmp, "w") as f:
            f.write(text)
            f.flush()
            os.fsync(f.fileno())

    atomic_write(path, _w)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> None:
    atomic_write(path, lambda tmp: torch.save(obj, tmp))


def atomic_write_parquet(path: str | os.PathLike, df) -> None:
    atomic_write(path, lambda tmp: df.to_parquet(tmp, index=False))


def read_json(path: str | os.PathLike, default: Any = None) -> Any:
    try:
        with open(path) as f:
            return json.load(f)
    except (FileNotFoundError, json.JSONDecodeError):
        return default


# --------------------------------------------------------------------------------------------- status
def _now() -> str:
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def write_status(run_dir: str | os.PathLike, status: str, iteration: int = 0, error: str | None = None) -> None:
    """status.json: `running`, `done` or `failed` (with the error's one-line message)."""
    atomic_write_json(
        Path(run_dir) / "status.json",
        {"status": status, "iteration": int(iteration), "error": error, "updated": _now()},
    )


def read_status(run_dir: str | os.PathLike) -> dict:
    return read_json(Path(run_dir) / "status.json", default={"status": "missing"})


# --------------------------------------------------------------------------------------------- device
def resolve_device(device: str) -> str:
    """`auto` -> `cuda` when a GPU is visible, else `cpu`; explicit values are checked."""
    if device == "auto":
        return "cuda:0" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        from bmimic import BmimicError

        raise BmimicError(f"device={device} was requested but no CUDA GPU is visible; use device=cpu or auto")
    if device == "cuda":
        return "cuda:0"
    return device


# --------------------------------------------------------------------------------------------- seeding
def seed_everything(seed: int) -> torch.Generator:
    """Seed python, numpy, torch and warp from one integer; return the generator the sampler uses."""
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)
    if torch.cuda.is_available():
        torch.cuda.manual_seed_all(seed)
    try:
        import warp as wp

        wp.rand_init(seed) if hasattr(wp, "rand_init") else None
    except ImportError:  # pragma: no cover - warp is a hard dependency, but seeding must not need it
        pass
    gen = torch.Generator()
    gen.manual_seed(seed + 1)  # a distinct stream for the motion sampler
    return gen


def rng_state() -> dict:
    """All global RNG states, for checkpoints."""
    state = {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    random.setstate(state["python"])
    np.random.set_state(state["numpy"])
    torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


# --------------------------------------------------------------------------------------------- provenance
def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=10, check=True
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def _version(module: str) -> str | None:
    try:
        from importlib.metadata import version

        return version(module)
    except Exception:
        return None


def provenance(device: str) -> dict:
    """What produced a run: code version, library versions, hardware, precision flags, command line."""
    info: dict[str, Any] = {
        "created": _now(),
        "git_commit": _git("rev-parse", "HEAD"),
        "git_dirty": bool(_git("status", "--porcelain", "--untracked-files=no")),
        "command": " ".join([Path(sys.argv[0]).name, *sys.argv[1:]]),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "hostname": platform.node(),
        "versions": {
            name: _version(name)
            for name in ("torch", "warp-lang", "mujoco", "mujoco-warp", "rsl-rl-lib", "hydra-core", "bmimic")
        },
        "device": device,
        "torch_precision": {
            "matmul_allow_tf32": torch.backends.cuda.matmul.allow_tf32,
            "cudnn_allow_tf32": torch.backends.cudnn.allow_tf32,
            "float32_matmul_precision": torch.get_float32_matmul_precision(),
        },
    }
    if device.startswith("cuda") and torch.cuda.is_available():
        idx = torch.device(device).index or 0
        info["gpu"] = {
            "name": torch.cuda.get_device_name(idx),
            "count": torch.cuda.device_count(),
            "cuda_runtime": torch.version.cuda,
            "driver": _nvidia_driver(),
        }
    return info


def _nvidia_driver() -> str | None:
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
            capture_output=True, text=True, timeout=10, check=True,
        )
        return out.stdout.strip().splitlines()[0]
    except (OSError, subprocess.SubprocessError, IndexError):
        return None


def write_provenance(run_dir: str | os.PathLike, device: str) -> dict:
    info = provenance(device)
    atomic_write_json(Path(run_dir) / "provenance.json", info)
    return info
