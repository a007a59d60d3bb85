"""The registry of samplers: kind -> (sampler class, config schema).

A sampler class registers itself with its schema (a dataclass subclassing
:class:`bmimic.sampling.config.SamplerConfig` that adds its own parameters, with `kind` defaulting to
the registered name)::

    @register_sampler("greedy", GreedyConfig)
    class GreedySampler(BinSampler): ...

Registering stores the schema in Hydra's ConfigStore as `sampler/<kind>_schema`, which a variant's
YAML (conf/sampler/<name>.yaml) lists first in its defaults. `make_sampler` and the validation look
the class up here; nothing else names the sampler classes.

Schemas and classes are two tables: composing a config needs only the schemas, which
:mod:`bmimic.sampling.schemas` registers without torch (`register_schema`); the built-in classes
register when :mod:`bmimic.sampling.config` first needs one (`sampler_class`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

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


def schema_name(kind: str) -> str:
    """The ConfigStore name of a kind's schema in the `sampler` group."""
    return f"{kind}_schema"


def register_schema(kind: str, config: type) -> None:
    """Register `config` as the schema of `kind` (also in Hydra's ConfigStore); the class may follow."""
    default = getattr(config(), "kind", None)
    if default != kind:
        raise ValueError(f"{config.__name__}.kind must default to {kind!r}, got {default!r}")
    if kind in SCHEMAS and SCHEMAS[kind].__qualname__ != config.__qualname__:
        raise ValueError(f"sampler kind {kind!r} is already registered with the schema {SCHEMAS[kind].__name__}")
    SCHEMAS[kind] = config
    ConfigStore.instance().store(group="sampler", name=schema_name(kind), node=config)


def register_sampler(kind: str, config: type):
    """Class decorator: register a sampler class under `kind` with its config schema."""

    def register(cls: type) -> type:
        if kind in SAMPLERS and SAMPLERS[kind].cls.__qualname__ != cls.__qualname__:
            raise ValueError(f"sampler kind {kind!r} is already registered by {SAMPLERS[kind].cls.__name__}")
        register_schema(kind, config)
        cls.kind = kind
        SAMPLERS[kind] = SamplerEntry(cls, config)
        return cls

    return register


def schema_of(kind: Any) -> type:
    """The registered config schema of `kind` (SamplerConfigError naming the known kinds)."""
    check_choice("kind", kind, tuple(sorted(SCHEMAS)))
    return SCHEMAS[kind]


def sampler_entry(kind: Any) -> SamplerEntry:
    """The registered class and schema of `kind` (SamplerConfigError naming the known kinds)."""
    check_choice("kind", kind, tuple(sorted(SAMPLERS)))
    return SAMPLERS[kind]


__all__ = ["SAMPLERS", "SCHEMAS", "SamplerEntry", "register_sampler", "register_schema", "sampler_entry", "schema_name",
           "schema_of"]
