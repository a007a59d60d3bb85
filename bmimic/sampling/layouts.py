"""`make_layout`: the bin layout a run uses, of one motion (bmimic.sampling.bins) or of a library of
clips (bmimic.sampling.clips)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from bmimic.sampling.bins import LAYOUTS, BinLayout, Layout, ReleasedBinLayout, bin_size_s
from bmimic.sampling.checks import check_choice
from bmimic.sampling.clips import ClipLayout

if TYPE_CHECKING:
    import torch


def make_layout(bins: str, num_frames: int, fps: float, bin_size_seconds: float | None,
                device: torch.device | str = "cpu", clip_starts: Any = None, clip_names: Any = None) -> Layout:
    """The bin layout ``bins`` ("time" or "released") of a motion of ``num_frames`` at ``fps``; with
    several ``clip_starts`` (a library) the bins of each clip, indexed globally (ClipLayout)."""
    check_choice("bins", bins, LAYOUTS)
    if clip_starts is not None and len(clip_starts) > 1:
        return ClipLayout(bins, clip_starts, num_frames, fps, bin_size_seconds, clip_names, device=device)
    if bins == "released":
        layout: Layout = ReleasedBinLayout(num_frames, fps, device=device)
    else:
        layout = BinLayout(num_frames, fps, bin_size_s(bins, bin_size_seconds), device=device)
    if clip_names is not None and len(clip_names) == 1:
        layout.clip_names = (str(clip_names[0]),)
    return layout


__all__ = ["make_layout"]
