"""The config schemas of the sampler group: the keys every variant has (:class:`SamplerConfig`, with
the episode accounting's :class:`AccountingConfig`) and each built-in sampler kind's own parameters.

They live apart from the sampler classes (torch) so that composing a config, `--help`, `--cfg job`
and `python -m bmimic.launch list` need neither torch nor the simulator: importing this module
stores every built-in schema in Hydra's ConfigStore as `sampler/<kind>_schema`. Each class in
:mod:`bmimic.sampling.samplers`, :mod:`bmimic.sampling.peer_errors` and
:mod:`bmimic.sampling.peer_clips` registers with its schema from here (`register_sampler`); the
formulas and the range checks (`check_config`) are beside the classes.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from bmimic.sampling.registry import register_schema


@dataclass
class AccountingConfig:
    """`sampler.accounting`: which bin a finished episode counts for, what counts as a failure and
    when the sampler sees the counts. Every sampler variant has it (the uniform one too: its per-bin
    counts are the diagnostics); the defaults are the design's."""

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


@dataclass
class SamplerConfig:
    """The keys every variant of ``conf/sampler/`` has; each sampler's schema subclasses it."""

    name: str = ""
    """The variant: equals the YAML's file name (adaptive, adaptive_hybrid, beyondmimic, egm, gmt, low_return, phc,
    protomotions, uniform)."""
    kind: str = ""
    """The registered sampler class the variant configures (its schema's default; not set in a YAML)."""
    enabled: bool = True
    """false: draw start bins uniformly (the design's switch back to uniform sampling)."""
    bins: str = "time"
    """Bin layout: "time" = bins of bin_size_seconds; "released" = the released code's
    B = T // 50 + 1 bins over T frames at 50 Hz (bin_size_seconds does not apply)."""
    bin_size_seconds: Optional[float] = 1.0
    """Time bins: length of one bin of the reference motion in seconds (the last may be shorter);
    null with bins=released."""
    clip_balance: str = "bins"
    """With a motion library: "bins" = P over all bins as the sampler computes it (under uniform
    sampling every bin is equal, so long clips get more starts); "clips" = every clip gets the same
    total probability, the sampler's proportions kept within each clip (one clip: no effect)."""
    accounting: AccountingConfig = field(default_factory=AccountingConfig)
    """The episode accounting: attribution, failure rule and update timing (sampler.accounting.*)."""
    log_every: Optional[int] = None
    """sampler.parquet gets one row per bin every this many iterations and at the last one; null:
    1, or thinned to stay under about a million rows when there are more than 1,000 bins."""


@dataclass
class UniformConfig(SamplerConfig):
    """`sampler=uniform`: no parameters of its own."""

    name: str = "uniform"
    kind: str = "uniform"


@dataclass
class AdaptiveConfig(SamplerConfig):
    """Schema of the adaptive sampler's variants; the defaults are the design's (`sampler=adaptive`)."""

    name: str = "adaptive"
    kind: str = "adaptive"
    gamma: float = 0.9
    """Decay of the look-ahead kernel gamma^u, u = 0..K-1, in (0, 1]."""
    lambda_uniform: float = 0.1
    """Share of probability mass spread uniformly, in [0, 1]; P_s >= lambda_uniform/S."""
    K: int = 5
    """Length of the look-ahead kernel in bins (1 = no smoothing across bins)."""
    alpha_smooth: float = 0.1
    """EMA weight of a new failure-rate observation, in (0, 1]."""
    empty_bins: str = "decay"
    """"decay": every update moves every bin (a bin without finished episodes decays towards 0, the
    design's formula); "hold": bins without finished episodes keep their value."""


@dataclass
class BeyondMimicConfig(SamplerConfig):
    """Schema of the released code's sampler; the defaults are the released code's."""

    name: str = "beyondmimic"
    kind: str = "beyondmimic"
    bins: str = "released"
    bin_size_seconds: Optional[float] = None
    gamma: float = 0.8
    """Decay of the look-ahead kernel gamma^u, u = 0..K-1, in (0, 1]."""
    K: int = 1
    """Length of the look-ahead kernel in bins (1 = no smoothing across bins)."""
    alpha: float = 0.001
    """EMA weight of each update's failure histogram, in (0, 1]."""
    uniform_ratio: float = 0.1
    """uniform_ratio/S is added to the EMA counts before smoothing (> 0)."""
    empty_bins: str = "decay"
    """"decay": every update decays every bin (the released code); "hold": bins without finished
    episodes keep their value."""


