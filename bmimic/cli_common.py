"""What every command line shares: which errors are the user's (one line, exit status 2) and the
--trust-checkpoint flag."""

from __future__ import annotations

import argparse


def first_line(e: BaseException) -> str:
    """The first line of an error's message (its type's name when it has none)."""
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean bad input (printed as one line, exit status 2)."""
    from bmimic import BmimicError
    from bmimic.motion.segments import MotionDataError

    return (BmimicError, MotionDataError)


def add_trust_flag(p: argparse.ArgumentParser) -> None:
    """Add --trust-checkpoint to a command's parser."""
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="also read bmimic checkpoint format 1 (pickled numpy RNG state), still weights-only: "
                        "numpy arrays are admitted, any other global is refused")

