"""Sampler options (the Hydra group ``sampler``), their validation, and the sampler factory.

Every field of :class:`SamplerConfig` is set by each YAML under ``conf/sampler/`` so sweeps can
override any of them, e.g. ``sampler.gamma=0.5,0.8,0.9``. Fields a sampler does not use are
still validated, so a sweep never silently carries a nonsensical value.

Which fields each sampler reads:

=============  ==========================================================================
uniform        ``bin_size_seconds`` (bins are still used for diagnostics)
adaptive       ``bin_size_seconds, gamma, lambda_uniform, K, alpha_smooth``
beyondmimic    ``bin_size_seconds, gamma, K, alpha, uniform_ratio``
=============  ==========================================================================

``attribution``, ``failure`` and ``failure_threshold`` decide how the environment turns finished
episodes into per-bin counts (see :func:`bmimic.sampling.bins.attribute` and
:func:`bmimic.sampling.bins.failed_mask`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from bmimic import BmimicError

SAMPLER_NAMES = ("uniform", "adaptive", "beyondmimic")
ATTRIBUTIONS = ("failure", "start")
FAILURES = ("terminated", "short")


class SamplerConfigError(BmimicError, ValueError):
    """A sampler option, or a sampler input that depends on one, is invalid."""


@dataclass
class SamplerConfig:
    name: str = "adaptive"
    """Which sampler: "uniform", "adaptive" (paper form) or "beyondmimic" (released-code form)."""

    bin_size_seconds: float = 1.0
    """Length of one time bin of the reference motion, in seconds (the last bin may be shorter)."""

    gamma: float = 0.8
    """Decay of the look-ahead kernel gamma^u, u = 0..K-1, in (0, 1]."""

    lambda_uniform: float = 0.1
    """Adaptive sampler: share of probability mass spread uniformly, in [0, 1]; P_s >= lambda_uniform/S."""

    K: int = 3
    """Length of the look-ahead kernel in bins (1 = no smoothing across bins)."""

    alpha_smooth: float = 0.1
    """Adaptive sampler: EMA weight of a new failure-rate observation, in (0, 1]."""

    attribution: str = "failure"
    """Which bin an episode is charged to: "failure" = the bin of the frame where it ended (every bin
    it passed through counts as visited), "start" = the bin it started in."""

    failure: str = "terminated"
    """What counts as a failed episode: "terminated" = any termination other than a time-out,
    "short" = a termination before failure_threshold x the max episode length (episode length <
    failure_threshold x max length; time-outs and clip ends never fail)."""

    failure_threshold: float = 0.8
    """For failure="short": fraction of the max episode length below which an episode failed, in (0, 1]."""

    alpha: float = 0.001
    """BeyondMimic sampler: EMA weight of each update's failure histogram, in (0, 1]."""

    uniform_ratio: float = 0.1
    """BeyondMimic sampler: uniform_ratio/S is added to the EMA counts before smoothing (> 0)."""


def _fail(key: str, rule: str, value: Any) -> None:
    raise SamplerConfigError(f"sampler.{key} must be {rule}, got {value!r}")


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


# Range checks shared by validate_sampler_config and the sampler constructors, so a bad value
# gets the same message whichever way it arrives. Comparisons are written `not (lo < x <= hi)`
# so that NaN fails them.
def check_gamma(gamma: float) -> None:
    if not (_is_number(gamma) and 0.0 < gamma <= 1.0):
        _fail("gamma", "in (0, 1]", gamma)


def check_K(K: int) -> None:
    if not (isinstance(K, int) and not isinstance(K, bool) and K >= 1):
        _fail("K", "an integer >= 1", K)


def check_lambda_uniform(lambda_uniform: float) -> None:
    if not (_is_number(lambda_uniform) and 0.0 <= lambda_uniform <= 1.0):
        _fail("lambda_uniform", "in [0, 1]", lambda_uniform)


def check_alpha_smooth(alpha_smooth: float) -> None:
    if not (_is_number(alpha_smooth) and 0.0 < alpha_smooth <= 1.0):
        _fail("alpha_smooth", "in (0, 1]", alpha_smooth)


def check_alpha(alpha: float) -> None:
    if not (_is_number(alpha) and 0.0 < alpha <= 1.0):
        _fail("alpha", "in (0, 1]", alpha)


def check_uniform_ratio(uniform_ratio: float) -> None:
    if not (_is_number(uniform_ratio) and 0.0 < uniform_ratio < math.inf):
        _fail("uniform_ratio", "a finite number > 0", uniform_ratio)


def check_bin_size(bin_size_seconds: float, motion_duration_s: float) -> None:
    if not (_is_number(bin_size_seconds) and 0.0 < bin_size_seconds < math.inf):
        _fail("bin_size_seconds", "a finite number > 0", bin_size_seconds)
    if bin_size_seconds > motion_duration_s:
        _fail("bin_size_seconds", f"<= the motion duration ({motion_duration_s:g} s)", bin_size_seconds)


def check_attribution(attribution: str) -> None:
    if attribution not in ATTRIBUTIONS:
        _fail("attribution", f"one of {', '.join(ATTRIBUTIONS)}", attribution)


def check_failure(failure: str, failure_threshold: float) -> None:
    if failure not in FAILURES:
        _fail("failure", f"one of {', '.join(FAILURES)}", failure)
    if not (_is_number(failure_threshold) and 0.0 < failure_threshold <= 1.0):
        _fail("failure_threshold", "in (0, 1]", failure_threshold)


def validate_sampler_config(cfg: Any, motion_duration_s: float) -> None:
    """Check every field of a sampler config (a :class:`SamplerConfig` or the composed Hydra node).

    Raises :class:`SamplerConfigError` with a one-line message naming the first bad key.
    """
    if cfg.name not in SAMPLER_NAMES:
        _fail("name", f"one of {', '.join(SAMPLER_NAMES)}", cfg.name)
    check_bin_size(cfg.bin_size_seconds, motion_duration_s)
    check_gamma(cfg.gamma)
    check_lambda_uniform(cfg.lambda_uniform)
    check_K(cfg.K)
    check_alpha_smooth(cfg.alpha_smooth)
    check_alpha(cfg.alpha)
    check_uniform_ratio(cfg.uniform_ratio)
    check_attribution(cfg.attribution)
    check_failure(cfg.failure, cfg.failure_threshold)


def make_sampler(cfg: Any, num_bins: int, device: Any = "cpu"):
    """Build the sampler ``cfg.name`` over ``num_bins`` bins on ``device``."""
    # Imported here because the samplers import this module's range checks.
    from bmimic.sampling.samplers import AdaptiveSampler, BeyondMimicSampler, UniformSampler

    if cfg.name == "uniform":
        return UniformSampler(num_bins, device=device)
    if cfg.name == "adaptive":
        return AdaptiveSampler(
            num_bins,
            gamma=cfg.gamma,
            lambda_uniform=cfg.lambda_uniform,
            K=cfg.K,
            alpha_smooth=cfg.alpha_smooth,
            device=device,
        )
    if cfg.name == "beyondmimic":
        return BeyondMimicSampler(
            num_bins,
            gamma=cfg.gamma,
            K=cfg.K,
            alpha=cfg.alpha,
            uniform_ratio=cfg.uniform_ratio,
            device=device,
        )
    _fail("name", f"one of {', '.join(SAMPLER_NAMES)}", cfg.name)
