"""GPU slots for parallel sweep jobs on one machine (`hydra/launcher=joblib_gpus`).

Jobs run in joblib's worker processes, which are reused from job to job. A CUDA context binds a
process to the GPUs visible when it was created, so each worker claims one GPU slot the first time
it runs a job, keeps it for its lifetime, and makes only that slot's GPU visible before torch or warp
touch CUDA. Slots are claimed with file locks, so two workers never hold the same slot even when
jobs finish out of order; slot k uses GPU k mod (number of GPUs), so n_jobs = 2 x GPUs puts two jobs
on every GPU. Importing this module registers the `bmimic.gpu_slots` resolver the launcher config uses.
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Mapping, Sequence

from omegaconf import OmegaConf

from bmimic import BmimicError

log = logging.getLogger("bmimic.launch")


def parse_visible_devices(value: str) -> list[str]:
    """Device ids in a CUDA_VISIBLE_DEVICES value, as CUDA reads it (stops at an empty or negative entry)."""
    devices = []
    for item in value.split(","):
        item = item.strip()
        if not item or item.startswith("-"):
            break
        devices.append(item)
    return devices


class VisibleDevicesError(BmimicError, ValueError):
    """A CUDA_VISIBLE_DEVICES value under which CUDA would see no GPU although GPUs are named."""


def check_visible_devices(environ: Mapping[str, str] | None = None) -> None:
    """Refuse a CUDA_VISIBLE_DEVICES that names one GPU twice: CUDA then sees no GPU at all, so
    `device=auto` falls back to the CPU and a GPU sweep is refused as hours of CPU training (seen with
    `3,0,1,2,3` meant as "more jobs on GPU 3"). Several jobs per GPU are `hydra.launcher.n_jobs`."""
    environ = os.environ if environ is None else environ
    value = environ.get("CUDA_VISIBLE_DEVICES")
    if value is None:
        return
    seen: set[str] = set()
    for device in parse_visible_devices(value):
        if device in seen:
            raise VisibleDevicesError(
                f"CUDA_VISIBLE_DEVICES={value}: names GPU {device} twice, and CUDA then sees no GPU at all; "
                "name each GPU once (hydra/launcher=joblib_gpus hydra.launcher.n_jobs=N runs several jobs per GPU)")
        seen.add(device)


def visible_gpus(environ: dict[str, str] | None = None) -> list[str]:
    """GPUs this process may use, without initialising CUDA: CUDA_VISIBLE_DEVICES, else nvidia-smi."""
    env = os.environ if environ is None else environ
    if "CUDA_VISIBLE_DEVICES" in env:
        return parse_visible_devices(env["CUDA_VISIBLE_DEVICES"])
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=index", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=30, check=True)
    except (OSError, subprocess.SubprocessError):
        return []
    return [line.strip() for line in out.stdout.splitlines() if line.strip()]


def gpu_slots(jobs_per_gpu: int = 1) -> int:
    """Concurrent jobs for `jobs_per_gpu` jobs on each visible GPU (at least 1: CPU-only machines)."""
    if int(jobs_per_gpu) < 1:
        raise ValueError(f"jobs_per_gpu must be >= 1, got {jobs_per_gpu}")
    return max(1, len(visible_gpus()) * int(jobs_per_gpu))


if not OmegaConf.has_resolver("bmimic.gpu_slots"):
    OmegaConf.register_new_resolver("bmimic.gpu_slots", gpu_slots)


def slot_order(job_num: int, num_slots: int) -> list[int]:
    """Slots in the order a job tries them: its own `job_num % num_slots` first, then the next ones."""
    if num_slots < 1:
        raise ValueError(f"num_slots must be >= 1, got {num_slots}")
    first = job_num % num_slots
    return [(first + i) % num_slots for i in range(num_slots)]


def slot_gpu(slot: int, gpus: Sequence[str]) -> str:
    """The GPU of a slot: round robin, so the first len(gpus) slots cover every GPU once."""
    if not gpus:
        raise ValueError("no GPUs to assign")
    return gpus[slot % len(gpus)]


def claim_slot(lock_dir: Path, job_num: int, num_slots: int) -> tuple[int, Any] | None:
    """Lock the first free slot in `slot_order`; (slot, open lock file) or None when all are taken.

    The lock lives as long as the returned file stays open (the process's lifetime for a worker);
    the OS drops it when the process dies, so a crashed worker never leaks its slot.
    """
    lock_dir.mkdir(parents=True, exist_ok=True)
    for slot in slot_order(job_num, num_slots):
        f = open(lock_dir / f"slot_{slot}.lock", "a")
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            f.close()
            continue
        return slot, f
    return None


_claimed: dict[str, Any] = {}  # this process's slot: {"slot", "gpu", "lock"}; set once per process


def pin_job_to_gpu() -> str | None:
    """In a joblib worker, make one GPU visible to this process; returns it (None: nothing pinned).

    Call at the start of the job, before anything initialises CUDA. Only the joblib launchers pin:
    the basic launcher runs jobs one after another in the launching process, and SLURM gives each
    submitit job its own GPUs.
    """
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    if "joblib" not in str(hc.launcher.get("_target_", "")):
        return None
    if _claimed:  # a reused worker: its CUDA context (if any) is bound to the GPU pinned first
        log.info("GPU slot %d: CUDA_VISIBLE_DEVICES=%s (held by worker pid %d since its first job)",
                 _claimed["slot"], _claimed["gpu"], os.getpid())
        return _claimed["gpu"]
    gpus = visible_gpus()
    if not gpus:
        return None
    from joblib import effective_n_jobs

    num_slots = max(1, effective_n_jobs(int(hc.launcher.n_jobs)))
    key = hashlib.sha1(str(Path(str(hc.sweep.dir)).resolve()).encode()).hexdigest()[:16]
    lock_dir = Path(tempfile.gettempdir()) / "bmimic-gpu-slots" / key
    claim = claim_slot(lock_dir, int(hc.job.num), num_slots)
    if claim is None:  # more live workers than n_jobs: should not happen; share rather than stall
        slot, lock = int(hc.job.num) % num_slots, None
        log.warning("all %d GPU slots are held; job %d shares slot %d", num_slots, hc.job.num, slot)
    else:
        slot, lock = claim
    gpu = slot_gpu(slot, gpus)
    if "torch" in sys.modules and sys.modules["torch"].cuda.is_initialized():
        log.warning("CUDA was initialised before the GPU slot was chosen; CUDA_VISIBLE_DEVICES=%s "
                    "may not take effect in this process", gpu)
    os.environ["CUDA_VISIBLE_DEVICES"] = gpu
    _claimed.update(slot=slot, gpu=gpu, lock=lock)
    log.info("GPU slot %d of %d: CUDA_VISIBLE_DEVICES=%s (worker pid %d)", slot, num_slots, gpu, os.getpid())
    return gpu
