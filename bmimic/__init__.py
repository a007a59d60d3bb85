"""bmimic: Hydra-configured ablations of adaptive motion sampling for BeyondMimic-style tracking."""

__version__ = "0.1.0"


class BmimicError(Exception):
    """An error the user can fix (bad config, bad file); printed as one line, never a traceback."""
