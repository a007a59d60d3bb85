r"""Time bins of a reference motion, and charging finished episodes to them.

Conventions. A motion of N frames at f frames per second spans :math:`T = N/f` seconds; frame i
is at time :math:`t_i = i/f`. With bin size b seconds there are

.. math:: S = \lceil T / b \rceil

bins; bin s covers :math:`[s\,b, \min((s+1)\,b, T))`, so the last bin may be shorter. The bin of
time t is :math:`\min(\lfloor t/b \rfloor, S-1)` (time T itself belongs to the last bin).
Quotients within 1e-9 (relative) of an integer are snapped to it first, so float error never
moves a boundary: ``num_bins(30.0, 1.0) == 30`` and frame 9 at 30 fps is in bin 3 for b = 0.1 s
even though ``9/30/0.1 == 2.9999999999999996``.

Two bin layouts map frames to bins and draw start frames; which one a run uses is ``sampler.bins``
(:func:`bmimic.sampling.layouts.make_layout`), and the same layout serves sampling, attribution, diagnostics and the
evaluation tables:

- :class:`BinLayout` (``bins: time``): the time bins above; a start frame is drawn uniformly among
  the frames of the bin.
- :class:`ReleasedBinLayout` (``bins: released``): the bins of the released BeyondMimic code
  (HybridRobotics/whole_body_tracking, ``mdp/commands.py``). For a motion of T frames at f frames
  per second (f = 50, the control rate, in the released code and in bmimic),
  :math:`B = \lfloor T / f \rfloor + 1` bins; frame t is in bin
  :math:`\min(\lfloor t B / T \rfloor, B-1)` (where the released code charges a failure), and a start
  frame for bin b is drawn as :math:`\lfloor (b + U) / B \cdot (T-1) \rfloor`, U uniform in [0, 1).
  ``bin_size_seconds`` does not apply. The two formulas use T and T-1: a start drawn for bin b can
  lie in bin b-1 by the first formula (the first frame or so of each bin's draw range), as in the
  released code. Start frames are computed in float64; the released code's float32 can round b + U
  up to b + 1 (and so start at frame T-1) for U within 2^-24 (b+1) of 1.

When b is not a multiple of the frame period the last bin can be a sliver shorter than one
frame period that holds no frame; such a bin is dropped (its time joins the previous bin), so
every bin of a layout holds at least one frame and ``layout.num_bins`` may be one less than
``num_bins(T, b)`` in that case.

Charging episodes (:func:`attribute`), for finished segments with start frame, end frame and a
failed flag (a segment is a stretch of one episode on one contiguous piece of the motion):

- ``attribution="failure"``: a failure is charged to the bin of the frame where the segment
  ended; ``episodes[s]`` counts the segments that were active in bin s (visits, computed with a
  difference array over [start_bin, end_bin] and a cumulative sum), so the adaptive sampler's
  rate is failures per visit.
- ``attribution="start"``: both counts go to the bin the segment started in.

What counts as failed (:func:`failed_mask`): ``"terminated"`` = any termination other than a
time-out (the caller passes the terminated flag, which excludes time-outs); ``"short"`` = a
termination that came before failure_threshold x the max episode length. For whole episodes the
latter is the same as "episode length < failure_threshold x max length", since an episode that
was not terminated timed out at the max length; for a segment that ended because the reference
clip ended, requiring a termination keeps it from counting as failed.

Everything here is vectorised with fixed output shapes, so it runs on the GPU inside the
environment step without synchronising with the host.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from bmimic.sampling.base import bin_counts
from bmimic.sampling.checks import SamplerConfigError, check_choice, check_fraction, fail, is_number

ATTRIBUTIONS = ("failure", "start")
FAILURES = ("terminated", "short")
LAYOUTS = ("time", "released")


def check_bin_size(bin_size_seconds: Any, motion_duration_s: float | None = None) -> None:
    """A finite bin size > 0 and, when the motion's duration is given, at most that long."""
    if not (is_number(bin_size_seconds) and 0.0 < bin_size_seconds < math.inf):
        fail("bin_size_seconds", "a finite number > 0", bin_size_seconds)
    if motion_duration_s is not None and bin_size_seconds > motion_duration_s:
        fail("bin_size_seconds", f"<= the motion duration ({motion_duration_s:g} s)", bin_size_seconds)


