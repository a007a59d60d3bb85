"""Sampler options (the Hydra group ``sampler``), their validation, and the factories.

Each YAML under ``conf/sampler/`` is a named variant; its ``name`` equals its file name and decides
the sampler class (:data:`SAMPLER_CLASSES`). Every variant sets every field of
:class:`SamplerConfig`, so any design choice can be overridden on any variant, one at a time
(``sampler=adaptive sampler.attribution=failure``). Fields a variant does not use are still
validated, so a sweep never silently carries a nonsensical value.

=================  ==================  ========================================================
variant (name)     class               what it is
=================  ==================  ========================================================
adaptive           AdaptiveSampler     the design (the schema defaults below)
adaptive_hybrid    AdaptiveSampler     the earlier ``adaptive``: the design's formulas with the
                                       released code's bookkeeping (results in docs/results)
beyondmimic        BeyondMimicSampler  the released code, its bins included
uniform            UniformSampler      uniform start bins (the baseline)
=================  ==================  ========================================================

Which fields each part reads:

- the sampler class: ``gamma, K, empty_bins`` and ``lambda_uniform, alpha_smooth`` (adaptive) or
  ``alpha, uniform_ratio`` (beyondmimic); the uniform sampler reads none;
- the bin layout (:func:`bmimic.sampling.bins.make_layout`): ``bins`` and, for time bins,
  ``bin_size_seconds``;
- the episode accounting (:class:`bmimic.sampling.accounting.EpisodeAccounting`): ``attribution,
  failure, failure_threshold, update_every`` (for every sampler, uniform included, since the
  per-bin counts are also the diagnostics);
- the trainer: ``log_every``.

``enabled: false`` draws start bins uniformly whatever the variant (the design's switch back to
uniform sampling); the run then equals ``sampler=uniform`` except for the recorded name.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any, Optional

from bmimic.sampling.accounting import UPDATE_EVERY
from bmimic.sampling.bins import (
    LAYOUTS,
    Layout,
    check_attribution,
    check_bin_size,
    check_failure,
    make_layout,
)
from bmimic.sampling.samplers import (
    AdaptiveSampler,
    BeyondMimicSampler,
    SamplerConfigError,
    UniformSampler,
    check_choice,
    fail,
)

SAMPLER_CLASSES = {
    "adaptive": AdaptiveSampler,
    "adaptive_hybrid": AdaptiveSampler,
    "beyondmimic": BeyondMimicSampler,
    "uniform": UniformSampler,
}
"""Variant name (= YAML file name) -> sampler class."""
SAMPLER_NAMES = tuple(SAMPLER_CLASSES)


@dataclass
class SamplerConfig:
    """The schema of ``conf/sampler/*.yaml``; its defaults are the design (``sampler=adaptive``)."""

    name: str = "adaptive"
    """The variant: adaptive (the design), adaptive_hybrid, beyondmimic (released code) or uniform;
    equals the YAML's file name and decides the sampler class."""

    enabled: bool = True
    """false: draw start bins uniformly (the design's switch back to uniform sampling)."""

    bins: str = "time"
    """Bin layout: "time" = bins of bin_size_seconds; "released" = the released code's
    B = T // 50 + 1 bins over T frames at 50 Hz (bin_size_seconds does not apply)."""

    bin_size_seconds: Optional[float] = 1.0
    """Time bins: length of one bin of the reference motion in seconds (the last may be shorter);
    null with bins=released."""

    gamma: float = 0.9
    """Decay of the look-ahead kernel gamma^u, u = 0..K-1, in (0, 1]."""

    lambda_uniform: float = 0.1
    """Adaptive sampler: share of probability mass spread uniformly, in [0, 1]; P_s >= lambda_uniform/S."""

    K: int = 5
    """Length of the look-ahead kernel in bins (1 = no smoothing across bins)."""

    alpha_smooth: float = 0.1
    """Adaptive sampler: EMA weight of a new failure-rate observation, in (0, 1]."""

    empty_bins: str = "decay"
    """"decay": every update moves every bin (a bin without finished episodes decays towards 0, the
    design's formula); "hold": bins without finished episodes keep their value."""

    alpha: float = 0.001
    """BeyondMimic sampler: EMA weight of each update's failure histogram, in (0, 1]."""

    uniform_ratio: float = 0.1
    """BeyondMimic sampler: uniform_ratio/S is added to the EMA counts before smoothing (> 0)."""

    attribution: str = "start"
    """Which bin a finished episode counts for: "start" = the bin it started in (kept through
    clip-end resamples); "failure" = every bin its reference segment passed through counts a visit
    and a failure counts in the bin where it ended (rate = failures per visit)."""

    failure: str = "short"
    """What counts as a failed episode: "short" = ended by a termination before failure_threshold x
    the max episode length; "terminated" = any termination (time-outs never fail)."""

    failure_threshold: float = 0.8
    """For failure="short": fraction of the max episode length below which a termination is a
    failure, in (0, 1]."""

    update_every: str = "iteration"
    """"iteration": one sampler update per PPO iteration, after the rollout, from every episode that
    finished during it; "step": one update per control step (the released code)."""

    log_every: Optional[int] = None
    """sampler.parquet gets one row per bin every this many iterations and at the last one; null:
    1, or thinned to stay under about a million rows when there are more than 1,000 bins."""


def validate_sampler_config(cfg: Any, motion_duration_s: float | None = None) -> None:
    """Check every field of a sampler config (a :class:`SamplerConfig` or the composed Hydra node).

    Raises :class:`SamplerConfigError` with a one-line message naming the first bad key.
    """
    check_choice("name", cfg.name, SAMPLER_NAMES)
    if not isinstance(cfg.enabled, bool):
        fail("enabled", "true or false", cfg.enabled)
    check_choice("bins", cfg.bins, LAYOUTS)
    if cfg.bins == "time" or cfg.bin_size_seconds is not None:
        check_bin_size(cfg.bin_size_seconds, motion_duration_s if cfg.bins == "time" else None)
    for cls in dict.fromkeys(SAMPLER_CLASSES.values()):
        cls.check_config(cfg)
    check_attribution(cfg.attribution)
    check_failure(cfg.failure, cfg.failure_threshold)
    check_choice("update_every", cfg.update_every, UPDATE_EVERY)
    if cfg.log_every is not None and not (isinstance(cfg.log_every, int) and not isinstance(cfg.log_every, bool)
                                          and cfg.log_every >= 1):
        fail("log_every", "an integer >= 1 or null", cfg.log_every)


def make_sampler(cfg: Any, num_bins: int, device: Any = "cpu"):
    """Build the sampler of variant ``cfg.name`` over ``num_bins`` bins on ``device`` (uniform
    when ``cfg.enabled`` is false)."""
    check_choice("name", cfg.name, SAMPLER_NAMES)
    cls = SAMPLER_CLASSES[cfg.name] if getattr(cfg, "enabled", True) is not False else UniformSampler
    return cls.from_config(cfg, num_bins, device)


def layout_for(cfg: Any, num_frames: int, fps: float, device: Any = "cpu") -> Layout:
    """The bin layout ``cfg.bins`` of a motion of ``num_frames`` frames at ``fps``."""
    return make_layout(cfg.bins, num_frames, fps, cfg.bin_size_seconds, device=device)


def min_motion_bin_s(cfg: Any) -> float:
    """The bin size a motion must be at least two of (0 with the released layout, whose bin count
    follows the motion)."""
    return float(cfg.bin_size_seconds) if cfg.bins == "time" else 0.0


def describe(cfg: Any, layout: Layout, sampler: Any) -> list[str]:
    """The lines the run's log gets: the variant and every sampler value in force."""
    lines = []
    name = cfg.name
    if cfg.enabled is False:
        lines.append(f"sampler {name}: sampler.enabled=false, so start bins are drawn uniformly "
                     "(as sampler=uniform; the values below only shape the per-bin diagnostics)")
    hp = " ".join(f"{k}={v}" for k, v in sampler.hparams().items())
    lines.append(
        f"sampler {name} ({type(sampler).__name__}): {layout.describe()}; {hp + '; ' if hp else ''}"
        f"attribution={cfg.attribution} failure={cfg.failure}"
        f"{f' failure_threshold={cfg.failure_threshold:g}' if cfg.failure == 'short' else ''} "
        f"update_every={cfg.update_every} log_every={'null' if cfg.log_every is None else cfg.log_every}"
    )
    if cfg.bins == "released" and cfg.bin_size_seconds is not None:
        lines.append(f"sampler.bin_size_seconds={cfg.bin_size_seconds:g} does not apply to the released bins "
                     f"(sampler.bins=released: {layout.num_bins} bins from the motion's length); ignored")
    return lines


def load_variant(name: str) -> SamplerConfig:
    """The named variant ``conf/sampler/<name>.yaml`` as a :class:`SamplerConfig` (without Hydra)."""
    from omegaconf import OmegaConf

    from bmimic import CONF_DIR

    check_choice("name", name, SAMPLER_NAMES)
    node = OmegaConf.load(CONF_DIR / "sampler" / f"{name}.yaml")
    node.pop("defaults", None)
    return OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(SamplerConfig), node))


def default_values() -> dict[str, Any]:
    """The schema's defaults, field by field."""
    return {f.name: f.default for f in fields(SamplerConfig)}


__all__ = [
    "SAMPLER_CLASSES",
    "SAMPLER_NAMES",
    "SamplerConfig",
    "SamplerConfigError",
    "default_values",
    "describe",
    "layout_for",
    "load_variant",
    "make_sampler",
    "min_motion_bin_s",
    "validate_sampler_config",
]
