"""The process a run lives in: its device, random streams, process group and provenance.

`resolve_device` turns `device=auto|cpu|cuda|cuda:N` into a torch device, `seed_everything` seeds
python, numpy, torch and warp from one integer, `rng_state`/`set_rng_state` carry every stream in a
checkpoint, `init_distributed` joins torchrun's process group, and `provenance` records what
produced a run (bmimic.runs.folder writes it to provenance.json).
"""

from __future__ import annotations

import logging
import os
import platform
import random
import re
import subprocess
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bmimic import BmimicError
from bmimic.rendezvous import DistributedSetupError, meet
from bmimic.runs.folder import now

if TYPE_CHECKING:
    import torch

log = logging.getLogger(__name__)

REPO_ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------------- device
_DEVICE = re.compile(r"^(auto|cpu|cuda|cuda:(0|[1-9][0-9]*))$")


def resolve_device(device: str) -> str:
    """`auto` -> `cuda:0` when a GPU is visible, else `cpu`; `cpu`, `cuda`, `cuda:N` are checked."""
    import torch

    if not isinstance(device, str) or not _DEVICE.match(device):
        raise BmimicError(f"device: {device!r} is not one of auto, cpu, cuda, cuda:N")
    if device == "auto":
        return "cuda:0" if torch.cuda.is_available() else "cpu"
    if device == "cpu":
        return device
    if not torch.cuda.is_available():
        raise BmimicError(f"device={device} was requested but no CUDA GPU is visible; use device=cpu or auto")
    index = int(device.split(":")[1]) if ":" in device else 0
    count = torch.cuda.device_count()
    if index >= count:
        raise BmimicError(f"device={device}: only {count} GPU(s) are visible (cuda:0..cuda:{count - 1})")
    return f"cuda:{index}"


def guess_device(device: str) -> str:
    """`resolve_device` without importing torch, for a dry run: `cpu` where resolve_device would give it
    (device=cpu, or auto where the NVIDIA driver lists no GPU or CUDA_VISIBLE_DEVICES hides them all),
    else the GPU `device` names (`cuda:0` for auto); it checks nothing a real run checks."""
    if device != "auto":
        return device
    hidden = os.environ.get("CUDA_VISIBLE_DEVICES", None) in ("", "-1")
    gpus = Path("/proc/driver/nvidia/gpus")
    return "cuda:0" if not hidden and gpus.is_dir() and any(gpus.iterdir()) else "cpu"


THREAD_ENV = ("OMP_NUM_THREADS", "MKL_NUM_THREADS")
"""Environment variables by which a user sets torch's CPU threads; set, they are obeyed."""


def use_cpu_threads(device: str) -> int | None:
    """A CPU run's torch threads: one, unless THREAD_ENV names a number (returns what was set; None on a
    GPU or where the environment decides). The physics runs on Warp's CPU backend, one thread; what
    torch computes there (the policy, PPO's mini-batches of a few hundred rows) is too small to share,
    so a second thread only waits, and beside other processes (a sweep's jobs, pytest's workers) it
    oversubscribes the cores. Measured on 2 cores (docs/benchmarks.md, 2026-12-08): the default run's
    4 iterations trained in 12 s with one thread, 28-45 s with torch's default, the same numbers."""
    if not device.startswith("cpu") or any(os.environ.get(name, "").strip() for name in THREAD_ENV):
        return None
    import torch

    torch.set_num_threads(1)
    return 1


RENDEZVOUS_TIMEOUT_S = 300.0
"""How long a torchrun rank waits for the others to meet (`$BMIMIC_RENDEZVOUS_TIMEOUT_S` sets it): a
rank started alone (WORLD_SIZE=2 without its peer) ends with one line instead of waiting forever."""


def _whole(name: str, default: int, low: int) -> int:
    text = os.environ.get(name)
    if text is None:
        return default
    try:
        value = int(text.strip())
    except ValueError:
        value = low - 1
    if value < low:
        raise DistributedSetupError(f"{name}={text!r}: must be a whole number >= {low} (torchrun sets it; unset it to "
                                    "run one process)")
    return value


