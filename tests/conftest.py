"""Shared fixtures: composed configs, the repo root, the shared data folder."""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CONF = REPO / "conf"
SHARED_MOTIONS = Path(os.environ.get("BMIMIC_LAFAN_DIR") or REPO.parent / "shared" / "motions")
"""LAFAN1 G1 clips (not shipped: CC BY-NC-ND): $BMIMIC_LAFAN_DIR, else the development machine's copy of
three; tests using them skip without them."""
if SHARED_MOTIONS.is_dir():  # data.lafan_dir defaults to $BMIMIC_LAFAN_DIR; subprocesses inherit it
    os.environ.setdefault("BMIMIC_LAFAN_DIR", str(SHARED_MOTIONS))
if int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1")) > 1:
    # pytest-xdist (`-n auto` in pyproject) already keeps every core busy with one worker each: a worker's
    # torch, and the CLIs it starts, oversubscribe the cores with more than one thread each.
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    os.environ.setdefault("MKL_NUM_THREADS", "1")

MAX_WORKERS = 4
"""Workers for `-n auto`: each imports torch, Warp and MuJoCo (~1 GB); beyond 4 the suite is bound by
its longest tests."""


def pytest_xdist_auto_num_workers(config) -> int:
    return max(1, min(MAX_WORKERS, os.cpu_count() or 1))

# Tiny sizes for end-to-end runs of the real command line on a CPU.
TINY = [
    "device=cpu", "num_envs=2", "max_iterations=2", "ppo.num_steps_per_env=8", "ppo.num_mini_batches=2",
    "motion=easy_only", "eval.horizon_s=0.2", "progress_bar=false",
]


def compose(overrides: list[str] | None = None, return_hydra_config: bool = False):
    """Compose conf/train.yaml with overrides, the way the CLI does."""
    from hydra import compose as _compose
    from hydra import initialize_config_dir

    import bmimic.config  # noqa: F401  (registers the schemas)

    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return _compose("train", overrides=overrides or [], return_hydra_config=return_hydra_config)


@pytest.fixture
def cfg():
    return compose()


def run_module_as_main(name: str) -> None:
    """`python -m NAME` in this process. A module that an earlier test imported is set aside for the run
    and put back after it: runpy would otherwise warn that it found it in sys.modules (the run is a fresh
    `__main__` either way)."""
    import runpy
    import sys

    imported = sys.modules.pop(name, None)
    try:
        runpy.run_module(name, run_name="__main__")
    finally:
        if imported is not None:
            sys.modules[name] = imported


def run_train(*args: str, cwd: Path | None = None, env: dict | None = None) -> tuple[int, str]:
    """`python -m bmimic.train ARGS` in this process (the real Hydra app, without a new interpreter's
    start-up): its exit status and everything it printed. `env` sets (value None: removes) variables
    for the run; the working directory, sys.argv and the environment are restored after it."""
    import contextlib
    import io
    import sys

    saved = sys.argv, os.getcwd(), {k: os.environ.get(k) for k in (env or {})}
    out = io.StringIO()
    try:
        for key, value in (env or {}).items():
            os.environ.pop(key, None) if value is None else os.environ.__setitem__(key, value)
        if cwd is not None:
            os.chdir(cwd)
        sys.argv = ["bmimic.train", *args]
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
            try:
                run_module_as_main("bmimic.train")
                code = 0
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    finally:
        sys.argv = saved[0]
        os.chdir(saved[1])
        for key, value in saved[2].items():
            os.environ.pop(key, None) if value is None else os.environ.__setitem__(key, value)
    return code, out.getvalue()


def train_in_process(run_dir: Path, *overrides: str, cwd: Path | None = None) -> Path:
    """A tiny training run in `run_dir` (hydra.run.dir), in this process; fails the test when it fails."""
    code, out = run_train(*overrides, f"hydra.run.dir={run_dir}", cwd=cwd)
    if code != 0:
        pytest.fail(f"bmimic.train {' '.join(overrides)} exited {code}:\n{out[-3000:]}")
    return run_dir
