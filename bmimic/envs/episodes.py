"""Who starts and ends a TrackingEnv's episodes: the one place where training and evaluation differ.

The env asks its episodes object and never its mode: `SampledEpisodes` (training: the sampler draws the
starts and is told what ended) or `PlacedEpisodes` (evaluation: the caller places the worlds; perturbed
or not).
"""

from __future__ import annotations

from typing import Any

import torch

from bmimic.envs.resets import write_reference_state
from bmimic.envs.state import tracking_errors
from bmimic.sampling.bins import Layout
from bmimic.sampling.feedback import SamplerFeedback

TrackingEnv = Any
"""The env these objects serve (bmimic.envs.tracking_env.TrackingEnv, which imports this module: not
imported here, so that the floor keeps no cycle)."""


class SampledEpisodes:
    """Training: episodes start where the sampler of `feedback` draws, and end into its counts."""

    perturbed = True
    """Events (domain randomisation, pushes) and observation noise are on."""
    places_worlds = False
    """Whether the caller places the worlds (evaluation) instead of the sampler."""

    def __init__(self, feedback: SamplerFeedback) -> None:
        self.feedback = feedback
        self.layout: Layout = feedback.layout

    def kinematics_after_step(self, env: TrackingEnv) -> bool:
        """Whether the step recomputes kinematics after its state writes (resets move worlds every step)."""
        return True

    def begin(self, env: TrackingEnv) -> None:
        """Every world starts at a sampled frame; the runner never calls reset."""
        self.start(env, mask=env._ones, new_episode=env._ones)
        env.events.reset(env, env._ones)

    def start(self, env: TrackingEnv, mask: torch.Tensor, new_episode: torch.Tensor) -> None:
        """Masked worlds start a reference segment at a frame the sampler draws, with RSI noise; those
        also in `new_episode` start an episode there (a clip-end resample keeps the episode's start bin)."""
        bins = self.feedback.draw_bins(env.num_envs)
        frames = env.segments.start(mask, self.layout.sample_frames(bins))
        self.feedback.start_episodes(mask & new_episode, bins)
        write_reference_state(env.sim, env.reference, mask, frames, env.cfg.reset, env.uniform,
                              env.soft_joint_limits)

    def end_step(self, env: TrackingEnv, dones: torch.Tensor, terminated: torch.Tensor,
                 broken: torch.Tensor) -> None:
        """Count what ended for the sampler, restart finished worlds, resample at clip ends, run events."""
        feedback = self.feedback
        state = env.state  # the errors are computed only for a sampler that declares them
        feedback.measure(env.time_steps, broken, dones, env.rew_buf, lambda: tracking_errors(state))
        env.stats.end_episodes(dones, terminated | broken, env.episode_length_buf)
        env.rewards.end_episodes(dones)
        # What ends now, counted in one pass: finished episodes (at this frame) and, for
        # attribution=failure, continuing episodes whose clip ends on the next frame.
        clip_end, end_frames = env.segments.ending(dones)
        counts = feedback.count(dones=dones, clip_end=clip_end, end_frames=end_frames,
                                segment_start=env.segment_start, terminated=terminated, broken=broken,
                                episode_length=env.episode_length_buf)
        self.start(env, mask=dones, new_episode=dones)
        env.episode_length_buf.masked_fill_(dones, 0)
        env.actions.masked_fill_(dones[:, None], 0.0)
        env.last_actions.masked_fill_(dones[:, None], 0.0)
        # End of the clip mid-episode: resample and teleport; the episode continues. This also
        # catches a reset that started on the clip's last frame: that episode has not tracked a
        # frame yet, so it starts (and counts for) the bin drawn now.
        self.start(env, mask=env.segments.advance(), new_episode=dones)
        # After this step's resets were drawn, as in the released code: the sampler update
        # (update_every=step), or the counts wait for end_rollout (update_every=iteration).
        feedback.record(counts)
        env.events.reset(env, dones)
        env.events.interval(env, env.step_dt)

    def end_rollout(self) -> None:
        """The sampler update of update_every=iteration (the design's runner hook)."""
        self.feedback.end_rollout()

    def pop_counts(self) -> tuple:
        """Per bin, as the sampler was fed them (after end_rollout for update_every=iteration)."""
        return self.feedback.pop_counts()


class PlacedEpisodes:
    """Evaluation: the caller places the worlds and reads the terminations; nothing is sampled."""

    places_worlds = True

    def __init__(self, robust: bool, layout: Layout | None) -> None:
        self.perturbed = robust
        """Events and observation noise as in training (robust evaluation), else none."""
        self.feedback: SamplerFeedback | None = None
        self.layout = layout
        """For the exported metadata only."""

    def kinematics_after_step(self, env: TrackingEnv) -> bool:
        """Only pushes move a world after physics here."""
        return env.events.has_interval

    def begin(self, env: TrackingEnv) -> None:
        """Every world at the first frame, until the caller places it."""
        env.reset_to_frames(torch.zeros(env.num_envs, dtype=torch.long, device=env.device))

    def end_step(self, env: TrackingEnv, dones: torch.Tensor, terminated: torch.Tensor,
                 broken: torch.Tensor) -> None:
        """The reference stops at each clip's end; pushes in a robust evaluation."""
        env.segments.advance_to_clip_end()
        if env.events.has_interval:
            env.events.interval(env, env.step_dt)

    def end_rollout(self) -> None:
        """Nothing to update."""

    def pop_counts(self) -> tuple:
        return None, None


Episodes = SampledEpisodes | PlacedEpisodes
"""What a TrackingEnv asks about its episodes."""
