"""Adaptive motion sampling: time bins of a motion and the samplers that pick start bins.

See :mod:`bmimic.sampling.samplers` for the formulas, :mod:`bmimic.sampling.bins` for the bin
conventions and episode attribution, :mod:`bmimic.sampling.config` for the options.
"""

from bmimic.sampling.bins import (
    BinLayout,
    attribute,
    bin_edges_s,
    bins_of_time,
    failed_mask,
    num_bins,
    visits_histogram,
)
from bmimic.sampling.config import (
    SamplerConfig,
    SamplerConfigError,
    make_sampler,
    validate_sampler_config,
)
from bmimic.sampling.diagnostics import bin_table, sampling_entropy, summary
from bmimic.sampling.samplers import AdaptiveSampler, BeyondMimicSampler, UniformSampler

__all__ = [
    "AdaptiveSampler",
    "BeyondMimicSampler",
    "BinLayout",
    "SamplerConfig",
    "SamplerConfigError",
    "UniformSampler",
    "attribute",
    "bin_edges_s",
    "bin_table",
    "bins_of_time",
    "failed_mask",
    "make_sampler",
    "num_bins",
    "sampling_entropy",
    "summary",
    "validate_sampler_config",
    "visits_histogram",
]
