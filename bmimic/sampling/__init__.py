"""Adaptive motion sampling: bins of a motion, the samplers that pick start bins (a registry of
classes, each with its config schema), and the episode accounting that turns finished episodes into
per-bin counts.

See :mod:`bmimic.sampling.samplers` for the formulas, :mod:`bmimic.sampling.registry` for how a
sampler is registered, :mod:`bmimic.sampling.bins` for the bin layouts,
:mod:`bmimic.sampling.signals` for the signals samplers learn from, :mod:`bmimic.sampling.feedback` for
episode attribution and update timing,
:mod:`bmimic.sampling.config` for the options and the named variants.

Importing the package registers the built-in samplers (the modules of ``registry.BUILT_IN``: each
sampler's schema and class, torch bound on first use, so that composing a config needs no torch); the
first use of any other name loads its module (torch). The sampler classes (``AdaptiveSampler``, ...) and
``SAMPLERS`` come from the registry.
"""

import importlib
from typing import Any

from bmimic.sampling.checks import SamplerConfigError
from bmimic.sampling.registry import BUILT_IN, SAMPLERS, register_sampler
from bmimic.sampling.schemas import SamplerConfig

for _module in BUILT_IN:
    importlib.import_module(_module)  # registers its samplers
from bmimic.sampling.samplers import AdaptiveConfig, BeyondMimicConfig, UniformConfig  # noqa: E402

_LAZY = {
    "AccountingConfig": "schemas",
    "SamplerFeedback": "feedback",
    "BinSampler": "base",
    "bin_counts": "base",
    "BinLayout": "bins",
    "ReleasedBinLayout": "bins",
    "attribute": "bins",
    "bin_edges_s": "bins",
    "bins_of_time": "bins",
    "failed_mask": "bins",
    "num_bins": "bins",
    "visits_histogram": "bins",
    "ClipLayout": "clips",
    "layout_for": "config",
    "load_variant": "config",
    "make_sampler": "config",
    "sampler_config": "config",
    "validate_sampler_config": "config",
    "variant_names": "config",
    "bin_table": "diagnostics",
    "sampling_entropy": "diagnostics",
    "summary": "diagnostics",
    "make_layout": "layouts",
}
"""Public names imported on first use: name -> module of this package (the sampler classes: the registry's)."""


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        # The first use loads the package's modules (torch).
        from bmimic.sampling import (
            base,
            bins,
            clips,
            config,
            diagnostics,
            feedback,
            layouts,
            registry,
            schemas,
        )

        modules = {m.__name__.rpartition(".")[2]: m for m in (base, bins, clips, config, diagnostics, feedback,
                                                              layouts, registry, schemas)}
        return getattr(modules[_LAZY[name]], name)
    classes = {entry.cls.__name__: entry.cls for entry in SAMPLERS.values()}
    if name in classes:  # a registered sampler class
        return classes[name]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


__all__ = [
    "AccountingConfig",
    "AdaptiveConfig",
    "BeyondMimicConfig",
    "BinLayout",
    "BinSampler",
    "ClipLayout",
    "ReleasedBinLayout",
    "SAMPLERS",
    "SamplerConfig",
    "SamplerConfigError",
    "SamplerFeedback",
    "UniformConfig",
    "attribute",
    "bin_counts",
    "bin_edges_s",
    "bin_table",
    "bins_of_time",
    "failed_mask",
    "layout_for",
    "load_variant",
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