@dataclass
class EGMConfig(SamplerConfig):
    """`sampler=egm`: EGM's bin-based adaptive sampling from an EMA of a composite tracking error."""

    name: str = "egm"
    kind: str = "egm"
    ema: float = 0.1
    """EMA weight beta of an iteration's mean error in a bin, in (0, 1]."""
    weight_body_pos: float = 1.0
    """Weight of the mean body position error (m) in the composite error, >= 0."""
    weight_body_ori: float = 0.1
    """Weight of the mean body orientation error (rad), >= 0."""
    weight_body_lin_vel: float = 0.1
    """Weight of the mean body linear-velocity error (m/s), >= 0."""
    power_start: float = 0.5
    """Exponent tau of the normalised error at iteration 0 (the paper's "smoothing temperature";
    low = flat), > 0."""
    power_end: float = 2.0
    """Exponent tau after schedule_iterations (high = sharp), > 0."""
    uniform_start: float = 0.5
    """Uniform ratio u at iteration 0, in [0, 1]."""
    uniform_end: float = 0.1
    """Uniform ratio u after schedule_iterations, in [0, 1]."""
    schedule_iterations: Optional[int] = None
    """Iterations over which tau and u move linearly from start to end (>= 1); null: the run's
    max_iterations (the paper's schedule spans training; filled by bmimic.config.resolve_runtime),
    or peer_errors.UNSET_SCHEDULE_ITERATIONS where no run exists (benchmarks, unit tests)."""


@dataclass
class GMTConfig(SamplerConfig):
    """`sampler=gmt`: GMT's completion-level sampling of sub-clips."""

    name: str = "gmt"
    kind: str = "gmt"
    subclip_bins: int = 10
    """Longest sub-clip, in bins (10 = GMT's 10 s at 1 s bins); clips are cut from their start."""
    initial_level: float = 10.0
    """Completion level c of a sub-clip never completed, >= min_level."""
    completion_decay: float = 0.99
    """c is multiplied by this at each completion, in (0, 1]."""
    min_level: float = 1.0
    """Floor of c (a sub-clip at the floor is sampled by its error), > 0."""
    error_scale_m: float = 0.15
    """At the floor, s = min(E / error_scale_m, 1) ^ error_power, E in m; > 0."""
    error_power: float = 5.0
    """See error_scale_m; > 0."""


@dataclass
class LowReturnConfig(SamplerConfig):
    """`sampler=low_return`: start where episodes earn least (the per-bin mean episode return)."""

    name: str = "low_return"
    kind: str = "low_return"
    ema: float = 0.1
    """EMA weight of an iteration's mean return of the episodes started in a bin, in (0, 1]."""
    temperature: float = 1.0
    """Softmax temperature over the negated mean returns (return units), > 0: low = sharp."""
    lambda_uniform: float = 0.1
    """Share of probability mass spread uniformly, in [0, 1]."""


@dataclass
class PHCConfig(SamplerConfig):
    """`sampler=phc`: PHC's evaluation-driven hard-negative mining over clips."""

    name: str = "phc"
    kind: str = "phc"
    mode: str = "soft"
    """"soft" (auto_pmcp_soft, PHC's default): p_m = h_m / sum(h), h the failed evaluations of clip m,
    uniform when the latest evaluation failed no clip; "hard" (auto_pmcp): uniform over the clips that
    failed the latest evaluation."""
    rollout_max_s: Optional[float] = None
    """Seconds of each clip's evaluation rollout from its first frame, > 0; null: to the clip's end
    (PHC evaluates the whole motion)."""


@dataclass
class ProtoMotionsConfig(SamplerConfig):
    """`sampler=protomotions`: ProtoMotions v3's evaluation-driven multiplicative clip weights."""

    name: str = "protomotions"
    kind: str = "protomotions"
    success_decay: float = 0.999
    """d_s: a clip that succeeded an evaluation is multiplied by d_s^K (K iterations since the last), in (0, 1]."""
    failure_decay: float = 0.0
    """d_f: a failed clip is divided by d_f^K; 0 resets it to 1 (every shipped experiment), in [0, 1]."""
    min_weight: Optional[float] = None
    """Floor of every weight, > 0; null: 1 / number of clips (ProtoMotions' default)."""
    rollout_max_s: Optional[float] = 12.0
    """Seconds of each clip's evaluation rollout from its first frame, > 0 (ProtoMotions' max_eval_steps,
    600 steps at its 50 Hz G1 control rate); null: to the clip's end."""


BUILTIN_SCHEMAS = {"uniform": UniformConfig, "adaptive": AdaptiveConfig, "beyondmimic": BeyondMimicConfig,
                   "egm": EGMConfig, "gmt": GMTConfig, "phc": PHCConfig, "protomotions": ProtoMotionsConfig,
                   "low_return": LowReturnConfig}
"""The built-in sampler kinds and their schemas (the classes register with the same ones)."""

for _kind, _schema in BUILTIN_SCHEMAS.items():
    register_schema(_kind, _schema)

__all__ = ["BUILTIN_SCHEMAS", "AccountingConfig", "AdaptiveConfig", "BeyondMimicConfig", "EGMConfig", "GMTConfig",
           "LowReturnConfig", "PHCConfig", "ProtoMotionsConfig", "SamplerConfig", "UniformConfig"]
