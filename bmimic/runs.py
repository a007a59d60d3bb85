"""Run folders, provenance, status files, atomic writes, checkpoints on disk, device resolution, seeding.

Every file bmimic writes goes through `atomic_write` (a temp file in the same folder, fsynced, then
renamed over the target, then the folder fsynced), so an interrupted run never leaves a half-written
checkpoint, table or status file behind, and files get the permissions the umask asks for (0644 under
umask 022), so a team can read each other's runs. Checkpoints are read only with
`torch.load(weights_only=True)`: loading a shared checkpoint never runs code.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime as _dt
import fcntl
import json
import math
import os
import pickle
import platform
import random
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np

from bmimic import BmimicError

REPO_ROOT = Path(__file__).resolve().parents[1]


# --------------------------------------------------------------------------------------------- atomic I/O
def current_umask() -> int:
    """The process umask, read without changing it where Linux allows (os.umask is not thread-safe)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def _fsync_path(path: str | os.PathLike, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    try:
        fd = os.open(path, flags)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:  # some filesystems cannot fsync a folder; the rename is still atomic
        pass
    finally:
        os.close(fd)


def atomic_write(path: str | os.PathLike, write: Callable[[str], None]) -> Path:
    """Call `write(tmp_path)`, fsync, and rename the result onto `path`; the one writer of the project.

    The temp file `.<name>.tmp-<random><ext>` lies in the target's folder (so the rename is atomic) and
    ends in the target's own extension, so writers that pick a format by suffix (ffmpeg, np.savez,
    matplotlib) behave as for the real name. Its permissions are those a plain open() would give
    (0666 & ~umask), not mkstemp's 0600. On any failure the temp file is removed and the old file, if
    any, is left as it was.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.tmp-", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        os.chmod(tmp, 0o666 & ~current_umask())
        write(tmp)
        _fsync_path(tmp)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    _fsync_path(path.parent, directory=True)
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    def _w(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)

    return atomic_write(path, _w)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    return atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=True, default=str) + "\n")


def atomic_torch_save(path: str | os.PathLike, obj: Any) -> Path:
    import torch

    return atomic_write(path, lambda tmp: torch.save(obj, tmp))


def atomic_write_parquet(path: str | os.PathLike, df) -> Path:
    return atomic_write(path, lambda tmp: df.to_parquet(tmp, index=False))


@contextlib.contextmanager
def folder_lock(folder: str | os.PathLike) -> Iterator[None]:
    """Serialise read-modify-write of files in `folder` between processes (flock on the folder).

    Where the filesystem cannot lock a folder (some network filesystems) it goes on unlocked: the
    atomic rename still keeps every file whole.
    """
    fd = None
    try:
        fd = os.open(folder, os.O_RDONLY)
        fcntl.flock(fd, fcntl.LOCK_EX)
    except OSError:
        pass
    try:
        yield
    finally:
        if fd is not None:
            os.close(fd)  # closing drops the lock


def atomic_append_text(path: str | os.PathLike, text: str) -> Path:
    """Append `text` to a log file as one atomic replace, serialised against other appenders."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with folder_lock(path.parent):
        try:
            old = path.read_bytes()
        except FileNotFoundError:
            old = b""
        return atomic_write_bytes(path, old + text.encode("utf-8"))


def read_json(path: str | os.PathLike, default: Any = None) -> Any:
    try:
        with open(path) as f:
            return json.load(f)
    except (FileNotFoundError, json.JSONDecodeError, UnicodeDecodeError, IsADirectoryError):
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
    status = read_json(Path(run_dir) / "status.json", default=None)
    return status if isinstance(status, dict) else {"status": "missing"}


# --------------------------------------------------------------------------------------------- run lock
LOCK_NAME = ".bmimic.lock"


class RunLockedError(BmimicError):
    """Another live process is training in this run folder."""


def lock_run(run_dir: str | os.PathLike):
    """Take the exclusive lock of a run folder; returns the open lock file (the lock lives while it is
    open and dies with the process, so a killed run never leaves a stale lock), or None when another
    process holds it."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    f = open(run_dir / LOCK_NAME, "a")
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.close()
        return None
    except OSError:  # a filesystem without locks: cannot tell, so do not block the run
        return f
    return f


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
    """Restore `rng_state()`; also reads the pickled tuples of format-1 checkpoints."""
    import torch

    py, npy = state["python"], state["numpy"]
    if isinstance(py, dict):
        py = (py["version"], tuple(int(x) for x in py["state"].tolist()), py["gauss"])
    random.setstate(py)
    if isinstance(npy, dict):
        npy = (npy["bit_generator"], np.asarray(npy["keys"].tolist(), dtype=np.uint32), npy["pos"],
               npy["has_gauss"], npy["cached_gaussian"])
    np.random.set_state(npy)
    torch.set_rng_state(state["torch"].cpu())
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([s.cpu() for s in state["cuda"]])


# --------------------------------------------------------------------------------------------- checkpoints
CHECKPOINT_FORMAT = "bmimic-checkpoint-2"
"""Tensors and plain values only: readable with torch.load(weights_only=True)."""
LEGACY_CHECKPOINT_FORMATS = ("bmimic-checkpoint-1",)
"""Written by earlier bmimic versions with pickled numpy RNG states: they load only when trusted."""


class CheckpointError(BmimicError):
    """A checkpoint that cannot be read (missing, truncated, not a torch file)."""


class UnsafeCheckpointError(CheckpointError):
    """A checkpoint whose pickle names a global that could run code; refused unless trusted."""


def load_checkpoint_file(path: str | os.PathLike, map_location: str = "cpu", trust: bool = False) -> dict:
    """The checkpoint dict at `path`, read with `weights_only=True` (nothing in it can run code).

    `trust=True` (`--trust-checkpoint`, `trust_checkpoint=true`) falls back to a full unpickling for a
    file refused for its globals: only for checkpoints you wrote yourself, e.g. format-1 checkpoints
    of earlier bmimic versions. Raises CheckpointError / UnsafeCheckpointError with one line.
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
        try:
            state = torch.load(path, map_location=map_location, weights_only=False)
        except Exception as e2:  # noqa: BLE001 - any reader failure is "cannot read this file"
            raise CheckpointError(f"{path}: not a readable torch checkpoint ({_first_line(e2)})") from None
    except Exception as e:  # noqa: BLE001 - truncated zip, empty file, not a torch file, I/O error
        raise CheckpointError(f"{path}: not a readable torch checkpoint ({_first_line(e)})") from None
    if not isinstance(state, dict) or "actor_state_dict" not in state:
        raise CheckpointError(f"{path}: not an rsl-rl/bmimic checkpoint (no actor_state_dict)")
    return state


def _first_line(e: BaseException) -> str:
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(e)).strip()
    return text.splitlines()[0][:200] if text else type(e).__name__