def check_attribution(attribution: Any) -> None:
    check_choice("accounting.attribution", attribution, ATTRIBUTIONS)


def check_failure(failure: Any, failure_threshold: Any) -> None:
    check_choice("accounting.failure", failure, FAILURES)
    check_fraction("accounting.failure_threshold", failure_threshold)

_SNAP_RTOL = 1e-9


def _snap(x: float) -> float:
    r = round(x)
    return float(r) if abs(x - r) <= _SNAP_RTOL * max(1.0, abs(r)) else x


def _snap_tensor(x: torch.Tensor) -> torch.Tensor:
    r = torch.round(x)
    return torch.where((x - r).abs() <= _SNAP_RTOL * r.abs().clamp(min=1.0), r, x)


def num_bins(duration_s: float, bin_size_seconds: float) -> int:
    """S = ceil(T / b), robust to float error. Raises SamplerConfigError unless 0 < b <= T."""
    check_bin_size(bin_size_seconds, duration_s)
    return max(1, math.ceil(_snap(duration_s / bin_size_seconds)))


def bin_edges_s(duration_s: float, bin_size_seconds: float) -> torch.Tensor:
    """Bin edges [0, b, 2b, ..., (S-1) b, T] in seconds (float64, S+1 entries)."""
    s = num_bins(duration_s, bin_size_seconds)
    edges = torch.arange(s + 1, dtype=torch.float64) * bin_size_seconds
    edges[-1] = duration_s
    return edges


def bins_of_time(t_s: torch.Tensor, bin_size_seconds: float, num_bins: int) -> torch.Tensor:
    """Bin of each time: min(floor(t / b), S-1), with float-error snapping (LongTensor)."""
    q = _snap_tensor(torch.as_tensor(t_s, dtype=torch.float64) / bin_size_seconds)
    return q.floor().long().clamp_(0, num_bins - 1)


def bin_size_s(kind: str, bin_size_seconds: float | None) -> float:
    """The bin size of time bins (0.0 for released bins, which have none)."""
    if kind != "time":
        return 0.0
    if bin_size_seconds is None:
        raise SamplerConfigError("sampler.bin_size_seconds: time bins need a size in seconds, got null")
    return float(bin_size_seconds)


