"""Which machine kind each run trained on (provenance.json), so wall times are compared only within one.

Wall time depends on the GPU (an H200 is not an H100) as much as on the sampler, so a ratio of wall
times between runs of different machine kinds measures the machines. The report prints wall-time
speedups only when every included run trained on the same kind; otherwise it leaves them out and says
which runs ran where. (Runs sharing one GPU under MPS differ too; provenance does not record that.)
"""

from __future__ import annotations

import pandas as pd

from bmimic.runs.folder import read_provenance

UNKNOWN = "unknown"


def machine_kind(provenance: dict) -> str:
    """``"<count> x <GPU name>"`` (``"NVIDIA H100 80GB HBM3"`` for one GPU), ``"CPU"`` for a run on the
    CPU, ``"unknown"`` without a record."""
    gpu = provenance.get("gpu")
    if isinstance(gpu, dict) and gpu.get("name"):
        count = gpu.get("count")
        name = str(gpu["name"])
        return f"{int(count)} x {name}" if isinstance(count, int) and count > 1 else name
    device = str(provenance.get("device", ""))
    if device.startswith("cpu"):
        return "CPU"
    return UNKNOWN


def machine_kinds(runs: pd.DataFrame) -> pd.Series:
    """The machine kind of every included run (index: run_dir)."""
    inc = runs[runs["included"]]
    return pd.Series({r: machine_kind(read_provenance(r)) for r in inc["run_dir"]}, dtype=object)


def wall_time_comparable(kinds: pd.Series) -> bool:
    """Wall times compare only when every run has one known machine kind."""
    values = set(kinds)
    return len(values) == 1 and UNKNOWN not in values


def kinds_text(runs: pd.DataFrame, kinds: pd.Series) -> str:
    """``arm: n on <kind>, m on <kind>; ...`` for the report's sentence on mixed machines."""
    df = runs[runs["included"]][["arm", "run_dir"]].assign(kind=lambda d: d["run_dir"].map(kinds))
    parts = []
    for arm, g in df.groupby("arm", sort=True):
        counts = g["kind"].value_counts().sort_index()
        parts.append(f"`{arm}`: " + ", ".join(f"{n} on {k}" for k, n in counts.items()))
    return "; ".join(parts)