def checkpoint_iteration(path: Path) -> int:
    """Iteration in a `model_<it>.pt` name (-1 for other names)."""
    m = re.fullmatch(r"model_(\d+)\.pt", path.name)
    return int(m.group(1)) if m else -1


def intact_checkpoints(ckpt_dir: Path) -> list[Path]:
    """latest.pt, then model_<it>.pt newest first: the order a resume tries them in."""
    found = sorted((p for p in ckpt_dir.glob("model_*.pt") if checkpoint_iteration(p) >= 0),
                   key=checkpoint_iteration, reverse=True) if ckpt_dir.is_dir() else []
    latest = ckpt_dir / "latest.pt"
    return ([latest] if latest.is_file() else []) + found


def load_newest_intact(ckpt_dir: Path, trust: bool = False) -> tuple[Path, dict, str]:
    """(path, state, note) of the newest checkpoint in `ckpt_dir` that reads; `note` says which
    damaged files were passed over. A checkpoint refused as unsafe is never passed over."""
    damaged = []
    for path in intact_checkpoints(ckpt_dir):
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


# --------------------------------------------------------------------------------------------- resume
RESUME_FREE_KEYS = ("resume", "resume_allow_changes", "trust_checkpoint", "device", "progress_bar", "logger",
                    "wandb_project", "max_iterations", "time_limit_s", "run_name", "sweep_name", "ppo.save_interval",
                    "eval.every_iters")
