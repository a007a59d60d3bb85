r"""How a sampler hears from the environment: :class:`SamplerFeedback`, the one component that
measures each signal its sampler declared and delivers it at its cadence.

The signals and what a sampler declares: :mod:`bmimic.sampling.signals` (torch-free, so that a sampler
module imports without torch). The environment calls the feedback at four points of its step (1-3) and the runner at two (4-5):

1. ``start_episodes(mask, bins)`` when envs start a new episode (a real reset) at a frame drawn
   for ``bins``: each env remembers the bin its episode started in. A clip-end resample (the
   reference jumps to a new frame, the episode goes on) does not call it, so the start bin survives.
2. ``measure(frames, broken, dones, rewards, errors)`` in the step: the per-step measurements of the
   per-iteration signals the sampler declared (``TRACKING_ERRORS``: every env's errors, from ``errors()``, which
   the environment computes only when asked; a broken world is charged BROKEN_ERRORS, in the bin of
   its reference frame). A sampler that declares none costs the step nothing.
3. ``count(...)`` before the resets, for the episodes (and reference segments) that end now, giving
   the per-bin counts ``(episodes, failures)`` of the step as a [2, S] tensor:

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
   ``record(counts)`` after the resets were drawn: with ``update_every="step"`` a sampler that
   declares ``EPISODE_OUTCOMES`` is updated now (the counts all-reduced first under torchrun), as in
   the released code; with ``update_every="iteration"`` the counts wait in a pending total, so the
   sampling distribution does not change within the rollout.
4. ``end_rollout()`` once per PPO iteration, after the rollout (the design's runner hook): every
   per-iteration signal (all-reduced first under torchrun) and, with ``update_every="iteration"``,
   the rollout's ``EPISODE_OUTCOMES``.
5. ``after_evaluation(measure, iterations)`` after each periodic evaluation, on every rank:
   for ``CLIP_OUTCOMES``, rank 0 calls ``measure(sampler.rollout_max_s)`` (the runner's clip
   rollouts) and broadcasts the outcome.

Everything in 1-3 has fixed shapes, writes preallocated buffers in place and never reads values on
the host, so it runs inside the environment's captured CUDA graphs. The per-bin counts are kept for
every sampler (the diagnostics' sampler.parquet): ``pop_counts`` returns (and clears) the counts of
the iteration, summed.
"""

from __future__ import annotations

import math
from typing import Any, Callable, cast

import numpy as np
import torch

from bmimic.sampling.base import ERROR_COMPONENTS, BinSampler, bin_counts
from bmimic.sampling.bins import Layout, attribute, check_attribution, check_failure, failed_mask
from bmimic.sampling.checks import check_choice
from bmimic.sampling.schemas import AccountingConfig
from bmimic.sampling.signals import (
    CLIP_OUTCOMES,
    EPISODE_OUTCOMES,
    EPISODE_RETURNS,
    TRACKING_ERRORS,
    ClipOutcomeSampler,
    Signal,
    declared_signals,
)

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


