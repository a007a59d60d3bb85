"""Analysis of bmimic run folders: tidy loaders, metrics, plots and the sweep report.

Read top to bottom: ``load`` turns run folders into tidy pandas frames, ``stats`` holds the
statistics over seeds (IQM, bootstrap intervals), ``metrics`` the pure task metrics (mastery,
time to threshold, speedup), ``plots`` one function per figure, ``report`` the command line
``python -m analysis.report`` and ``index`` the per-sweep ``index.csv``.

This package never imports torch or the simulator, so reports can be built on any machine.
"""


class AnalysisError(Exception):
    """Bad input to the analysis (a missing file, an unreadable table, a wrong column).

    The message is one line naming the file or field and what is wrong.
    """
