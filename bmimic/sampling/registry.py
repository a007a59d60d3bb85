"""The registry of samplers: kind -> (sampler class, config schema), the one list of samplers.

A sampler is a config schema (a dataclass subclassing
:class:`bmimic.sampling.schemas.SamplerConfig`: its parameters with their defaults and a docstring
under each, `kind` and `name` defaulting to the registered name, and `check`, the range rules of its
keys) and a class (a :class:`bmimic.sampling.base.BinSampler` whose constructor takes
``(num_bins, cfg, device)``, cfg the validated schema instance). The schema registers torch-free,
naming the module of its class, and the class registers with its schema when that module is imported::

    @sampler_schema("greedy", "bmimic.sampling.samplers")     # in bmimic/sampling/schemas.py
    @dataclass
    class GreedyConfig(SamplerConfig): ...

    @register_sampler("greedy", GreedyConfig)                  # in bmimic/sampling/samplers.py
    class GreedySampler(BinSampler): ...

Registering stores the schema in Hydra's ConfigStore as `sampler/<kind>_schema`, which a variant's
YAML (conf/sampler/<name>.yaml) lists first in its defaults before overriding some of its values.
`make_sampler`, the validation and the package's lazy names look kinds, schemas and classes up here
(`sampler_entry` imports a class's module on first use); nothing else lists the samplers. A sampler
defined elsewhere (a test, a plug-in) may skip the schema's decorator: `register_sampler` registers
both.
"""

from __future__ import annotations

import importlib
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

SCHEMAS: dict[str, type] = {}
"""Registered config schemas by kind (a registered sampler's included)."""

CLASS_MODULES: dict[str, str] = {}
"""The module that registers each kind's class (imported when the class is first needed)."""

T = TypeVar("T", bound=type)


class _Registered(Protocol):
    """What registration sets on a sampler class (a BinSampler)."""

    kind: str
    schema: Any


S = TypeVar("S", bound=type[_Registered])


def schema_name(kind: str) -> str:
    """The ConfigStore name of a kind's schema in the `sampler` group."""
    return f"{kind}_schema"


def register_schema(kind: str, config: type, module: str) -> None:
    """Register `config` as the schema of `kind` (also in Hydra's ConfigStore), whose class `module`
    registers when imported."""
    default = getattr(config(), "kind", None)
    if default != kind:
        raise ValueError(f"{config.__name__}.kind must default to {kind!r}, got {default!r}")
    if kind in SCHEMAS and SCHEMAS[kind].__qualname__ != config.__qualname__:
        raise ValueError(f"sampler kind {kind!r} is already registered with the schema {SCHEMAS[kind].__name__}")
    SCHEMAS[kind] = config
    CLASS_MODULES[kind] = module
    ConfigStore.instance().store(group="sampler", name=schema_name(kind), node=config)


def sampler_schema(kind: str, module: str) -> Callable[[T], T]:
    """Dataclass decorator: register a config schema under `kind`, its class to come from `module`."""

    def register(config: T) -> T:
        register_schema(kind, config, module)
        return config

    return register


def register_sampler(kind: str, config: type) -> Callable[[S], S]:
    """Class decorator: register a sampler class under `kind` with its config schema."""

    def register(cls: S) -> S:
        if kind in SAMPLERS and SAMPLERS[kind].cls.__qualname__ != cls.__qualname__:
            raise ValueError(f"sampler kind {kind!r} is already registered by {SAMPLERS[kind].cls.__name__}")
        register_schema(kind, config, cls.__module__)
        cls.kind = kind
        cls.schema = config
        SAMPLERS[kind] = SamplerEntry(cls, config)
        return cls

    return register


def schema_of(kind: Any) -> type:
    """The registered config schema of `kind` (SamplerConfigError naming the known kinds)."""
    check_choice("kind", kind, tuple(sorted(SCHEMAS)))
    return SCHEMAS[kind]


def sampler_entry(kind: Any) -> SamplerEntry:
    """The registered class and schema of `kind`, its module imported if need be (SamplerConfigError
    naming the known kinds)."""
    check_choice("kind", kind, tuple(sorted(SCHEMAS)))
    if kind not in SAMPLERS:
        importlib.import_module(CLASS_MODULES[kind])
    return SAMPLERS[kind]


def load_classes() -> dict[str, SamplerEntry]:
    """Every registered kind's class (their modules imported: torch), as SAMPLERS."""
    for kind in sorted(SCHEMAS):
        sampler_entry(kind)
    return SAMPLERS


__all__ = ["CLASS_MODULES", "SAMPLERS", "SCHEMAS", "SamplerEntry", "load_classes", "register_sampler", "register_schema",
           "sampler_entry", "sampler_schema", "schema_name", "schema_of"]
