"""bmimic: Hydra-configured ablations of adaptive motion sampling for BeyondMimic-style tracking."""

from pathlib import Path

from bmimic.console import exit_if_mujoco_gl_is_broken

__version__ = "0.1.0"

CONF_DIR = Path(__file__).resolve().parent / "conf"
"""The Hydra config tree. In a checkout `bmimic/conf` links to the top-level conf/ (whose sweep/ links
to sweeps/); a wheel carries copies of both, so every command works from any directory."""


class BmimicError(Exception):
    """An error the user can fix (bad config, bad file); printed as one line, never a traceback."""


exit_if_mujoco_gl_is_broken()
