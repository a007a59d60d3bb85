"""The registry of samplers: kind -> (sampler class, config schema), the one list of samplers.

A sampler is a config schema (a dataclass subclassing
:class:`bmimic.sampling.schemas.SamplerConfig`: its parameters with their defaults and a docstring
under each, `kind` and `name` defaulting to the registered name, and `check`, the range rules of its
keys) and a class (a :class:`bmimic.sampling.base.BinSampler` whose constructor takes
``(num_bins, cfg, device)``, cfg the validated schema instance), side by side in one module, which
binds torch on first use (``import_on_first_use``) so that it imports without torch::

    @dataclass
    class GreedyConfig(SamplerConfig): ...

    @register_sampler("greedy", GreedyConfig)
    class GreedySampler(BinSampler[GreedyConfig]): ...

Registering stores the schema in Hydra's ConfigStore as `sampler/<kind>_schema`, which a variant's
YAML (conf/sampler/<name>.yaml) lists first in its defaults before overriding some of its values.
Importing bmimic.sampling imports the modules of BUILT_IN, so every built-in kind is registered before
a config is composed; a sampler defined elsewhere (a test, a plug-in) registers when its module is
imported. `make_sampler`, the validation and the package's names look kinds, schemas and classes up
here; nothing else lists the samplers.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Protocol, TypeVar

from hydra.core.config_store import ConfigStore

from bmimic.sampling.checks import check_choice


@dataclass(frozen=True)
class SamplerEntry:
    cls: type
    """The sampler class (a BinSampler)."""
    config: type
    """Its config schema (a SamplerConfig dataclass)."""


SAMPLERS: dict[str, SamplerEntry] = {}
"""Registered samplers by kind."""

BUILT_IN = ("bmimic.sampling.samplers", "bmimic.sampling.peer_clips", "bmimic.sampling.peer_errors")
"""The modules of the built-in samplers (imported by bmimic.sampling)."""


class _Registered(Protocol):
    """What registration sets on a sampler class (a BinSampler)."""

    kind: str
    schema: Any


S = TypeVar("S", bound=type[_Registered])


def schema_name(kind: str) -> str:
    """The ConfigStore name of a kind's schema in the `sampler` group."""
    return f"{kind}_schema"


def register_sampler(kind: str, config: type) -> Callable[[S], S]:
    """Class decorator: register a sampler class under `kind` with its config schema."""

    def register(cls: S) -> S:
        if kind in SAMPLERS and SAMPLERS[kind].cls.__qualname__ != cls.__qualname__:
            raise ValueError(f"sampler kind {kind!r} is already registered by {SAMPLERS[kind].cls.__name__}")
        default = getattr(config(), "kind", None)
        if default != kind:
            raise ValueError(f"{config.__name__}.kind must default to {kind!r}, got {default!r}")
        ConfigStore.instance().store(group="sampler", name=schema_name(kind), node=config)
        cls.kind = kind
        cls.schema = config
        SAMPLERS[kind] = SamplerEntry(cls, config)
        return cls

    return register


def schema_of(kind: Any) -> type:
    """The registered config schema of `kind` (SamplerConfigError naming the known kinds)."""
    return sampler_entry(kind).config


def sampler_entry(kind: Any) -> SamplerEntry:
    """The registered class and schema of `kind` (SamplerConfigError naming the known kinds)."""
    check_choice("kind", kind, tuple(sorted(SAMPLERS)))
    return SAMPLERS[kind]


__all__ = ["BUILT_IN", "SAMPLERS", "SamplerEntry", "register_sampler", "sampler_entry", "schema_name", "schema_of"]