"""Keys a resume may change without naming them in resume_allow_changes: where and how long to run
and how to log, not what is trained. Changes are still recorded in resumes.json."""


def flatten_config(tree: Any, prefix: str = "") -> dict[str, Any]:
    """{'a.b.c': value} for every leaf of a nested dict (lists are leaves)."""
    if isinstance(tree, dict) and tree:
        out: dict[str, Any] = {}
        for key, value in tree.items():
            out.update(flatten_config(value, f"{prefix}{key}."))
        return out
    return {prefix[:-1]: tree} if prefix else {}


def config_changes(old: dict, new: dict) -> dict[str, tuple[Any, Any]]:
    """{key: (old, new)} for every leaf that differs (missing on one side counts as a change)."""
    a, b = flatten_config(old), flatten_config(new)
    missing = object()
    out = {}
    for key in sorted(set(a) | set(b)):
        x, y = a.get(key, missing), b.get(key, missing)
        if not _same_value(x, y):
            out[key] = (None if x is missing else x, None if y is missing else y)
    return out


def _same_value(x: Any, y: Any) -> bool:
    if isinstance(x, bool) or isinstance(y, bool):
        return x is y
    if isinstance(x, (int, float)) and isinstance(y, (int, float)):
        return x == y or (isinstance(x, float) and isinstance(y, float) and math.isnan(x) and math.isnan(y))
    return x == y


def refused_changes(changes: dict[str, tuple[Any, Any]], allowed: list[str] | tuple[str, ...]) -> list[str]:
    """Changed keys neither free nor named (or under a prefix named) in `allowed`."""
    return [k for k in changes if not key_allowed(k, (*RESUME_FREE_KEYS, *allowed))]


def key_allowed(key: str, allowed: list[str] | tuple[str, ...]) -> bool:
    """`key` is one of `allowed` or under one of them (`env` allows `env.rewards.x.weight`)."""
    return any(key == a or key.startswith(a + ".") for a in allowed)


class ResumeRefusedError(BmimicError):
    """A resume that would change, damage or mismatch the run it continues; nothing was written."""


def resume_request(resume: Any) -> str | None:
    """None (start fresh), "latest" (resume=true) or a path, from the `resume` config value."""
    if resume is None or resume is False or str(resume).strip().lower() in ("false", "none", "null", "no", "0", ""):
        return None
    if resume is True or str(resume).strip().lower() in ("true", "latest", "1", "yes"):
        return "latest"
    return str(resume)


def is_run_folder(path: Path) -> bool:
    return any((path / name).exists() for name in ("status.json", "resolved_config.json", ".hydra"))


@dataclasses.dataclass
class RunPlan:
    """Where a launch writes and what it continues from, decided before anything is written."""

    run_dir: Path
    """The folder this launch trains in."""
    launch_dir: Path
    """The folder Hydra made for this launch (run_dir, or removed when continuing another run)."""
    checkpoint: Path | None = None
    """The checkpoint loaded (None: a fresh run)."""
    state: dict | None = None
    """Its contents, read with weights_only unless trusted."""
    continues: bool = False
    """run_dir is an existing run that this launch continues (not a new folder)."""
    note: str = ""
    """What the planner had to do that the user must hear (e.g. passed over a damaged latest.pt)."""


