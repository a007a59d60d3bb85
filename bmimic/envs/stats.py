"""`IterationStats`: the training environment's per-iteration statistics, accumulated on the device
inside the step and read once per iteration (the per-term ones are the managers', the per-bin
counts the episode accounting's)."""

from __future__ import annotations

import math

import torch

from bmimic.envs.state import TrackingState


class IterationStats:
    """Finished episodes, failures and lengths; broken and overflowed world-steps; tracking errors."""

    def __init__(self, device: torch.device | str) -> None:
        z = lambda: torch.zeros((), device=device)  # noqa: E731
        self.episodes, self.failures, self.length_sum, self.steps = z(), z(), z(), z()
        self.nonfinite, self.out_of_bounds, self.overflow = z(), z(), z()
        self.errors = torch.zeros(3, device=device)  # anchor pos m, body pos m, joint pos rad

    def broken(self, nonfinite: torch.Tensor, out_of_bounds: torch.Tensor, overflowed: torch.Tensor) -> None:
        """World-steps reset as non-finite or beyond bounds, and those whose buffers overflowed."""
        self.overflow += overflowed.sum()
        self.nonfinite += nonfinite.sum()
        self.out_of_bounds += out_of_bounds.sum()

    def step(self, s: TrackingState) -> None:
        """One step's mean tracking errors over the envs."""
        self.steps += 1
        self.errors[0] += (s.ref_anchor_pos - s.robot_anchor_pos).norm(dim=-1).mean()
        self.errors[1] += (s.ref_body_pos_relative - s.robot_body_pos).norm(dim=-1).mean()
        self.errors[2] += (s.ref_joint_pos - s.joint_pos).abs().mean()

    def end_episodes(self, dones: torch.Tensor, terminated: torch.Tensor, length: torch.Tensor) -> None:
        d = dones.float()
        self.episodes += d.sum()
        self.failures += terminated.float().sum()
        self.length_sum += (length.float() * d).sum()

    def pop(self) -> tuple[dict[str, float], dict[str, float], float]:
        """(counts, `metrics/*` mean errors, steps >= 1) of the iteration (one host transfer each);
        then cleared."""
        episodes = float(self.episodes)
        steps = max(float(self.steps), 1.0)
        errs = (self.errors / steps).cpu().numpy()
        counts = {
            "nonfinite_resets": float(self.nonfinite),
            "out_of_bounds_resets": float(self.out_of_bounds),
            "overflow_worlds": float(self.overflow),
            "episodes": episodes,
            "failures": float(self.failures),
            "mean_episode_length": float(self.length_sum) / episodes if episodes else math.nan,
        }
        metrics = {
            "metrics/error_anchor_pos_m": float(errs[0]),
            "metrics/error_body_pos_m": float(errs[1]),
            "metrics/error_joint_pos_rad": float(errs[2]),
        }
        for buf in (self.episodes, self.failures, self.length_sum, self.steps, self.nonfinite, self.out_of_bounds,
                    self.overflow, self.errors):
            buf.zero_()
        return counts, metrics, steps


__all__ = ["IterationStats"]
