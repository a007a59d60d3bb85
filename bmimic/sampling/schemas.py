"""The keys every sampler variant has: :class:`SamplerConfig`, which each sampler's config schema
subclasses, and the episode accounting's :class:`AccountingConfig`.

A sampler's own schema sits beside its class, in the sampler's module (bmimic.sampling.samplers,
peer_clips, peer_errors): the one place of its defaults (a docstring under each field) and of their
range rules (its `check`, run once when the config is validated: `validate_sampler_config`). The YAML
variants under ``conf/sampler/`` only select a schema and override some of its values, and the
sampler's constructor takes the validated schema instance. Registering a class stores its schema in
Hydra's ConfigStore as `sampler/<kind>_schema` (bmimic.sampling.registry); the sampler modules import
without torch (they bind it on first use), so composing a config, `--help`, `--cfg job` and
`python -m bmimic.launch list` need neither torch nor the simulator.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional


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


__all__ = ["AccountingConfig", "SamplerConfig"]