def free_port() -> int:
    """A TCP port on localhost that nothing listens on now (for a process group's rendezvous)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


RANKS_GROUP = pytest.mark.xdist_group("ranks")
"""Tests that start several ranks (torch.multiprocessing, torchrun) run one after another on one
pytest-xdist worker (`--dist loadgroup`): side by side on a 2-core machine, two of them
(4+ processes, each with gloo's threads) lost a rank to SIGABRT twice in CI."""


def _rank_entry(rank: int, fn, world: int, folder: str, backend: str, args: tuple) -> None:
    # Each rank's output to its own file, so a rank that dies says why in the test's failure.
    log = os.open(os.path.join(folder, f"rank{rank}.log"), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(log, 1)
    os.dup2(log, 2)
    import torch.distributed as dist

    # A file store: no TCP port to pick, so nothing else on the machine can take it first.
    dist.init_process_group(backend, init_method=f"file://{os.path.join(folder, 'store')}", rank=rank,
                            world_size=world)
    try:
        fn(rank, *args)
    finally:
        dist.destroy_process_group()


def spawn_ranks(fn, args: tuple, world: int, folder: Path, backend: str = "gloo") -> None:
    """`fn(rank, *args)` on `world` processes in one process group; each rank's output in
    folder/rank<r>.log, whose tail a failure shows."""
    import torch.multiprocessing as mp

    try:
        mp.spawn(_rank_entry, args=(fn, world, str(folder), backend, args), nprocs=world, join=True)
    except Exception as e:
        logs = "\n".join(f"--- rank {r}:\n" + (folder / f"rank{r}.log").read_text(errors="replace")[-3000:]
                         for r in range(world) if (folder / f"rank{r}.log").exists())
        raise AssertionError(f"{e}\n{logs}") from e


def cli_env() -> dict:
    env = dict(os.environ)
    env.setdefault("PYTHONUNBUFFERED", "1")
    return env


def wait_for(proc, ready, what: str, timeout_s: float = 600) -> None:
    """Poll `ready()` while the subprocess `proc` runs (a file not written yet, or half-written JSON,
    counts as not ready); fail the test with `what` if it never holds."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if ready():
                return
        except (FileNotFoundError, json.JSONDecodeError):
            pass
        time.sleep(0.05)
    pytest.fail(f"never reached: {what}")


@pytest.fixture(scope="session")
def gl_backend() -> str:
    """A GL backend that can render offscreen here (checked in a subprocess), else skip."""
    from bmimic import render

    chosen = os.environ.get("MUJOCO_GL")
    candidates = [chosen] if chosen else list(render.GL_BACKENDS)
    reasons = []
    for backend in candidates:
        why = render.probe_gl_backend(backend)
        if why is None:
            return backend
        reasons.append(f"{backend}: {why}")
    pytest.skip("no offscreen OpenGL backend (" + "; ".join(reasons) + ")")


@pytest.fixture(autouse=True)
def _no_hydra_state_between_tests():
    """Tests that run a Hydra app in-process leave Hydra's singletons set (HydraConfig keeps the last
    run's original working directory, which bmimic's relative paths are resolved against); clear
    them after every test so each test sees a fresh process's state."""
    yield
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.hydra_config import HydraConfig

    HydraConfig.instance().cfg = None
    GlobalHydra.instance().clear()


# ------------------------------------------------------------------------------------ the quick tier
DURATIONS = Path(__file__).with_name("durations.json")
"""{test id: seconds of setup + call} as last recorded with `pytest --record-durations` on the 2-core
development machine (tests under 0.5 s are left out)."""

QUICK_LIMIT_S = 2.0
"""A test recorded at this many seconds or more is marked slow, so `pytest -m "not slow"` (the quick
tier) keeps the many fast checks and leaves the cold command-line runs and long simulations to the
full suite, which runs everything."""

_recorded: dict[str, float] = {}


def pytest_addoption(parser) -> None:
    parser.addoption("--record-durations", action="store_true",
                     help="update tests/durations.json (the quick tier's source) with this session's times")


def pytest_collection_modifyitems(config, items) -> None:
    recorded = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}
    for item in items:
        if recorded.get(item.nodeid, 0.0) >= QUICK_LIMIT_S:
            item.add_marker(pytest.mark.slow)
    # Longest first, so that no long test starts last and leaves the other workers idle at the end of the
    # run: files in the order of their longest recorded test, each file's tests kept together and in
    # their own order (a file's module fixtures are made once per worker, not again after another file).
    longest: dict[Path, float] = {}
    for item in items:
        longest[item.path] = max(longest.get(item.path, 0.0), recorded.get(item.nodeid, 0.0))
    order = {id(item): i for i, item in enumerate(items)}
    items.sort(key=lambda item: (-longest[item.path], str(item.path), order[id(item)]))


def pytest_runtest_logreport(report) -> None:
    if report.when in ("setup", "call"):
        _recorded[report.nodeid] = _recorded.get(report.nodeid, 0.0) + report.duration


def pytest_sessionfinish(session) -> None:
    # The controller (not an xdist worker) writes: it receives every worker's reports.
    if not session.config.getoption("--record-durations") or hasattr(session.config, "workerinput"):
        return
    merged = json.loads(DURATIONS.read_text()) if DURATIONS.is_file() else {}
    merged.update({k: round(v, 1) for k, v in _recorded.items()})
    kept = {k: v for k, v in sorted(merged.items()) if v >= 0.5}
    tmp = DURATIONS.with_suffix(".tmp")
    tmp.write_text(json.dumps(kept, indent=0) + "\n")
    os.replace(tmp, DURATIONS)