def torchrun_env() -> tuple[int, int, int]:
    """(rank, world size, local rank) from torchrun's RANK, WORLD_SIZE and LOCAL_RANK ((0, 1, 0) without
    them), checked: whole numbers, the rank below the world size, and with more than one rank the
    rendezvous address (MASTER_ADDR, MASTER_PORT). DistributedSetupError (one line) otherwise."""
    world = _whole("WORLD_SIZE", 1, 1)
    rank = _whole("RANK", 0, 0)
    local = _whole("LOCAL_RANK", 0, 0)
    if rank >= world:
        raise DistributedSetupError(f"RANK={rank} with WORLD_SIZE={world}: a rank must be below the world size "
                                    "(torchrun sets both; unset them to run one process)")
    if world > 1:
        if "RANK" not in os.environ:
            raise DistributedSetupError(f"WORLD_SIZE={world} without RANK: start the ranks with torchrun (or unset "
                                        "WORLD_SIZE to run one process)")
        for name in ("MASTER_ADDR", "MASTER_PORT"):
            if not os.environ.get(name, "").strip():
                raise DistributedSetupError(f"WORLD_SIZE={world} without {name}: start the ranks with torchrun, which "
                                            "sets it (or unset WORLD_SIZE to run one process)")
        port = os.environ["MASTER_PORT"].strip()
        if not port.isdigit() or not 0 < int(port) < 2**16:
            raise DistributedSetupError(f"MASTER_PORT={port!r}: must be a TCP port (1-65535)")
    return rank, world, local


def process_rank() -> int:
    """This process's torchrun rank (0 without torchrun, or when RANK is malformed: the checks of
    torchrun_env refuse that before anything runs; for the paths that report an error)."""
    try:
        return torchrun_env()[0]
    except DistributedSetupError:
        return 0


def process_world() -> int:
    """This process's torchrun world size (1 without torchrun, or when the variables are malformed, which
    torchrun_env refuses before anything runs; for the paths that decide how to refuse)."""
    try:
        return torchrun_env()[1]
    except DistributedSetupError:
        return 1


def rendezvous_timeout_s() -> float:
    """RENDEZVOUS_TIMEOUT_S, or `$BMIMIC_RENDEZVOUS_TIMEOUT_S` (seconds > 0)."""
    text = os.environ.get("BMIMIC_RENDEZVOUS_TIMEOUT_S")
    if text is None:
        return RENDEZVOUS_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        value = -1.0
    if not (value > 0 and value < 1e7):
        raise DistributedSetupError(f"BMIMIC_RENDEZVOUS_TIMEOUT_S={text!r}: must be a number of seconds > 0")
    return value


def init_distributed() -> tuple[int, int]:
    """(rank, world size); under torchrun, join the process group (NCCL on GPUs, gloo on a CPU-only
    machine) before any env is built. The ranks meet through bmimic.rendezvous: a stop signal is handled
    at once, and a rank whose peers do not come within rendezvous_timeout_s ends with one line of its own,
    without torch's C++ stack frames."""
    import torch

    rank, world, local = torchrun_env()
    if world <= 1:
        return 0, 1
    if not torch.distributed.is_initialized():
        timeout_s = rendezvous_timeout_s()
        if torch.cuda.is_available():
            if local >= torch.cuda.device_count():
                raise DistributedSetupError(f"LOCAL_RANK={local}: only {torch.cuda.device_count()} GPU(s) are visible")
            torch.cuda.set_device(local)
        store = meet(rank, world, timeout_s)
        # (CPU ranks use gloo: the same code path, for smoke tests without a GPU)
        torch.distributed.init_process_group("nccl" if torch.cuda.is_available() else "gloo", store=store,
                                             rank=rank, world_size=world)
    return torch.distributed.get_rank(), world


def any_rank(flag: bool, device: torch.device | str) -> bool:
    """`flag` on any rank: one scalar all-reduce under torchrun, so that every rank stops after the same
    iteration (ranks' clocks and signals differ; a rank that went on alone would wait forever)."""
    import torch

    if not (torch.distributed.is_available() and torch.distributed.is_initialized()
            and torch.distributed.get_world_size() > 1):
        return flag
    t = torch.tensor(float(flag), device=device)
    torch.distributed.all_reduce(t, op=torch.distributed.ReduceOp.MAX)
    return bool(t.item())


