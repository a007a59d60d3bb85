"""Adaptive motion sampling: bins of a motion, the samplers that pick start bins, and the
bookkeeping that turns finished episodes into per-bin counts.

See :mod:`bmimic.sampling.samplers` for the formulas, :mod:`bmimic.sampling.bins` for the bin
layouts, :mod:`bmimic.sampling.accounting` for episode attribution and update timing,
:mod:`bmimic.sampling.config` for the options and the named variants.
"""

from bmimic.sampling.accounting import EpisodeAccounting
from bmimic.sampling.bins import (
    BinLayout,
    ReleasedBinLayout,
    attribute,
    bin_edges_s,
    bins_of_time,
    failed_mask,
    make_layout,
    num_bins,
    visits_histogram,
)
from bmimic.sampling.config import (
    SAMPLER_NAMES,
    SamplerConfig,
    SamplerConfigError,
    layout_for,
    load_variant,
    make_sampler,
    validate_sampler_config,
)
from bmimic.sampling.diagnostics import bin_table, sampling_entropy, summary
from bmimic.sampling.samplers import AdaptiveSampler, BeyondMimicSampler, UniformSampler

__all__ = [
    "SAMPLER_NAMES",
    "AdaptiveSampler",
    "BeyondMimicSampler",
    "BinLayout",
    "EpisodeAccounting",
    "ReleasedBinLayout",
    "SamplerConfig",
    "SamplerConfigError",
    "UniformSampler",
    "attribute",
    "bin_edges_s",
    "bin_table",
    "bins_of_time",
    "failed_mask",
    "layout_for",
    "load_variant",
    "make_layout",
    "make_sampler",
    "num_bins",
    "sampling_entropy",
    "summary",
    "validate_sampler_config",
    "visits_histogram",
]
