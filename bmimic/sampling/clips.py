r"""Bins over a motion library: several clips back to back on one time axis, no bin spanning two.

A library of C clips (``Motion.concatenate``; clip c holds frames :math:`[a_c, e_c)`) is cut clip by
clip: clip c gets the bins its own layout gives it (``time``: :math:`S_c = \lceil T_c / b \rceil`
bins of b seconds, the last one shorter, one bin for a clip shorter than b; ``released``: the released code's
:math:`B_c = \lfloor N_c / f \rfloor + 1` bins of its :math:`N_c` frames), and the global bin ids run
clip by clip: clip c's local bin j is global bin :math:`o_c + j`, :math:`o_c = \sum_{c' < c} S_{c'}`.

One mapping serves both directions: ``frame_to_bin`` (a library frame to its global bin) and
``bin_first_frame`` / ``bin_num_frames`` / ``bin_clip`` (a global bin to its clip and frame range).
Every bin's frames lie inside its clip, so a start frame drawn for a bin never belongs to another clip,
and ``bin_last_in_clip`` (the last global bin of each bin's clip) lets the samplers' look-ahead kernel
stop at the clip's end instead of reading the next clip's first bins.
"""

from __future__ import annotations

from typing import Sequence

import torch

from bmimic.sampling.bins import BinLayout, ReleasedBinLayout, _FrameBins, bin_size_s
from bmimic.sampling.checks import SamplerConfigError


class ClipLayout(_FrameBins):
    """The bins of a library: each clip cut by its own layout (``kind``: "time" or "released"), the
    global bin ids running clip by clip. Same interface as the single-clip layouts, plus
    ``clip_first_bin`` / ``clip_num_bins`` / ``clip_starts`` (LongTensor[C]) and ``bin_local``."""

    def __init__(self, kind: str, clip_starts: Sequence[int], num_frames: int, fps: float,
                 bin_size_seconds: float | None, clip_names: Sequence[str] | None = None, device: torch.device | str = "cpu"):
        super().__init__(num_frames, fps)
        starts = [int(s) for s in clip_starts]
        if not starts or starts[0] != 0 or any(b <= a for a, b in zip(starts, starts[1:])) or starts[-1] >= num_frames:
            raise SamplerConfigError(f"clip starts must begin at 0 and increase below {num_frames}, got {starts}")
        ends = [*starts[1:], num_frames]
        self.kind = kind
        self.bin_size_seconds = None if bin_size_seconds is None else float(bin_size_seconds)
        size_s = bin_size_s(kind, bin_size_seconds)
        # A clip shorter than one bin is one bin of its own length.
        clips = [BinLayout(e - a, fps, min(size_s, (e - a) / fps)) if kind == "time"
                 else ReleasedBinLayout(e - a, fps) for a, e in zip(starts, ends)]
        self._clips = clips
        offsets = torch.tensor([0, *[c.num_bins for c in clips]]).cumsum(0)
        frame_to_bin = torch.cat([c.frame_to_bin + o for c, o in zip(clips, offsets[:-1])])
        self._set_frame_to_bin(frame_to_bin, device)
        dev = self.device
        self.num_clips = len(clips)
        self.clip_names = tuple(clip_names) if clip_names is not None else tuple(f"clip{i}" for i in range(len(clips)))
        if len(self.clip_names) != self.num_clips:
            raise SamplerConfigError(f"{len(self.clip_names)} clip names for {self.num_clips} clips")
        counts = torch.tensor([c.num_bins for c in clips])
        self.clip_first_bin = offsets[:-1].to(dev)
        self.clip_num_bins = counts.to(dev)
        self.clip_starts = torch.tensor(starts).to(dev)
        self.bin_clip = torch.repeat_interleave(torch.arange(self.num_clips), counts).to(dev)
        self.bin_local = (torch.arange(self.num_bins) - offsets[:-1].repeat_interleave(counts)).to(dev)
        self.bin_last_in_clip = (offsets[1:] - 1).repeat_interleave(counts).to(dev)
        # released draws: floor((j + U) / B_c * (N_c - 1)) within clip c, per bin
        self._bin_clip_frames = torch.tensor(ends).sub(torch.tensor(starts)).repeat_interleave(counts).to(dev)

    def _edges_s(self, first_frame: torch.Tensor) -> torch.Tensor:
        # Each clip's own edges (multiples of the bin size from the clip's start) shifted to the clip's
        # start time; the library's end closes the last bin.
        starts = [0] + [int(s) for s in torch.cumsum(torch.tensor([c.num_frames for c in self._clips]), 0)[:-1]]
        parts = [c.edges_s.cpu()[:-1] + a / self.fps for c, a in zip(self._clips, starts)]
        return torch.cat((*parts, torch.tensor([self.duration_s], dtype=torch.float64)))

    def sample_frames(self, bins: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """A start frame for each global bin, inside the bin's clip, drawn as the clip's layout draws."""
        bins = torch.as_tensor(bins, device=self.device).long()
        u = torch.rand(bins.shape, generator=generator, dtype=torch.float64, device=self.device)
        if self.kind == "time":
            count = self.bin_num_frames[bins]
            return self.bin_first_frame[bins] + torch.minimum((u * count).long(), count - 1)
        clip = self.bin_clip[bins]
        local = ((self.bin_local[bins] + u) / self.clip_num_bins[clip] * (self._bin_clip_frames[bins] - 1)).long()
        return self.clip_starts[clip] + local

    def global_bin(self, clip: torch.Tensor, frame_in_clip: torch.Tensor) -> torch.Tensor:
        """The global bin of frame `frame_in_clip` of clip `clip` (LongTensors of one shape)."""
        clip = torch.as_tensor(clip, device=self.device).long()
        return self.bins_of(self.clip_starts[clip] + torch.as_tensor(frame_in_clip, device=self.device).long())

    def describe(self) -> str:
        per = f"time bins of {self.bin_size_seconds:g} s" if self.kind == "time" else "released bins"
        return f"{self.num_bins} {per} over {self.num_clips} clips ({self.duration_s:g} s)"

    def __repr__(self) -> str:
        return (f"ClipLayout(kind={self.kind!r}, num_clips={self.num_clips}, num_frames={self.num_frames}, "
                f"fps={self.fps:g}, num_bins={self.num_bins})")


__all__ = ["ClipLayout"]
