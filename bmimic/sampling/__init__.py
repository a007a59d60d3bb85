"""Adaptive motion sampling: bins of a motion, the samplers that pick start bins (a registry of
classes, each with its config schema), and the episode accounting that turns finished episodes into
per-bin counts.

See :mod:`bmimic.sampling.samplers` for the formulas, :mod:`bmimic.sampling.registry` for how a
sampler is registered, :mod:`bmimic.sampling.bins` for the bin layouts,
:mod:`bmimic.sampling.accounting` for episode attribution and update timing,
:mod:`bmimic.sampling.config` for the options and the named variants. Importing the package
registers the built-in samplers.
"""

from bmimic.sampling.accounting import AccountingConfig, EpisodeAccounting
from bmimic.sampling.base import BinSampler, bin_counts
from bmimic.sampling.bins import (
    BinLayout,
    ReleasedBinLayout,
    attribute,
    bin_edges_s,
    bins_of_time,
    failed_mask,
    num_bins,
    visits_histogram,
)
from bmimic.sampling.checks import SamplerConfigError
from bmimic.sampling.clips import ClipLayout
from bmimic.sampling.config import (
    SamplerConfig,
    layout_for,
    load_variant,
    make_sampler,
    sampler_config,
    validate_sampler_config,
    variant_names,
)
from bmimic.sampling.diagnostics import bin_table, sampling_entropy, summary
from bmimic.sampling.layouts import make_layout
from bmimic.sampling.peer_clips import PHCSampler, ProtoMotionsSampler
from bmimic.sampling.peer_errors import EGMSampler, GMTSampler
from bmimic.sampling.registry import SAMPLERS, register_sampler
from bmimic.sampling.samplers import (
    AdaptiveConfig,
    AdaptiveSampler,
    BeyondMimicConfig,
    BeyondMimicSampler,
    UniformConfig,
    UniformSampler,
)

__all__ = [
    "SAMPLERS",
    "AccountingConfig",
    "AdaptiveConfig",
    "AdaptiveSampler",
    "BeyondMimicConfig",
    "BeyondMimicSampler",
    "BinLayout",
    "BinSampler",
    "EGMSampler",
    "EpisodeAccounting",
    "GMTSampler",
    "PHCSampler",
    "ProtoMotionsSampler",
    "ReleasedBinLayout",
    "SamplerConfig",
    "SamplerConfigError",
    "UniformConfig",
    "UniformSampler",
    "attribute",
    "bin_counts",
    "bin_edges_s",
    "bin_table",
    "bins_of_time",
    "failed_mask",
    "layout_for",
    "load_variant",
    "ClipLayout",
    "make_layout",
    "make_sampler",
    "num_bins",
    "register_sampler",
    "sampler_config",
    "sampling_entropy",
    "summary",
    "validate_sampler_config",
    "variant_names",
    "visits_histogram",
]
