"""What a command runs before it imports anything else: `start_command(__spec__.name)` is the first
statement of every entry point (`python -m` module and console-script target).

- Under `python -m`, the working directory is sys.path[0], ahead of the standard library and
  site-packages, so a run folder (or any folder) holding a planted `yaml.py`, `typing.py` or
  `numpy.py` would be imported, and run, by the command reading it. The command takes it off sys.path
  first, as the console scripts (`bmimic-train`, ...) never have it; in a checkout's root, where bmimic
  itself lives, it stays.
- MuJoCo binds the OpenGL backend named by MUJOCO_GL when it is first imported and, when that
  backend's library is missing, fails deep inside PyOpenGL; a command tries it once, here, and exits
  with one line instead of a traceback later.

Only commands do this: importing bmimic, or a library module of it, changes nothing. This module
imports only what the interpreter has loaded before `python -m` runs any code (os, sys), so that it
cannot itself be shadowed; the packages a `python -m` entry point lives in (bmimic, bmimic.motion,
bmimic.sim2sim, analysis) import nothing else before it runs, or call `leave_working_directory` first.
"""

import os
import sys
import time  # built into the interpreter: no file can shadow it

STARTED_S = time.monotonic()
"""When this process imported its first bmimic module, as near to the command's start as a module sees
(a run's done line gives the whole command's wall time from it, not training alone)."""


def command_wall_s() -> float:
    """Seconds since this process started its command (STARTED_S)."""
    return time.monotonic() - STARTED_S


def python_m_module() -> str | None:
    """The module this process was started to run with `python -m` (read from sys.orig_argv), else None."""
    args = list(sys.orig_argv[1:])
    while args:
        arg = args.pop(0)
        if arg == "--check-hash-based-pycs":  # the one long option with a separate value
            del args[:1]
            continue
        if not arg.startswith("-") or arg in ("-", "--"):
            return None  # a script file or stdin: no module
        if arg.startswith("--"):
            continue
        for i, flag in enumerate(arg[1:], 1):  # a cluster of short options: `-Im mod`, `-mmod`
            if flag in "mcWX":  # the options that take a value (the rest of the cluster, else the next one)
                value = arg[i + 1:] or (args.pop(0) if args else "")
                if flag == "c":
                    return None
                if flag == "m":
                    return value or None
                break
    return None


def checkout_root() -> str:
    """The folder that holds the bmimic package (this file is bmimic/cli/startup.py): a checkout's root."""
    return os.path.realpath(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def leave_working_directory(module: str) -> None:
    """Take the working directory off sys.path when this process is `python -m <module>` (or a module
    inside it), unless the working directory is the checkout that holds bmimic."""
    target = python_m_module()
    if target is None or not (target == module or target.startswith(module + ".")) or not sys.path:
        return
    cwd = os.path.realpath(os.getcwd())
    if os.path.realpath(sys.path[0] or ".") != cwd:
        return
    if checkout_root() == cwd:
        return
    # Every entry that is the working directory: an empty PYTHONPATH entry ("a:" or ":a") adds it again.
    sys.path[:] = [p for p in sys.path if os.path.realpath(p or ".") != cwd]


def start_command(module: str) -> None:
    """What the command `module` (its `__spec__.name`) runs first: the working directory off sys.path
    under `python -m`, then the MUJOCO_GL check (exit status 2 with one line when it is broken)."""
    leave_working_directory(module)
    from bmimic.cli.console import exit_if_mujoco_gl_is_broken  # after: it imports logging, tempfile, ...

    exit_if_mujoco_gl_is_broken()