class SamplerFeedback:
    """Per-env start bins, per-bin counts and the sampler's declared signals, for one training env."""

    def __init__(
        self,
        sampler: BinSampler,
        layout: Layout,
        num_envs: int,
        max_episode_length: int,
        attribution: str = "start",
        failure: str = "short",
        failure_threshold: float = 0.8,
        update_every: str = "iteration",
        device: torch.device | str = "cpu",
        world_size: int | None = None,
    ) -> None:
        check_accounting(AccountingConfig(attribution, failure, failure_threshold, update_every))
        self.sampler = sampler
        self.signals = declared_signals(sampler)
        """What the sampler learns from (its class's `signals`)."""
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
        self.device = dev
        s = layout.num_bins
        self.start_bin = torch.zeros(num_envs, dtype=torch.long, device=dev)
        """The bin each env's current episode started in (written only by start_episodes)."""
        self._pending = torch.zeros(2, s, dtype=torch.float64, device=dev)
        self._iteration = torch.zeros(2, s, dtype=torch.float64, device=dev)
        # Rows: the ERROR_COMPONENTS sums, then the env-steps counted; float64 so that a long
        # rollout's sums of small errors lose nothing.
        self._errors = torch.zeros(len(ERROR_COMPONENTS) + 1, s, dtype=torch.float64, device=dev)
        self._broken_errors = torch.tensor([*BROKEN_ERRORS, 1.0], device=dev)[:, None]  # (+ the step count)
        self._episode_return = torch.zeros(num_envs, dtype=torch.float64, device=dev)
        self._returns = torch.zeros(2, s, dtype=torch.float64, device=dev)  # return sums, episodes

    @classmethod
    def from_config(cls, cfg: AccountingConfig, sampler: BinSampler, layout: Layout, num_envs: int, max_episode_length: int,
                    device: torch.device | str = "cpu", world_size: int | None = None) -> "SamplerFeedback":
        """The feedback `cfg` (`sampler.accounting`) describes, for `num_envs` envs."""
        return cls(sampler, layout, num_envs, max_episode_length, attribution=cfg.attribution, failure=cfg.failure,
                   failure_threshold=cfg.failure_threshold, update_every=cfg.update_every, device=device,
                   world_size=world_size)

    def wants(self, signal: Signal) -> bool:
        """Whether the sampler declared `signal`."""
        return signal in self.signals

    # ------------------------------------------------------------------ in the step
    def draw_bins(self, n: int) -> torch.Tensor:
        """Start bins for `n` worlds, drawn from the sampler's P (LongTensor [n], on its device)."""
        return self.sampler.sample(n)

    def start_episodes(self, mask: torch.Tensor, bins: torch.Tensor) -> None:
        """The masked envs start a new episode in ``bins`` (the bins their start frames were drawn for)."""
        self.start_bin.copy_(torch.where(mask, bins, self.start_bin))

    def measure(self, frames: torch.Tensor, broken: torch.Tensor, dones: torch.Tensor, rewards: torch.Tensor,
                errors: Callable[[], torch.Tensor]) -> None:
        """This step's measurements for the declared per-iteration signals, from what the step knows
        (each env's): ``frames`` the reference frame; ``broken`` reset as broken this step; ``dones``
        the episode ends now; ``rewards`` this step's reward; ``errors()`` the ERROR_COMPONENTS [4, N]
        (computed only when the sampler declares TRACKING_ERRORS). Call it before the resets, while
        each env's start bin is still its finishing episode's."""
        if self.wants(TRACKING_ERRORS):
            e = errors()
            per_env = torch.cat((e, torch.ones_like(e[:1])))  # [components + 1, N]: + the step count
            # where, not a product: a broken world's NaN stays out; it is charged a lost track instead
            per_env = torch.where(broken, self._broken_errors.to(per_env.dtype), per_env)
            self._errors.index_add_(1, self.layout.bins_of(frames), per_env.to(torch.float64))
        if self.wants(EPISODE_RETURNS):
            self._episode_return += rewards
            ended = torch.stack((torch.where(dones, self._episode_return, 0.0), dones.to(torch.float64)))
            self._returns.index_add_(1, self.start_bin, ended)
            self._episode_return.masked_fill_(dones, 0.0)

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

    def record(self, counts: torch.Tensor) -> None:
        """One step's counts: to the sampler now (update_every="step") or at end_rollout."""
        if self.update_every == "step":
            if self.world_size > 1:
                # Several GPUs train one policy: every rank's sampler sees every rank's episodes,
                # so all ranks sample from the same distribution.
                torch.distributed.all_reduce(counts)
            if self.wants(EPISODE_OUTCOMES):
                self.sampler.update_counts(counts[0], counts[1])
            self._iteration += counts
        else:
            self._pending += counts

    # ------------------------------------------------------------------ once per iteration
    def end_rollout(self) -> None:
        """The iteration's signals: the declared per-iteration ones, and the rollout's episode
        outcomes with update_every="iteration"."""
        if self.wants(TRACKING_ERRORS):
            self._deliver(self._errors, TRACKING_ERRORS)
        if self.wants(EPISODE_RETURNS):
            self._deliver(self._returns, EPISODE_RETURNS)
        if self.update_every != "iteration":
            return
        if self.world_size > 1:
            torch.distributed.all_reduce(self._pending)
        if self.wants(EPISODE_OUTCOMES):
            self.sampler.update_counts(self._pending[0], self._pending[1])
        self._iteration += self._pending
        self._pending.zero_()

    def _deliver(self, sums: torch.Tensor, signal: Signal) -> None:
        """One per-iteration signal: its per-bin sums (last row: the count they are over), summed
        over the ranks, to the sampler's method the signal names; then cleared."""
        if self.world_size > 1:
            torch.distributed.all_reduce(sums)
        getattr(self.sampler, signal.receiver)(sums[:-1], sums[-1])
        sums.zero_()

    # ------------------------------------------------------------------ after an evaluation
    def after_evaluation(self, measure: Callable[[Any], torch.Tensor], iterations: int) -> None:
        """Every rank, after each periodic evaluation: for CLIP_OUTCOMES, rank 0's
        ``measure(sampler.rollout_max_s)`` ([C], > 0 where a clip failed), broadcast, to the sampler
        with the ``iterations`` since the previous evaluation."""
        if not self.wants(CLIP_OUTCOMES):
            return
        failed = torch.zeros(self.layout.num_clips, dtype=torch.float32, device=self.device)
        if self.world_size == 1 or torch.distributed.get_rank() == 0:
            failed.copy_(measure(cast(ClipOutcomeSampler, self.sampler).rollout_max_s))
        if self.world_size > 1:
            torch.distributed.broadcast(failed, src=0)
        self.sampler.observe_eval(failed > 0, iterations)

    def pop_counts(self) -> tuple[np.ndarray, np.ndarray]:
        """(episodes, failures) per bin counted since the last pop (summed over the ranks under
        torchrun); one host transfer, then cleared."""
        counts = self._iteration.cpu().numpy().copy()
        self._iteration.zero_()
        return counts[0], counts[1]

    def discard(self) -> None:
        """Forget counts and measurements not yet delivered or popped (the environment's warm-up steps)."""
        self._pending.zero_()
        self._iteration.zero_()
        self._errors.zero_()
        self._returns.zero_()
        self._episode_return.zero_()


__all__ = ["BROKEN_ERRORS", "UPDATE_EVERY", "SamplerFeedback", "check_accounting"]
