"""When the training loop hands off to its parts: the periodic evaluation (with the sampler's
evaluation feedback) and the periodic checkpoint."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Schedule:
    """Iteration counts after which the loop evaluates and checkpoints."""

    eval_every: int
    """eval.every_iters: evaluate after every this many iterations (0: never during training)."""
    save_every: int
    """ppo.save_interval: a checkpoint after every this many iterations (the run's last one is its
    caller's, after the final evaluation)."""

    def evaluates(self, iteration: int) -> bool:
        """Whether the loop evaluates after `iteration` iterations."""
        return bool(self.eval_every) and iteration % self.eval_every == 0

    def checkpoints(self, iteration: int, last: bool) -> bool:
        """Whether the loop checkpoints after `iteration` iterations (never after the last)."""
        return iteration % self.save_every == 0 and not last


__all__ = ["Schedule"]
