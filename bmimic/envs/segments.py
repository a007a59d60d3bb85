"""Where each env is on the reference: its frame, the first frame of its current reference segment
and the end of its clip. A segment is what an env tracks between two jumps of its reference (a reset
or a clip-end resample); a clip end is where training resamples and evaluation stops."""

from __future__ import annotations

import torch

from bmimic import BmimicError
from bmimic.motion.reference import ReferenceMotion
from bmimic.sim.config import SimConfig


class ReferenceSegments:
    """Per-env frame buffers (LongTensor[N]), written in place (the captured step holds them). The
    motion must be at the control rate: each step advances one frame."""

    def __init__(self, reference: ReferenceMotion, sim_cfg: SimConfig, num_envs: int, device: torch.device | str) -> None:
        control_fps = 1.0 / (sim_cfg.timestep_s * sim_cfg.decimation)
        if abs(reference.fps - control_fps) > 1e-6 * control_fps:
            # One reference frame per control step: any other rate plays the motion at the wrong speed.
            raise BmimicError(
                f"motion: is at {reference.fps:g} fps but sim.timestep_s * sim.decimation = "
                f"{sim_cfg.timestep_s:g} * {sim_cfg.decimation} s steps the policy at {control_fps:g} Hz; "
                "load it through bmimic.motion.config.load_motion(control_fps=...) to resample it")
        self.frame_clip_end = reference.frame_clip_end
        self.time_steps = torch.zeros(num_envs, dtype=torch.long, device=device)
        """The reference frame each env tracks now."""
        self.segment_start = torch.zeros(num_envs, dtype=torch.long, device=device)
        """The frame each env's current segment started at."""
        self.segment_end = torch.full((num_envs,), reference.num_frames, dtype=torch.long, device=device)
        """One past the last frame of the clip each env is in."""
        self.reached_clip_end = torch.zeros(num_envs, dtype=torch.bool, device=device)
        """Evaluation: the env is held on the last frame of its clip."""

    def start(self, mask: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
        """Masked envs start a segment at `frames`; returns every env's frame now."""
        frames = torch.where(mask, frames, self.time_steps)
        self.time_steps.copy_(frames)
        self.segment_start.copy_(torch.where(mask, frames, self.segment_start))
        self.segment_end.copy_(self.frame_clip_end[frames])
        return frames

    def ending(self, dones: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(clip_end, end_frames) before the step's resets: the continuing envs whose clip ends on the
        next frame, and the last frame of every segment that ends now (this frame for `dones`)."""
        next_frame = self.time_steps + 1
        clip_end = (next_frame >= self.segment_end) & ~dones
        return clip_end, torch.where(dones, self.time_steps, next_frame)

    def advance(self) -> torch.Tensor:
        """Training: every env moves one frame on; returns the envs now past their clip's end."""
        self.time_steps += 1
        return self.time_steps >= self.segment_end

    def advance_to_clip_end(self) -> None:
        """Evaluation: every env moves one frame on, holding at the last frame of its clip."""
        self.time_steps.copy_(torch.minimum(self.time_steps + 1, self.segment_end - 1))
        self.reached_clip_end.copy_(self.time_steps >= self.segment_end - 1)


__all__ = ["ReferenceSegments"]
