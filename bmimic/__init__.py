"""bmimic: Hydra-configured ablations of adaptive motion sampling for BeyondMimic-style tracking."""

import os
import sys


def _drop_working_directory() -> None:
    """`python -m` puts the working directory first on sys.path, so a run folder (or any folder) holding
    a planted `yaml.py` or `numpy.py` would be imported, and run, by the command reading it. Every
    bmimic command runs without it, as the console scripts (`bmimic-train`, ...) always do; in a
    checkout's root, where bmimic itself lives, it stays. Runs before any other import of the package."""
    if sys.argv[:1] != ["-m"] or not sys.path:
        return
    cwd = os.path.realpath(os.getcwd())
    if os.path.realpath(sys.path[0] or ".") != cwd:
        return
    if os.path.realpath(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))) == cwd:
        return
    # Every entry that is the working directory: an empty PYTHONPATH entry ("a:" or ":a") adds it again.
    sys.path[:] = [p for p in sys.path if os.path.realpath(p or ".") != cwd]


_drop_working_directory()

from pathlib import Path  # noqa: E402  (after the working directory left sys.path)

from bmimic.console import exit_if_mujoco_gl_is_broken  # noqa: E402

__version__ = "0.1.0"

CONF_DIR = Path(__file__).resolve().parent / "conf"
"""The Hydra config tree. In a checkout `bmimic/conf` links to the top-level conf/ (whose sweep/ links
to sweeps/); a wheel carries copies of both, so every command works from any directory."""


class BmimicError(Exception):
    """An error the user can fix (bad config, bad file); printed as one line, never a traceback."""


exit_if_mujoco_gl_is_broken()