def plan_run(resume: Any, launch_dir: Path, sweep_job: bool = False, trust: bool = False) -> RunPlan:
    """Decide where to train and from which checkpoint, reading but never writing.

    - no resume: a fresh run in launch_dir;
    - resume=true: a sweep job continues its own folder; a single run continues launch_dir when it
      already holds checkpoints (hydra.run.dir pinned), else the newest run of the same run_name
      (launch_dir's siblings); with none, a fresh run;
    - resume=RUN_FOLDER or a checkpoint in one: continues that run from its newest intact checkpoint;
      an older checkpoint of a run starts a new run in launch_dir from it (a branch), and so does a
      checkpoint outside any run folder.

    A damaged latest.pt is passed over for the newest intact model_<it>.pt (`note` says so); a
    checkpoint refused as unsafe never is. Raises ResumeRefusedError / CheckpointError (one line).
    """
    launch_dir = Path(launch_dir)
    request = resume_request(resume)
    if request is None:
        return RunPlan(launch_dir, launch_dir)
    if request == "latest":
        if sweep_job or intact_checkpoints(launch_dir / "checkpoints"):
            target = launch_dir
        else:
            parent = launch_dir.parent
            siblings = sorted((p for p in parent.iterdir() if p != launch_dir and p.is_dir()
                               and intact_checkpoints(p / "checkpoints")), key=lambda p: p.name) \
                if parent.is_dir() else []
            if not siblings:
                return RunPlan(launch_dir, launch_dir, note=f"resume=true: no run with a checkpoint under "
                                                             f"{parent}; starting a fresh run")
            target = siblings[-1]
        if not intact_checkpoints(target / "checkpoints"):
            return RunPlan(launch_dir, launch_dir)  # a sweep job that never reached a checkpoint
        path, state, note = load_newest_intact(target / "checkpoints", trust)
        return RunPlan(target, launch_dir, path, state, True, note)

    path = Path(request).expanduser()
    if not path.exists():
        raise ResumeRefusedError(f"resume: {path} does not exist")
    if path.is_dir():
        ckpt_dir = path / "checkpoints" if (path / "checkpoints").is_dir() else path
        run = ckpt_dir.parent if ckpt_dir.name == "checkpoints" else None
        checkpoint, state, note = load_newest_intact(ckpt_dir, trust)
    else:
        ckpt_dir = path.parent
        run = ckpt_dir.parent if ckpt_dir.name == "checkpoints" else None
        if path.name == "latest.pt":
            checkpoint, state, note = load_newest_intact(ckpt_dir, trust)
        else:
            checkpoint, state, note = path, load_checkpoint_file(path, "cpu", trust), ""
    if run is None or not is_run_folder(run):
        return RunPlan(launch_dir, launch_dir, checkpoint, state, False, note)
    run = run.resolve()
    newest = _newest_iteration(ckpt_dir)
    older = checkpoint.name != "latest.pt" and checkpoint_iteration(checkpoint) < newest
    if not older:
        return RunPlan(run, launch_dir, checkpoint, state, True, note)
    if launch_dir.resolve() == run:
        raise ResumeRefusedError(
            f"resume: {checkpoint.name} is older than {run}'s newest checkpoint (model_{newest}.pt); continuing "
            "that run from it would discard its later iterations; resume into a new folder instead")
    return RunPlan(launch_dir, launch_dir, checkpoint, state, False, note)


def _newest_iteration(ckpt_dir: Path) -> int:
    iterations = [checkpoint_iteration(p) for p in ckpt_dir.glob("model_*.pt")]
    return max(iterations, default=-1)


def previous_config(plan: RunPlan) -> dict | None:
    """The resolved config the checkpoint was trained with (stored in it from format 2 on; else the
    run folder's resolved_config.json)."""
    text = (plan.state or {}).get("config")
    if isinstance(text, str):
        try:
            cfg = json.loads(text)
        except ValueError:
            cfg = None
        if isinstance(cfg, dict):
            return cfg
    if plan.continues:
        cfg = read_json(plan.run_dir / "resolved_config.json")
        return cfg if isinstance(cfg, dict) else None
    return None


