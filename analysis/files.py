"""Atomic writes of report artefacts, through bmimic's one atomic writer (bmimic.runs.folder.atomic_write):
a temp file beside the target, fsynced, then renamed over it, with the umask's permissions.

A reader (or a second writer) never sees a half-written file; of two concurrent writers the last
replace wins and both leave a complete file.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pandas as pd

from bmimic.runs.folder import atomic_write as _atomic_write


def atomic_write(path: str | Path, write: Callable[[Path], object]) -> Path:
    """Call ``write(tmp_path)`` on a fresh temp file in ``path``'s folder, then move it onto ``path``."""
    return _atomic_write(path, lambda tmp: write(Path(tmp)))


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def write_csv(path: str | Path, df: pd.DataFrame) -> Path:
    """Write ``df`` as CSV (no index) to ``path`` atomically."""
    return atomic_write(path, lambda tmp: df.to_csv(tmp, index=False))


def save_figure(path: str | Path, fig, dpi: int = 100) -> Path:
    """Save a matplotlib figure as PNG to ``path`` atomically (Agg renders it; no display needed)."""
    return atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight"))