class _FrameBins:
    """Frame <-> bin maps of one motion (N frames at ``fps``), precomputed on ``device``.

    Attributes:
        kind: the layout's name in ``sampler.bins``.
        num_frames, fps, duration_s, num_bins.
        frame_to_bin: LongTensor[N], the bin of each frame.
        bin_first_frame: LongTensor[S], first frame of each bin.
        bin_num_frames: LongTensor[S], number of frames in each bin (>= 1).
        edges_s: float64 Tensor[S+1], bin edges in seconds (the time of each bin's first frame,
            then T).
    """

    kind = ""

    def __init__(self, num_frames: int, fps: float) -> None:
        if not (isinstance(num_frames, int) and num_frames >= 1):
            raise SamplerConfigError(f"motion num_frames must be an integer >= 1, got {num_frames!r}")
        if not (isinstance(fps, (int, float)) and 0.0 < fps < math.inf):
            raise SamplerConfigError(f"motion fps must be a finite number > 0, got {fps!r}")
        self.num_frames = num_frames
        self.fps = float(fps)
        self.duration_s = num_frames / self.fps

    def _set_frame_to_bin(self, frame_to_bin: torch.Tensor, device: torch.device | str) -> None:
        """Derive every table from the (CPU, non-decreasing, gap-free) frame -> bin map."""
        counts = torch.bincount(frame_to_bin)
        if not bool((counts >= 1).all()):
            raise SamplerConfigError(f"{type(self).__name__}: a bin holds no frame")
        self.num_bins = len(counts)
        first = torch.cumsum(counts, 0) - counts
        self.frame_to_bin = frame_to_bin.to(device)
        self.bin_num_frames = counts.to(device)
        self.bin_first_frame = first.to(device)
        self.edges_s = self._edges_s(first).to(device)
        self.device = self.frame_to_bin.device
        # One clip (a library's layout, bmimic.sampling.clips.ClipLayout, overrides these).
        self.num_clips = 1
        self.clip_names: tuple[str, ...] = ("motion",)
        self.bin_clip = torch.zeros(self.num_bins, dtype=torch.long, device=self.device)
        self.bin_last_in_clip = torch.full((self.num_bins,), self.num_bins - 1, dtype=torch.long, device=self.device)

    def _edges_s(self, first_frame: torch.Tensor) -> torch.Tensor:
        edges = torch.cat((first_frame.double() / self.fps, torch.tensor([self.duration_s], dtype=torch.float64)))
        return edges

    def bins_of(self, frames: torch.Tensor) -> torch.Tensor:
        """Bin of each frame index (LongTensor). Frames past the end (e.g. frame N, time T)
        count in the last bin; negative frames in the first."""
        frames = torch.as_tensor(frames, device=self.device).long()
        return self.frame_to_bin[frames.clamp(0, self.num_frames - 1)]

    def sample_frames(self, bins: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """A start frame for each bin (LongTensor, same shape as bins)."""
        raise NotImplementedError

    def describe(self) -> str:
        """One line for the run's log."""
        raise NotImplementedError


class BinLayout(_FrameBins):
    """Time bins of ``bin_size_seconds`` (``sampler.bins: time``); see the module docstring."""

    kind = "time"

    def __init__(self, num_frames: int, fps: float, bin_size_seconds: float, device: torch.device | str = "cpu"):
        super().__init__(num_frames, fps)
        self.bin_size_seconds = float(bin_size_seconds)
        s = num_bins(self.duration_s, bin_size_seconds)
        if _snap(self.fps * self.bin_size_seconds) < 1.0:
            raise SamplerConfigError(
                f"sampler.bin_size_seconds must be at least one frame period ({1.0 / self.fps:g} s at "
                f"{self.fps:g} fps), got {bin_size_seconds!r}"
            )
        # Built on the CPU in float64 once, then moved: exact and cheap. With >= 1 frame per bin
        # only the last bin can be empty (a sliver shorter than a frame); bincount drops it.
        frame_to_bin = bins_of_time(torch.arange(num_frames, dtype=torch.float64) / self.fps, bin_size_seconds, s)
        self._set_frame_to_bin(frame_to_bin, device)

    def _edges_s(self, first_frame: torch.Tensor) -> torch.Tensor:
        # Multiples of the bin size (not first-frame times), so edges read 0, b, 2b, ... exactly.
        edges = torch.arange(len(first_frame) + 1, dtype=torch.float64) * self.bin_size_seconds
        edges[-1] = self.duration_s
        return edges

    def sample_frames(self, bins: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """A frame drawn uniformly among the frames of each bin (LongTensor, same shape as bins)."""
        bins = torch.as_tensor(bins, device=self.device).long()
        count = self.bin_num_frames[bins]
        u = torch.rand(bins.shape, generator=generator, dtype=torch.float64, device=self.device)
        offset = torch.minimum((u * count).long(), count - 1)
        return self.bin_first_frame[bins] + offset

    def describe(self) -> str:
        return f"{self.num_bins} time bins of {self.bin_size_seconds:g} s over {self.duration_s:g} s"

    def __repr__(self) -> str:
        return (
            f"BinLayout(num_frames={self.num_frames}, fps={self.fps:g}, "
            f"bin_size_seconds={self.bin_size_seconds:g}, num_bins={self.num_bins})"
        )


class ReleasedBinLayout(_FrameBins):
    """The released BeyondMimic code's bins (``sampler.bins: released``); see the module docstring."""

    kind = "released"

    def __init__(self, num_frames: int, fps: float, device: torch.device | str = "cpu"):
        super().__init__(num_frames, fps)
        t = num_frames
        # int(T // (1 / control_dt)) + 1 in the released code; one frame per control step.
        self._B = int(t // self.fps) + 1
        self._set_frame_to_bin(torch.clamp(torch.arange(t) * self._B // t, 0, self._B - 1), device)
        assert self.num_bins == self._B  # T / B >= 1 frame per bin, so no bin is empty

    def sample_frames(self, bins: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
        """floor((b + U) / B * (T - 1)) with U uniform in [0, 1) (LongTensor, same shape as bins)."""
        bins = torch.as_tensor(bins, device=self.device).long()
        u = torch.rand(bins.shape, generator=generator, dtype=torch.float64, device=self.device)
        return ((bins + u) / self.num_bins * (self.num_frames - 1)).long()

    def describe(self) -> str:
        return (f"{self.num_bins} released bins (B = T // {self.fps:g} + 1 over T = {self.num_frames} frames, "
                f"{self.duration_s:g} s)")

    def __repr__(self) -> str:
        return f"ReleasedBinLayout(num_frames={self.num_frames}, fps={self.fps:g}, num_bins={self.num_bins})"


Layout = _FrameBins
"""Any bin layout: BinLayout, ReleasedBinLayout, or a library's ClipLayout (bmimic.sampling.clips)."""


def visits_histogram(
    start_bins: torch.Tensor, end_bins: torch.Tensor, num_bins: int, weights: torch.Tensor | None = None
) -> torch.Tensor:
    """Number of segments active in each bin, for segments [start_bin, end_bin] (inclusive).

    Difference array: +w at start, -w after end, cumulative sum (w = 1, or ``weights``, e.g. a
    mask of the segments to count). ``end < start`` cannot come from a real segment; it is treated
    as ``end = start`` so the counts are never negative. Returns Tensor[S] of the weights' dtype
    (long without weights).
    """
    start = torch.as_tensor(start_bins).long()
    end = torch.maximum(torch.as_tensor(end_bins, device=start.device).long(), start)
    w = torch.ones_like(start) if weights is None else torch.as_tensor(weights, device=start.device)
    diff = bin_counts(torch.cat((start, end + 1)), num_bins + 1, torch.cat((w, -w)))
    return torch.cumsum(diff[:num_bins], 0)


def failed_mask(
    terminated: torch.Tensor,
    episode_length_steps: torch.Tensor,
    max_episode_length_steps: int | float | torch.Tensor,
    failure: str,
    failure_threshold: float = 0.8,
) -> torch.Tensor:
    """Which finished episodes (or segments) failed (BoolTensor).

    ``"terminated"``: ``terminated`` itself (terminations other than time-outs).
    ``"short"``: ``terminated & (episode_length_steps < failure_threshold * max_episode_length_steps)``.
    """
    check_failure(failure, failure_threshold)
    terminated = torch.as_tensor(terminated).bool()
    if failure == "terminated":
        return terminated.clone()
    length = torch.as_tensor(episode_length_steps, device=terminated.device)
    # A Python limit stays a scalar operand: making it a device tensor would be a host-to-device copy,
    # a synchronisation on every step of the hot path.
    limit = max_episode_length_steps
    if isinstance(limit, torch.Tensor):
        limit = limit.to(terminated.device)
    return terminated & (length < failure_threshold * limit)


def attribute(
    start_frames: torch.Tensor,
    end_frames: torch.Tensor,
    failed: torch.Tensor,
    layout: Layout,
    attribution: str,
    counted: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-bin (episodes, failures) counts, LongTensor[S] each, for :meth:`update_counts`.

    Args:
        start_frames, end_frames: LongTensor[n], first and last frame of each segment.
        failed: BoolTensor[n].
        layout: the motion's bin layout.
        attribution: "failure" (episodes = visits over [start_bin, end_bin], failures at the end
            bin) or "start" (both at the start bin).
        counted: optional BoolTensor[n]; only these segments are counted. It lets the environment
            pass all envs every step (fixed shapes) with ``counted`` = the ones that finished.
    """
    check_attribution(attribution)
    start_bins = layout.bins_of(start_frames)
    failed = torch.as_tensor(failed, device=layout.device).bool()
    if counted is None:
        weights = torch.ones_like(start_bins)
    else:
        counted = torch.as_tensor(counted, device=layout.device).bool()
        weights = counted.long()
        failed = failed & counted
    failed = failed.long()
    s = layout.num_bins
    if attribution == "start":
        return bin_counts(start_bins, s, weights), bin_counts(start_bins, s, failed)
    end_bins = layout.bins_of(end_frames)
    return visits_histogram(start_bins, end_bins, s, weights), bin_counts(end_bins, s, failed)


__all__ = [
    "ATTRIBUTIONS",
    "FAILURES",
    "LAYOUTS",
    "BinLayout",
    "Layout",
    "ReleasedBinLayout",
    "attribute",
    "bin_edges_s",
    "bins_of_time",
    "failed_mask",
    "num_bins",
    "visits_histogram",
]
