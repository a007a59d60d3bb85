"""When an evaluation counts a bin as mastered: the one rule training's summary and the analysis share.

A bin is mastered at an evaluation when its failure rate is below the threshold and, if the bin is
`horizon_truncated` (its episodes run out of clip before the horizon), at least one episode tracked
all of its frames after entering it from an earlier bin (`tracked_through`), so the clip's last bins
are not "mastered" by a policy whose episodes simply run out of clip. Torch-free: the analysis
imports it on machines without torch.
"""

from __future__ import annotations

import pandas as pd


def counts_as_mastered(per_bin: pd.DataFrame, threshold: float) -> pd.Series:
    """Whether each row (one bin of one evaluation) counts as mastered (the module's rule).

    Reads ``failure_rate`` and, where present, ``horizon_truncated`` and ``tracked_through`` (tables
    from before those columns existed are taken as not truncated).
    """
    below = per_bin["failure_rate"].astype(float) < threshold
    if "horizon_truncated" not in per_bin:
        return below
    truncated = per_bin["horizon_truncated"].fillna(False).astype(bool)
    through = per_bin["tracked_through"].fillna(0) if "tracked_through" in per_bin else 0
    return below & (~truncated | (through >= 1))