def gather_floats(value: float) -> list[float]:
    """`value` of every rank, in rank order: one float64 all-gather under torchrun (on the rank's GPU with
    NCCL), `[value]` in a single process."""
    import torch

    dist = torch.distributed
    if not (dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
        return [float(value)]
    device = f"cuda:{torch.cuda.current_device()}" if dist.get_backend() == "nccl" else "cpu"
    mine = torch.tensor([float(value)], dtype=torch.float64, device=device)
    every = [torch.empty_like(mine) for _ in range(dist.get_world_size())]
    dist.all_gather(every, mine)
    return [float(t.item()) for t in every]


def exit_rank(code: int) -> None:
    """End a torchrun rank whose work is written and whose process group is destroyed: flush and
    exit without the interpreter's teardown. C++ static destructors (gloo, Warp) run at a normal exit
    and once aborted a rank after destroy_process_group ("terminate called without an active
    exception", CI 2026-11-24, the multi-GPU bench), which torchrun reports as a failed run although
    everything was written. bench and train call it under torchrun only."""
    sys.stdout.flush()
    sys.stderr.flush()
    logging.shutdown()
    os._exit(code)


def available_memory_bytes() -> int | None:
    """The host's memory available to a new allocation (MemAvailable of /proc/meminfo); None when unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return None


# --------------------------------------------------------------------------------------------- seeding
def seed_everything(seed: int):
    """Seed python, numpy, torch and warp from one integer; return the generator the sampler uses."""
    import torch

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
    """All global RNG states, for checkpoints, as tensors and plain values only (so a checkpoint
    loads with `weights_only=True`)."""
    import torch

    version, mt, gauss = random.getstate()
    name, keys, pos, has_gauss, cached = np.random.get_state(legacy=True)
    state = {
        "python": {"version": int(version), "state": torch.tensor(mt, dtype=torch.int64), "gauss": gauss},
        "numpy": {"bit_generator": str(name), "keys": torch.from_numpy(np.asarray(keys, dtype=np.int64)),
                  "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "torch": torch.get_rng_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    """Restore `rng_state()`."""
    import torch

    py, npy = state["python"], state["numpy"]
    random.setstate((py["version"], tuple(int(x) for x in py["state"].tolist()), py["gauss"]))
    np.random.set_state((npy["bit_generator"], np.asarray(npy["keys"].tolist(), dtype=np.uint32), npy["pos"],
                         npy["has_gauss"], npy["cached_gaussian"]))
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


# --------------------------------------------------------------------------------------------- provenance
def _git(*args: str) -> str | None:
    try:
        out = subprocess.run(
            ["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=10, check=True
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


SOURCE_COMMIT_ENV = "BMIMIC_SOURCE_COMMIT"
"""The code's commit for a tree without git metadata (a copy shipped to a GPU machine, an unpacked
archive): set it to `git rev-parse HEAD` where the copy was made. Ignored where git answers."""

_COMMIT = re.compile(r"[0-9a-f]{7,40}")


def source_commit() -> tuple[str | None, bool | None]:
    """(commit, dirty) of the running code: from git where the tree has its metadata; else the commit
    in $BMIMIC_SOURCE_COMMIT with dirty unknown (None); else (None, None). A value that is not a hex
    commit is ignored with a warning naming the variable: provenance never stops a run."""
    commit = _git("rev-parse", "HEAD")
    if commit:
        return commit, bool(_git("status", "--porcelain", "--untracked-files=no"))
    given = os.environ.get(SOURCE_COMMIT_ENV, "").strip().lower()
    if not given:
        return None, None
    if not _COMMIT.fullmatch(given):
        log.warning("%s=%r is not a git commit (7-40 hex digits); provenance records none", SOURCE_COMMIT_ENV,
                    given)
        return None, None
    return given, None


def _version(module: str) -> str | None:
    try:
        from importlib.metadata import version

        return version(module)
    except Exception:
        return None


def provenance(device: str) -> dict:
    """What produced a run: code version, library versions, hardware, precision flags, command line."""
    import torch

    commit, dirty = source_commit()
    info: dict[str, Any] = {
        "created": now(),
        "git_commit": commit,
        "git_dirty": dirty,
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
