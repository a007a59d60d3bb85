r"""Per-iteration summaries of a sampler, for ``train_metrics.parquet`` and ``sampler.parquet``.

:func:`summary` gives the scalar columns of ``train_metrics``:

- ``episodes``: total episodes (the sum of the per-bin counts unless given explicitly; pass
  ``total_episodes`` when the per-bin counts are visits, which count an episode once per bin);
- ``failure_rate``: total failures / episodes (NaN with no episodes);
- ``sampling_entropy``: :math:`H(P)/\log S` with :math:`H(P) = -\sum_s P_s \log P_s`
  (:math:`0 \log 0 = 0`); 1 for a uniform P, and 1 by definition when S = 1;
- ``top1_prob``, ``top1_bin``: the largest :math:`P_s` and its bin index (lowest on ties).

:func:`bin_table` gives the tidy rows of ``sampler.parquet``, one per bin, with columns
``iteration, bin, clip, bin_start_s, bin_end_s, episodes, failures, raw_failure_rate,
smoothed_failure_rate, probability``; ``raw_failure_rate`` = failures / episodes (NaN where a bin
had none), ``clip`` the name of the bin's clip (a single motion: its name) and ``smoothed_failure_rate`` = ``sampler.smoothed_failure()`` (the adaptive sampler's
EMA rate r, the BeyondMimic sampler's EMA failure count q, NaN for the uniform sampler; the peer
samplers' own signal: EGM's error EMA, GMT's completion level, PHC's clip failure count,
ProtoMotions' clip weight). The counts
are those the sampler was fed during the iteration and the probabilities those after its update,
i.e. the distribution the next iteration samples from.

:func:`log_every` decides how often the trainer writes those rows.
"""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import torch

from bmimic.runs.schema import BIN, FAILURE_RATE, ITERATION
from bmimic.sampling.checks import SamplerConfigError

MAX_SAMPLER_ROWS = 1_000_000
"""sampler.log_every=null thins sampler.parquet of runs with more than 1,000 bins to about this many rows."""

BIN_TABLE_COLUMNS = (
    ITERATION,
    BIN,
    "clip",
    "bin_start_s",
    "bin_end_s",
    "episodes",
    "failures",
    "raw_failure_rate",
    "smoothed_failure_rate",
    "probability",
)


def log_every(setting: int | None, num_bins: int, iterations: int) -> int:
    """Iterations between two sampler tables: ``setting`` when given; else 1, or for more than
    1,000 bins the smallest interval that keeps ``num_bins x iterations / interval`` rows under
    :data:`MAX_SAMPLER_ROWS`."""
    if setting is not None:
        return int(setting)
    if num_bins <= 1000:
        return 1
    return max(1, math.ceil(num_bins * max(iterations, 1) / MAX_SAMPLER_ROWS))


def sampling_entropy(probs: torch.Tensor) -> float:
    """H(P) / log S in [0, 1]; 1.0 when S == 1."""
    p = probs.detach().double().cpu()
    if p.numel() <= 1:
        return 1.0
    h = -torch.special.xlogy(p, p).sum()
    return float(h / math.log(p.numel()))


def summary(
    sampler,
    episodes_per_bin: torch.Tensor,
    failures_per_bin: torch.Tensor,
    total_episodes: float | None = None,
) -> dict[str, float]:
    """Scalar diagnostics of one iteration (see the module docstring for each key)."""
    episodes = torch.as_tensor(episodes_per_bin).detach().double().cpu()
    failures = torch.as_tensor(failures_per_bin).detach().double().cpu()
    n = float(episodes.sum()) if total_episodes is None else float(total_episodes)
    probs = sampler.probabilities().detach().double().cpu()
    top1 = int(torch.argmax(probs))
    return {
        "episodes": n,
        FAILURE_RATE: float(failures.sum()) / n if n > 0 else math.nan,
        "sampling_entropy": sampling_entropy(probs),
        "top1_prob": float(probs[top1]),
        "top1_bin": float(top1),
    }


def _clip_names(layout, num_bins: int) -> list[str]:
    """Each bin's clip name (a layout without clips, or bare edges: "motion")."""
    if not hasattr(layout, "bin_clip"):
        return ["motion"] * num_bins
    names = layout.clip_names
    return [names[i] for i in layout.bin_clip.cpu().tolist()]


def bin_table(
    iteration: int,
    layout,
    episodes_per_bin: torch.Tensor,
    failures_per_bin: torch.Tensor,
    sampler,
) -> pd.DataFrame:
    """One row per bin (columns :data:`BIN_TABLE_COLUMNS`); ``layout`` is a bin layout (anything
    with ``edges_s``) or the edges [S+1] in seconds."""
    edges = layout.edges_s if hasattr(layout, "edges_s") else torch.as_tensor(layout)
    edges = edges.detach().double().cpu().numpy()
    s = len(edges) - 1
    episodes = torch.as_tensor(episodes_per_bin).detach().double().cpu().numpy()
    failures = torch.as_tensor(failures_per_bin).detach().double().cpu().numpy()
    probs = sampler.probabilities().detach().double().cpu().numpy()
    smoothed = sampler.smoothed_failure().detach().double().cpu().numpy()
    for name, arr in (("episodes", episodes), ("failures", failures), ("probability", probs)):
        if arr.shape != (s,):
            raise SamplerConfigError(
                f"bin_table: {name} has shape {arr.shape}, expected ({s},) from the bin edges"
            )
    with np.errstate(divide="ignore", invalid="ignore"):
        raw = np.where(episodes > 0, failures / np.maximum(episodes, 1.0), np.nan)
    return pd.DataFrame(
        {
            ITERATION: np.full(s, int(iteration), dtype=np.int64),
            BIN: np.arange(s, dtype=np.int64),
            "clip": _clip_names(layout, s),
            "bin_start_s": edges[:-1],
            "bin_end_s": edges[1:],
            "episodes": np.rint(episodes).astype(np.int64),
            "failures": np.rint(failures).astype(np.int64),
            "raw_failure_rate": raw,
            "smoothed_failure_rate": smoothed,
            "probability": probs,
        },
        columns=list(BIN_TABLE_COLUMNS),
    )
