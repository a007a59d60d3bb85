r"""What a sampler may learn from: the signals, their cadences and the sampler methods that receive
them. :class:`bmimic.sampling.feedback.SamplerFeedback` measures and delivers them. Torch-free, so that
a sampler's module (its schema and its class) imports before a config is composed without torch.

A sampler class lists what it learns from in ``signals`` (a tuple of :class:`Signal`); the feedback
delivers each to the sampler method the signal names, and nothing else: no per-signal flags, no
caller reaching through the environment for the sampler. The signals:

============================  ===========================  ======================================================
signal                        cadence                      delivered as
============================  ===========================  ======================================================
``EPISODE_OUTCOMES``          ``sampler.accounting.        ``update_counts(episodes [S], failures [S])``: finished
                              update_every`` (step or      episodes and failures per bin, attributed and judged
                              iteration)                   by ``sampler.accounting``
``TRACKING_ERRORS``           iteration                    ``update_errors(sums [4, S], steps [S])``: sums of the
                                                           per-step ERROR_COMPONENTS over the env-steps at a frame
                                                           of each bin, and their number
``CLIP_OUTCOMES``             evaluation                   ``observe_eval(failed [C], iterations)``: whether one
                                                           rollout per clip from its first frame failed
``EPISODE_RETURNS``           iteration                    ``update_returns(sums [1, S], episodes [S])``: the
                                                           returns of the finished episodes per start bin
============================  ===========================  ======================================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from bmimic.sampling.checks import SamplerConfigError

if TYPE_CHECKING:
    from bmimic.sampling.base import BinSampler

CONFIGURED, ITERATION, EVALUATION = "sampler.accounting.update_every", "iteration", "evaluation"
"""Cadences: the accounting's (every control step or every iteration), once per PPO iteration after
the rollout, after each periodic evaluation."""


@dataclass(frozen=True)
class Signal:
    """Something a sampler may learn from, and how it is delivered."""

    name: str
    """What it is called in messages."""
    cadence: str
    """When it is delivered: CONFIGURED, ITERATION or EVALUATION."""
    receiver: str
    """The BinSampler method that receives it."""
    learner: str
    """The method a sampler that declares it implements: the receiver, or for episode outcomes `_update`,
    which BinSampler.update_counts calls after checking the counts. BinSampler's own does nothing."""


EPISODE_OUTCOMES = Signal("episode outcomes", CONFIGURED, "update_counts", "_update")
TRACKING_ERRORS = Signal("tracking errors", ITERATION, "update_errors", "update_errors")
CLIP_OUTCOMES = Signal("clip outcomes", EVALUATION, "observe_eval", "observe_eval")
EPISODE_RETURNS = Signal("episode returns", ITERATION, "update_returns", "update_returns")
"""Per start bin, the summed return of the episodes that finished in the iteration and their number:
``update_returns(sums [1, S], episodes [S])``."""
SIGNALS = (EPISODE_OUTCOMES, TRACKING_ERRORS, CLIP_OUTCOMES, EPISODE_RETURNS)


class ClipOutcomeSampler(Protocol):
    """What CLIP_OUTCOMES reads of its sampler besides the receiver."""

    rollout_max_s: float | None
    """How long the evaluation's rollout from each clip's first frame may run, s (None: to its end)."""


def declared_signals(sampler: BinSampler | type[BinSampler]) -> tuple[Signal, ...]:
    """The signals a sampler (class or instance) declares, checked: known, with their receiver, and
    learned from (the sampler's class implements the signal's `learner`, not only BinSampler's default)."""
    from bmimic.sampling.base import BinSampler  # torch-free at import, as this module

    cls = sampler if isinstance(sampler, type) else type(sampler)
    signals = tuple(getattr(sampler, "signals", ()))
    for s in signals:
        if s not in SIGNALS or not callable(getattr(sampler, s.receiver, None)):
            raise SamplerConfigError(f"sampler {getattr(sampler, 'kind', sampler)!r} declares {s!r}, which is not "
                                     "a signal of bmimic.sampling.signals with its receiver method")
        if getattr(cls, s.learner, None) is getattr(BinSampler, s.learner, None):
            raise SamplerConfigError(f"sampler {getattr(sampler, 'kind', cls.__name__)!r} declares {s.name} but does "
                                     f"not implement {s.learner}, so it would never learn from them")
    return signals


def learns_from_evaluations(sampler: BinSampler | type[BinSampler]) -> bool:
    """Whether a sampler (class or instance) declares a signal delivered after each evaluation."""
    return any(s.cadence == EVALUATION for s in declared_signals(sampler))


__all__ = ["CLIP_OUTCOMES", "CONFIGURED", "EPISODE_OUTCOMES", "EPISODE_RETURNS", "EVALUATION", "ITERATION", "SIGNALS",
           "TRACKING_ERRORS", "ClipOutcomeSampler", "Signal", "declared_signals", "learns_from_evaluations"]
