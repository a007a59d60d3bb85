"""When the training loop hands off to its parts: the periodic evaluation (with the sampler's
evaluation feedback), the whole-clip evaluation after it, and the periodic checkpoint."""

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


@dataclass
class WholeClipSchedule:
    """When a whole-clip evaluation follows a window evaluation (eval.whole_clip): once the windows reached
    `after_success` (then for good), after every `every` iterations, and whenever all evaluations, this
    one included, stay within `max_share` of the wall time since the first iteration."""

    every: int
    """eval.whole_clip.every_iters (0: no fixed cadence)."""
    max_share: float | None
    """eval.whole_clip.max_share (None: no share rule)."""
    after_success: float | None
    """eval.whole_clip.after_success (None: open from the start)."""
    opened: bool = False
    """The windows have reached `after_success` (a resume reopens it from the run's whole-clip rows)."""

    def due(self, iteration: int, window_success: float, evaluation_s: float, elapsed_s: float,
            estimate_s: float) -> bool:
        """Whether to evaluate whole clips now, after the window evaluation at `iteration` that scored
        `window_success`: `evaluation_s` of evaluations so far in `elapsed_s` of wall time since the first
        iteration, and a whole-clip evaluation expected to take `estimate_s`."""
        self.opened = self.opened or self.after_success is None or window_success >= self.after_success
        if not self.opened:
            return False
        if self.every and iteration % self.every == 0:
            return True
        return self.max_share is not None and evaluation_s + estimate_s <= self.max_share * (elapsed_s + estimate_s)


def whole_clip_wanted(cfg) -> bool:
    """Whether training evaluates whole clips (eval.whole_clip: a cadence, a share or at the end)."""
    w = cfg.eval.whole_clip
    return bool(w.every_iters) or w.max_share is not None or bool(w.at_end)


__all__ = ["Schedule", "WholeClipSchedule", "whole_clip_wanted"]
