"""What every command line shares: which errors are the user's (one line, exit status 2), the
--trust-checkpoint flag, the check of a path argument or of a file a command is told to write, and how
a printed command quotes its arguments so that it pastes back."""

from __future__ import annotations

import argparse
import os
import re
import shlex
from pathlib import Path


def first_line(e: BaseException) -> str:
    """The first line of an error's message (its type's name when it has none)."""
    text = str(e).strip()
    return text.splitlines()[0] if text else type(e).__name__


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that mean bad input (printed as one line, exit status 2)."""
    from bmimic import BmimicError

    return (BmimicError,)  # MotionDataError, ... are BmimicErrors


def add_trust_flag(p: argparse.ArgumentParser) -> None:
    """Add --trust-checkpoint to a command's parser."""
    p.add_argument("--trust-checkpoint", action="store_true",
                   help="trust the run folder: load a run config whose env terms import modules outside "
                        "bmimic (their code runs); the checkpoint itself is read weights-only either way")


def check_output_file(flag: str, path: str | os.PathLike) -> Path:
    """A file a command is told to write (`--json PATH`): a file name in a folder that exists, not a
    folder itself; raises BmimicError (one line naming `flag`), so that a typo never creates folders."""
    from bmimic import BmimicError

    out = Path(path)
    try:
        bad = not str(path) or "\0" in str(path) or out.is_dir() or not out.parent.is_dir()
    except OSError:  # a name too long for the filesystem
        bad = True
    if bad:
        raise BmimicError(f"{flag} {path}: must name a file in an existing folder")
    return out


def path_arg(text: str) -> Path:
    """argparse `type=` of a path argument: refuses, as argparse's one-line usage error, a path no file
    can have (empty, a name longer than the filesystem allows, a loop of links), which the commands'
    checks would otherwise meet as an OSError (a traceback) or as the working directory ('')."""
    import errno

    if not text:
        raise argparse.ArgumentTypeError("an empty path (an unset shell variable?)")
    try:
        os.stat(text)
    except OSError as e:
        if e.errno in (errno.ENAMETOOLONG, errno.ELOOP, errno.EILSEQ):
            raise argparse.ArgumentTypeError(f"{text[:60]}{'...' if len(text) > 60 else ''}: {e.strerror}") from None
    except ValueError as e:  # an embedded NUL byte (not possible from a shell, from another program)
        raise argparse.ArgumentTypeError(f"{text[:60]!r}: {e}") from None
    return Path(text)


def shell_arg(value: str | os.PathLike) -> str:
    """`value` as one shell word (quoted only when it must be: a folder with a space, `$`, `;`...)."""
    return shlex.quote(str(value))


_PLAIN_OVERRIDE_VALUE = re.compile(r"[\w./:+-]+")
"""Characters Hydra's override grammar reads as a plain value (no `=`, `,`, spaces, quotes, brackets)."""


def override_arg(key: str, value: str | os.PathLike) -> str:
    """`key=value` as one shell word Hydra reads back as that value: a path holding `=` or `,` (a sweep
    job's folder) or a space is quoted for Hydra too (`resume='outputs/sweeps/s/a=1,b=2/seed=0'`)."""
    text = str(value)
    if _PLAIN_OVERRIDE_VALUE.fullmatch(text):
        return shell_arg(f"{key}={text}")
    word = f"{key}='" + text.replace("\\", "\\\\").replace("'", "\\'") + "'"
    # Hydra's quotes inside the shell's double quotes, when nothing there is special to the shell.
    return f'"{word}"' if not any(c in word for c in '$`"\\!') else shell_arg(word)
