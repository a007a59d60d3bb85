"""What bmimic's commands print: quiet by default, one start-up summary, one line per problem.

Warp logs every kernel module it loads and rsl-rl prints its observation sets and models while its
runner is built; both stay off unless `verbose=true`, so a run shows its start-up summary, then the
progress bar. Console log lines are the bare message (warnings and errors say so); the run folder's
train.log keeps timestamps.

Every command imports this module first (bmimic.cli.startup), so it imports nothing heavy at module level.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import sys
import tempfile
from typing import Iterator, Sequence

_GL_INSTALL = {
    "osmesa": "OSMesa (Debian/Ubuntu: apt install libosmesa6)",
    "egl": "EGL (Debian/Ubuntu: apt install libegl1)",
    "glx": "OpenGL/GLX and a display (Debian/Ubuntu: apt install libgl1)",
    "glfw": "GLFW and a display (Debian/Ubuntu: apt install libglfw3)",
}
"""What each MuJoCo OpenGL backend needs installed."""

_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"
"""Warp's native warning on machines without an NVIDIA driver (the summary names the device instead)."""


# --------------------------------------------------------------------------------------------- OpenGL
def mujoco_gl_problem() -> str | None:
    """None when `import mujoco` works under the current MUJOCO_GL, else one line saying what to do."""
    gl = os.environ.get("MUJOCO_GL", "").strip()
    try:
        import mujoco  # noqa: F401  (binds the backend named by MUJOCO_GL)
    except ModuleNotFoundError as e:
        if e.name == "mujoco":
            raise
        why = f"{type(e).__name__}: {e}"
    except Exception as e:  # PyOpenGL fails with AttributeError/ImportError, mujoco with RuntimeError
        why = f"{type(e).__name__}: {str(e).strip().splitlines()[0] if str(e).strip() else ''}"
    else:
        return None
    need = _GL_INSTALL.get(gl.lower())
    if need is None:
        return (f"MUJOCO_GL={gl}: not an OpenGL backend MuJoCo can use ({why}); set MUJOCO_GL=egl or osmesa "
                "for offscreen rendering, or unset it (only rendering needs it)")
    return (f"MUJOCO_GL={gl}: MuJoCo cannot load this OpenGL backend ({why}); install {need}, "
            "choose another one (MUJOCO_GL=egl or osmesa), or unset MUJOCO_GL (only rendering needs it)")


def exit_if_mujoco_gl_is_broken() -> None:
    """Exit with one line when MUJOCO_GL names a backend whose library is missing.

    MuJoCo binds the backend named by MUJOCO_GL when it is first imported and, when that backend's
    library is missing, fails deep inside PyOpenGL. Every bmimic command imports mujoco, so when
    MUJOCO_GL is set it is tried once, here, instead of failing with a traceback later.
    """
    if not os.environ.get("MUJOCO_GL", "").strip() or "mujoco" in sys.modules:
        return
    problem = mujoco_gl_problem()
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        raise SystemExit(2)


# --------------------------------------------------------------------------------------------- quiet
def quiet_warp(verbose: bool = False) -> None:
    """Warp at warning level (no start-up banner, no per-module "load" lines) unless `verbose`.

    Also initialises Warp, so that its native "no NVIDIA driver" warning on a CPU-only machine can be
    dropped (it is written by C code straight to the stderr file descriptor); anything else Warp
    writes there while starting is passed on.
    """
    import warp as wp

    if verbose:
        return
    wp.config.quiet = True  # type: ignore[attr-defined]  # older Warp releases; current ones read log_level only
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    with _native_stderr_filtered(_NO_DRIVER):
        wp.init()


@contextlib.contextmanager
def _native_stderr_filtered(drop: str) -> Iterator[None]:
    """Capture what native code writes to file descriptor 2; re-emit every line not containing `drop`."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # a replaced sys.stderr (pytest capture): leave it alone
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    with tempfile.TemporaryFile(mode="w+b") as capture:
        os.dup2(capture.fileno(), fd)
        try:
            yield
        finally:
            os.dup2(saved, fd)
            os.close(saved)
            capture.seek(0)
            kept = [line for line in capture.read().decode(errors="replace").splitlines(keepends=True)
                    if drop not in line]
            if kept:
                sys.stderr.write("".join(kept))
                sys.stderr.flush()


@contextlib.contextmanager
def quiet_stdout(verbose: bool = False) -> Iterator[None]:
    """Drop what Python code prints to stdout inside the block, unless `verbose` (rsl-rl prints its
    observation sets and models while its runner is built)."""
    if verbose:
        yield
        return
    with contextlib.redirect_stdout(io.StringIO()):
        yield


# --------------------------------------------------------------------------------------------- output
class ConsoleFormatter(logging.Formatter):
    """Console log lines: the message alone; warnings and errors are prefixed `warning:` / `error:`.

    Used by conf/train.yaml's `hydra.job_logging` for the console; the file log keeps timestamps.
    """

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        if record.levelno >= logging.ERROR:
            return f"error: {text}"
        if record.levelno >= logging.WARNING:
            return f"warning: {text}"
        return text


def summary_block(title: str, rows: Sequence[tuple[str, str]]) -> str:
    """`title` then one aligned `name  value` line per row."""
    width = max((len(name) for name, _ in rows), default=0)
    return "\n".join([title, *(f"  {name:<{width}}  {value}" for name, value in rows)])


def start_summary(cfg, requested_device: str, world: int, smoke: bool, motion, layout, run_dir) -> str:
    """A training's start-up block: device, envs, motion, bins, sampler variant and run folder."""
    from hydra.core.hydra_config import HydraConfig

    choices = HydraConfig.get().runtime.choices if HydraConfig.initialized() else {}
    m = cfg.motion
    names = getattr(layout, "clip_names", ())
    library = f"library of {len(names)} clips ({', '.join(names[:4])}{', ...' if len(names) > 4 else ''})"
    source = {"builtin": f"built-in {m.builtin}", "lafan": f"LAFAN1 {m.clip}",
              "library": library}.get(m.source, str(m.path))
    if m.start_s is not None or m.end_s is not None:
        source += f", {m.start_s or 0:g}-{'end' if m.end_s is None else format(m.end_s, 'g')} s"
    variant = choices.get("sampler") or cfg.sampler.name
    ranks = f" per rank, {world} ranks" if world > 1 else ""
    title = ("no GPU: this is a smoke-scale run through the whole pipeline; on a GPU the same command "
             "trains for real" if smoke else "training")
    # the silence until the first iteration is the simulator's build: say so before it starts
    building = ("building the simulator and the policy (its kernels compile on a machine's first run and are "
                "cached; a GPU also captures its graphs) ...")
    return summary_block(title, [
        ("device", f"{cfg.device} (requested {requested_device})"),
        ("envs", f"{cfg.num_envs}{ranks}"),
        ("iterations", f"{cfg.max_iterations} of {cfg.ppo.num_steps_per_env} steps per env"
                       + (f", pausing after {cfg.stop_at_iteration}" if cfg.stop_at_iteration else "")),
        ("motion", f"{choices.get('motion') or m.name}: {source}; {motion.duration_s:.1f} s at {motion.fps:g} Hz"),
        ("bins", layout.describe()),
        ("sampler", variant if variant == cfg.sampler.name else f"{variant} ({cfg.sampler.name})"),
        ("run folder", str(run_dir)),
    ]) + "\n" + building
