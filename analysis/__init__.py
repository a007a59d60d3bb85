"""Analysis of bmimic run folders: tidy loaders, metrics, plots and the sweep report.

Read top to bottom: ``load`` turns run folders into tidy pandas frames, ``stats`` holds the
statistics over seeds (IQM, bootstrap intervals), ``metrics`` the pure task metrics (mastery,
time to threshold, speedup), ``plots`` one function per figure, ``report`` the command line
``python -m analysis.report`` and ``index`` the per-sweep ``index.csv``.

This package never imports torch or the simulator, so reports can be built on any machine.
"""


from bmimic import BmimicError


class AnalysisError(Exception):
    """Bad input to the analysis (a missing file, an unreadable table, a wrong column).

    The message is one line naming the file or field and what is wrong.
    """


REFUSED = (AnalysisError, BmimicError)
"""What a command refuses in one line, exit status 2: bad input, or a write the disk refuses
(bmimic.runs.atomic_io's WriteError, a BmimicError)."""


def error_line(e: BaseException) -> str:
    """The one line a command prints for a refused input or write."""
    text = str(e).strip()
    return f"error: {text.splitlines()[0] if text else type(e).__name__}"
