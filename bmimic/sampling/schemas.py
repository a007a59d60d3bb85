"""The config schemas of the sampler group: the keys every variant has (:class:`SamplerConfig`, with
the episode accounting's :class:`AccountingConfig`) and each built-in sampler kind's own parameters.

A schema is the one place of its sampler's defaults (a docstring under each field) and of their range
rules (its `check`, run once when the config is validated: `validate_sampler_config`); the YAML
variants under ``conf/sampler/`` only select a schema and override some of its values, and the
sampler's constructor takes the validated schema instance. The schemas live apart from the sampler
classes (torch) so that composing a config, `--help`, `--cfg job` and `python -m bmimic.launch list`
need neither torch nor the simulator: importing this module stores every built-in schema in Hydra's
ConfigStore as `sampler/<kind>_schema` (`sampler_schema`, which also names the module of its class).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

from bmimic.sampling.checks import (
    check_choice,
    check_fraction,
    check_int_at_least,
    check_nonnegative,
    check_positive,
    fail,
)
from bmimic.sampling.registry import sampler_schema

EMPTY_BINS = ("decay", "hold")
"""`empty_bins` of the look-ahead samplers (adaptive, beyondmimic)."""
PHC_MODES = ("soft", "hard")
"""`mode` of the PHC sampler."""


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
    """The variant: equals its YAML's file name in conf/sampler/ (the schema's default is its kind)."""
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

    def check(self) -> None:
        """Range rules of the sampler's own keys (SamplerConfigError naming the first bad one); the keys
        every variant has are checked by `bmimic.sampling.config.validate_sampler_config`."""


def _check_lookahead(cfg: AdaptiveConfig | BeyondMimicConfig) -> None:
    """The look-ahead kernel's keys, which the adaptive and beyondmimic schemas share (with their own defaults)."""
    check_fraction("gamma", cfg.gamma)
    check_int_at_least("K", cfg.K, 1)
    check_choice("empty_bins", cfg.empty_bins, EMPTY_BINS)


@dataclass
class ClipWeightingConfig(SamplerConfig):
    """Base of the schemas of samplers that weight clips (or sub-clips) themselves: gmt, phc, protomotions."""

    def check(self) -> None:
        if self.clip_balance != "bins":
            fail("clip_balance", f"bins (the {self.kind} sampler weights clips itself)", self.clip_balance)


@sampler_schema("uniform", "bmimic.sampling.samplers")
@dataclass
class UniformConfig(SamplerConfig):
    """`sampler=uniform`: no parameters of its own."""

    name: str = "uniform"
    kind: str = "uniform"


@sampler_schema("adaptive", "bmimic.sampling.samplers")
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

    def check(self) -> None:
        _check_lookahead(self)
        check_fraction("lambda_uniform", self.lambda_uniform, closed_below=True)
        check_fraction("alpha_smooth", self.alpha_smooth)


@sampler_schema("beyondmimic", "bmimic.sampling.samplers")
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

    def check(self) -> None:
        _check_lookahead(self)
        check_fraction("alpha", self.alpha)
        check_positive("uniform_ratio", self.uniform_ratio)


@sampler_schema("egm", "bmimic.sampling.peer_errors")
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

    def check(self) -> None:
        check_fraction("ema", self.ema)
        for key in ("weight_body_pos", "weight_body_ori", "weight_body_lin_vel"):
            check_nonnegative(key, getattr(self, key))
        if self.weight_body_pos + self.weight_body_ori + self.weight_body_lin_vel <= 0:
            fail("weight_body_pos", "weights whose sum is > 0", self.weight_body_pos)
        for key in ("power_start", "power_end"):
            check_positive(key, getattr(self, key))
        for key in ("uniform_start", "uniform_end"):
            check_fraction(key, getattr(self, key), closed_below=True)
        if self.schedule_iterations is not None:
            check_int_at_least("schedule_iterations", self.schedule_iterations, 1)


@sampler_schema("gmt", "bmimic.sampling.peer_errors")
@dataclass
class GMTConfig(ClipWeightingConfig):
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

    def check(self) -> None:
        super().check()
        check_int_at_least("subclip_bins", self.subclip_bins, 1)
        check_fraction("completion_decay", self.completion_decay)
        for key in ("min_level", "error_scale_m", "error_power"):
            check_positive(key, getattr(self, key))
        check_positive("initial_level", self.initial_level)
        if self.initial_level < self.min_level:
            fail("initial_level", f"a number >= min_level ({self.min_level})", self.initial_level)


@sampler_schema("low_return", "bmimic.sampling.samplers")
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

    def check(self) -> None:
        check_fraction("ema", self.ema)
        check_positive("temperature", self.temperature)
        check_fraction("lambda_uniform", self.lambda_uniform, closed_below=True)


@sampler_schema("phc", "bmimic.sampling.peer_clips")
@dataclass
class PHCConfig(ClipWeightingConfig):
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

    def check(self) -> None:
        super().check()
        check_choice("mode", self.mode, PHC_MODES)
        if self.rollout_max_s is not None:
            check_positive("rollout_max_s", self.rollout_max_s)


@sampler_schema("protomotions", "bmimic.sampling.peer_clips")
@dataclass
class ProtoMotionsConfig(ClipWeightingConfig):
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

    def check(self) -> None:
        super().check()
        check_fraction("success_decay", self.success_decay)
        check_fraction("failure_decay", self.failure_decay, closed_below=True)
        if self.min_weight is not None:
            check_positive("min_weight", self.min_weight)
        if self.rollout_max_s is not None:
            check_positive("rollout_max_s", self.rollout_max_s)



__all__ = ["EMPTY_BINS", "PHC_MODES", "AccountingConfig", "AdaptiveConfig", "BeyondMimicConfig", "ClipWeightingConfig",
           "EGMConfig", "GMTConfig", "LowReturnConfig", "PHCConfig", "ProtoMotionsConfig", "SamplerConfig",
           "UniformConfig"]
