"""bmimic: Hydra-configured ablations of adaptive motion sampling for BeyondMimic-style tracking.

Importing it changes nothing (sys.path, the process, MuJoCo's GL backend): a command does what it
needs first, in bmimic.cli.startup. `python -m bmimic.<command>` imports this module before the command
takes the working directory off sys.path, so it imports nothing a planted module could shadow.
"""

TYPE_CHECKING = False
if TYPE_CHECKING:
    from pathlib import Path

__version__ = "0.1.0"


class BmimicError(Exception):
    """An error the user can fix (bad config, bad file); printed as one line, never a traceback."""


def __getattr__(name: str) -> "Path":
    """CONF_DIR: the Hydra config tree. In a checkout `bmimic/conf` links to the top-level conf/ (whose
    sweep/ links to sweeps/); a wheel carries copies of both, so every command works from any directory.
    Built on first use, as pathlib is not loaded yet when `python -m` imports this module."""
    if name == "CONF_DIR":
        from pathlib import Path

        return Path(__file__).resolve().parent / "conf"
    raise AttributeError(f"module 'bmimic' has no attribute {name!r}")