def check_resume_changes(plan: RunPlan, new_config: dict, allowed: list[str] | tuple[str, ...],
                         fill_defaults: Callable[[dict], dict] | None = None) -> dict:
    """{key: (old, new)} of the accepted config changes of a resume; ResumeRefusedError listing the
    keys that changed without being named in resume_allow_changes. `fill_defaults` gives the old
    config the schema's defaults for keys it predates (a newer bmimic's options are no change)."""
    old = previous_config(plan)
    if plan.state is None or old is None:
        return {}
    if fill_defaults is not None:
        old = fill_defaults(old)
    changes = config_changes(old, new_config)
    refused = refused_changes(changes, allowed)
    if refused:
        shown = ", ".join(f"{k} ({_short(changes[k][0])} -> {_short(changes[k][1])})" for k in refused[:8])
        more = f" and {len(refused) - 8} more" if len(refused) > 8 else ""
        raise ResumeRefusedError(
            f"resume: the config differs from the one {plan.checkpoint} was trained with: {shown}{more}; "
            f"to continue anyway, add resume_allow_changes=[{','.join(refused)}]")
    return changes


def _short(value: Any) -> str:
    text = json.dumps(value, default=str)
    return text if len(text) <= 40 else text[:37] + "..."


def discard_launch_dir(launch_dir: Path) -> bool:
    """Remove a launch folder holding nothing but Hydra's log and bmimic's lock (a launch that
    continued another run, or was refused); returns whether it was removed."""
    launch_dir = Path(launch_dir)
    try:
        entries = list(launch_dir.iterdir())
    except OSError:
        return False
    if any(not (p.is_file() and (p.suffix == ".log" or p.name == LOCK_NAME)) for p in entries):
        return False
    for p in entries:
        with contextlib.suppress(OSError):
            p.unlink()
    with contextlib.suppress(OSError):
        launch_dir.rmdir()
    # Folders Hydra made on the way (outputs/runs/<run_name>/) go too when now empty, up to the cwd.
    cwd = Path.cwd().resolve()
    parent = launch_dir.resolve().parent
    while parent != cwd and parent.is_relative_to(cwd):
        try:
            parent.rmdir()  # only succeeds when empty
        except OSError:
            break
        parent = parent.parent
    return not launch_dir.exists()


def move_file_logs(src_dir: Path, dst_dir: Path) -> None:
    """Point the logging file handlers writing into `src_dir` at the same file names in `dst_dir`
    (appended), carrying over what was logged so far: a resumed run logs into its own folder."""
    import logging

    src_dir, dst_dir = Path(src_dir).resolve(), Path(dst_dir)
    root = logging.getLogger()
    for handler in list(root.handlers):
        if not isinstance(handler, logging.FileHandler):
            continue
        old = Path(handler.baseFilename)
        if old.parent != src_dir:
            continue
        handler.flush()
        handler.close()
        root.removeHandler(handler)
        new = logging.FileHandler(dst_dir / old.name, mode="a", encoding=handler.encoding)
        new.setLevel(handler.level)
        new.setFormatter(handler.formatter)
        for f in handler.filters:
            new.addFilter(f)
        try:
            earlier = old.read_text()
        except OSError:
            earlier = ""
        if earlier:
            new.stream.write(earlier)
            new.flush()
        root.addHandler(new)


def record_resume(run_dir: str | os.PathLike, entry: dict) -> None:
    """Append one resume (checkpoint, iteration, accepted config changes, provenance) to resumes.json."""
    path = Path(run_dir) / "resumes.json"
    with folder_lock(path.parent):
        history = read_json(path, default=[])
        history = history if isinstance(history, list) else []
        atomic_write_json(path, [*history, {"time": _now(), **entry}])


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
    import torch

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
