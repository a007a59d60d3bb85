r"""Episode accounting: how the training environment turns finished episodes into per-bin counts,
and when the sampler sees them.

The environment owns the reference state (frames, clip ends, resets); it calls one
:class:`EpisodeAccounting` at four points:

1. ``start_episodes(mask, bins)`` when envs start a new episode (a real reset) at a frame drawn
   for ``bins``: each env remembers the bin its episode started in. A clip-end resample (the
   reference jumps to a new frame, the episode goes on) does not call it, so the start bin survives
   it.
2. ``count(...)`` in the step, before the resets, for the episodes (and reference segments) that
   end now, giving the per-bin counts ``(episodes, failures)`` of the step as a [2, S] tensor:

   - ``attribution="start"``: each finished episode counts once, for its start bin;
   - ``attribution="failure"``: each reference segment that ends (an episode's end, or a clip-end
     resample) counts a visit in every bin of [start_bin, end_bin] of its frames, and a failure in
     the bin where it ended.

   A finished episode failed if (``failure="terminated"``) it ended by a termination (time-outs
   never fail), or (``failure="short"``) it ended by a termination while its length was below
   ``failure_threshold`` x the max episode length. The length is the environment's episode-length
   counter, which ``init_at_random_ep_len`` starts at a random value in each env's first episode,
   so a first episode's "length" includes that offset; a time-out is never a failure. A world that
   broke (non-finite state, |qvel| or the root beyond the simulator's bounds, a reward overflow) is
   a failure whatever its length, charged where it broke: a policy (or motion) that blows up the
   simulation must look hard to the sampler, never mastered.
3. ``record(counts)`` in the step, after the resets were drawn: with ``update_every="step"`` the
   sampler is updated now (all-reduced first under torchrun), as in the released code; with
   ``update_every="iteration"`` the counts are added to a pending total and the sampling
   distribution does not change within the rollout.
4. ``end_rollout()`` once per PPO iteration, after the rollout (the design's runner hook): with
   ``update_every="iteration"``, one all-reduce of the pending counts (torchrun), one
   ``sampler.update_counts`` with them, and the pending total is cleared.

For samplers that learn from tracking errors (``sampler.tracking_error``, e.g. ``egm`` and
``gmt``), ``track(state, frames, broken)`` in every step adds each env's errors
(:data:`bmimic.sampling.base.ERROR_COMPONENTS`; a broken world's are BROKEN_ERRORS) to the bin of
its current reference frame, and
``end_rollout`` hands the iteration's sums to ``sampler.update_errors`` (all-reduced first under
torchrun), whatever ``update_every`` is. Other samplers skip it: the step pays nothing.

Everything in 1-3 has fixed shapes, writes its buffers in place and never reads values on the
host, so it runs inside the environment's captured CUDA graphs. ``pop_counts`` returns (and
clears) the counts the sampler was fed during the iteration, summed, for the diagnostics.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from bmimic.envs.quat import quat_error_magnitude
from bmimic.sampling.base import ERROR_COMPONENTS, bin_counts
from bmimic.sampling.bins import Layout, attribute, check_attribution, check_failure, failed_mask
from bmimic.sampling.checks import check_choice
from bmimic.sampling.schemas import AccountingConfig

UPDATE_EVERY = ("iteration", "step")
BROKEN_ERRORS = (1.0, math.pi, 10.0, 1.0)
"""The per-step errors (ERROR_COMPONENTS: m, rad, m/s, m) a broken world is charged: tracking lost
entirely (a termination fires at 0.25 m), beyond any tracked world's, so an error-driven sampler
(EGM, GMT) reads a broken world as the hardest failure, as the count-driven ones read a failure."""


def check_accounting(cfg: Any) -> None:
    """Range checks of `sampler.accounting` (an AccountingConfig or its node)."""
    check_attribution(cfg.attribution)
    check_failure(cfg.failure, cfg.failure_threshold)
    check_choice("accounting.update_every", cfg.update_every, UPDATE_EVERY)


class EpisodeAccounting:
    """Per-env start bins and per-bin episode/failure counts of one training environment."""

    def __init__(
        self,
        sampler: Any,
        layout: Layout,
        num_envs: int,
        max_episode_length: int,
        attribution: str = "start",
        failure: str = "short",
        failure_threshold: float = 0.8,
        update_every: str = "iteration",
        device: Any = "cpu",
        world_size: int | None = None,
    ) -> None:
        check_accounting(AccountingConfig(attribution, failure, failure_threshold, update_every))
        self.sampler = sampler
        self.layout = layout
        self.max_episode_length = int(max_episode_length)
        self.attribution = attribution
        self.failure = failure
        self.failure_threshold = float(failure_threshold)
        self.update_every = update_every
        if world_size is None:  # under torchrun: every rank's sampler sees every rank's episodes
            dist = torch.distributed
            world_size = dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1
        self.world_size = int(world_size)
        dev = torch.device(device)
        s = layout.num_bins
        self.start_bin = torch.zeros(num_envs, dtype=torch.long, device=dev)
        """The bin each env's current episode started in (written only by start_episodes)."""
        self._pending = torch.zeros(2, s, dtype=torch.float64, device=dev)
        self._iteration = torch.zeros(2, s, dtype=torch.float64, device=dev)
        self.tracks_errors = bool(getattr(sampler, "tracking_error", False))
        """Whether the step measures per-bin tracking errors (only for a sampler that uses them)."""
        # Rows: the ERROR_COMPONENTS sums, then the env-steps counted; float64 so that a long
        # rollout's sums of small errors lose nothing.
        self._errors = torch.zeros(len(ERROR_COMPONENTS) + 1, s, dtype=torch.float64, device=dev)
        self._broken_errors = torch.tensor([*BROKEN_ERRORS, 1.0], device=dev)[:, None]  # (+ the step count)

    @classmethod
    def from_config(cls, cfg: AccountingConfig, sampler: Any, layout: Layout, num_envs: int, max_episode_length: int,
                    device: Any = "cpu", world_size: int | None = None) -> "EpisodeAccounting":
        """The accounting `cfg` (`sampler.accounting`) describes, for `num_envs` envs."""
        return cls(sampler, layout, num_envs, max_episode_length, attribution=cfg.attribution, failure=cfg.failure,
                   failure_threshold=cfg.failure_threshold, update_every=cfg.update_every, device=device,
                   world_size=world_size)

    # ------------------------------------------------------------------ in the step
    def start_episodes(self, mask: torch.Tensor, bins: torch.Tensor) -> None:
        """The masked envs start a new episode in ``bins`` (the bins their start frames were drawn for)."""
        self.start_bin.copy_(torch.where(mask, bins, self.start_bin))

    def count(
        self,
        dones: torch.Tensor,
        clip_end: torch.Tensor,
        end_frames: torch.Tensor,
        segment_start: torch.Tensor,
        terminated: torch.Tensor,
        broken: torch.Tensor,
        episode_length: torch.Tensor,
    ) -> torch.Tensor:
        """Per-bin (episodes, failures) of what ends now, float64 [2, S]; every env is passed
        (fixed shapes) and the masks select.

        Args:
            dones: episodes that end now (broken worlds included); clip_end: continuing episodes
                whose reference segment ends now (only used by attribution="failure").
            end_frames: last frame of each ending segment; segment_start: its first frame.
            terminated: ended by a termination (not a time-out); broken: reset because the world
                broke (a failure, whatever the failure rule says of its length).
            episode_length: the episode-length counter, in control steps.
        """
        failed = failed_mask(terminated, episode_length, self.max_episode_length, self.failure,
                             self.failure_threshold) | broken
        s = self.layout.num_bins
        if self.attribution == "start":
            episodes = bin_counts(self.start_bin, s, dones.long())
            failures = bin_counts(self.start_bin, s, (failed & dones).long())
        else:
            episodes, failures = attribute(segment_start, end_frames, failed, self.layout, "failure",
                                           counted=dones | clip_end)
        return torch.stack((episodes, failures)).to(torch.float64)

    def track(self, state: Any, frames: torch.Tensor, broken: torch.Tensor) -> None:
        """Add every env's tracking errors of this step to the bin of its reference frame (only when
        the sampler uses them). ``state``: the step's TrackingState; ``frames``: the reference frame
        of each env; ``broken``: envs reset as broken this step, charged BROKEN_ERRORS."""
        if not self.tracks_errors:
            return
        pos = (state.ref_body_pos_relative - state.robot_body_pos).norm(dim=-1)  # [N, bodies] m
        per_env = torch.stack((
            pos.mean(-1),
            quat_error_magnitude(state.ref_body_quat_relative, state.robot_body_quat).mean(-1),
            (state.ref_body_lin_vel - state.robot_body_lin_vel).norm(dim=-1).mean(-1),
            pos.amax(-1),
            torch.ones_like(pos[:, 0]),
        ))  # [components + 1, N]
        # where, not a product: a broken world's NaN stays out; it is charged a lost track instead
        per_env = torch.where(broken, self._broken_errors.to(per_env.dtype), per_env)
        bins = self.layout.bins_of(frames)
        self._errors.index_add_(1, bins, per_env.to(torch.float64))

    def record(self, counts: torch.Tensor) -> None:
        """Feed one step's counts to the sampler now (update_every="step") or at end_rollout."""
        if self.update_every == "step":
            if self.world_size > 1:
                # Several GPUs train one policy: every rank's sampler sees every rank's episodes,
                # so all ranks sample from the same distribution.
                torch.distributed.all_reduce(counts)
            self.sampler.update_counts(counts[0], counts[1])
            self._iteration += counts
        else:
            self._pending += counts

    # ------------------------------------------------------------------ once per iteration
    def end_rollout(self) -> None:
        """update_every="iteration": one sampler update with every episode of the rollout; and, for
        a sampler that uses them, the rollout's per-bin tracking errors."""
        if self.tracks_errors:
            if self.world_size > 1:
                torch.distributed.all_reduce(self._errors)
            self.sampler.update_errors(self._errors[:-1], self._errors[-1])
            self._errors.zero_()
        if self.update_every != "iteration":
            return
        if self.world_size > 1:
            torch.distributed.all_reduce(self._pending)
        self.sampler.update_counts(self._pending[0], self._pending[1])
        self._iteration += self._pending
        self._pending.zero_()

    def pop_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """(episodes, failures) per bin that the sampler was fed since the last pop (summed over
        the ranks under torchrun); one host transfer, then cleared."""
        counts = self._iteration.cpu().numpy().copy()
        self._iteration.zero_()
        return counts[0], counts[1]

    def discard(self) -> None:
        """Forget counts not yet fed or popped (the environment's warm-up steps)."""
        self._pending.zero_()
        self._iteration.zero_()
        self._errors.zero_()


__all__ = ["UPDATE_EVERY", "AccountingConfig", "EpisodeAccounting", "check_accounting"]
