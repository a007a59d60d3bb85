"""The `sampler` config group: the keys every sampler variant has, the variants, their validation
and the factories.

Each YAML under ``conf/sampler/`` is a named variant (``name`` = its file name) of a registered
sampler class: it lists that class's schema first in its defaults (``<kind>_schema``,
:mod:`bmimic.sampling.registry`) and may set only the keys that schema has:

- the keys of every variant (:class:`SamplerConfig`): ``name``, ``kind`` (the class; the schema's
  default), ``enabled``, the bin layout ``bins`` and ``bin_size_seconds``, ``accounting`` (the
  episode accounting, :class:`bmimic.sampling.schemas.AccountingConfig`: ``attribution``,
  ``failure``, ``failure_threshold``, ``update_every``) and ``log_every`` (the trainer's);
- the sampler's own parameters: its schema, beside its class in the sampler's module (e.g.
  :mod:`bmimic.sampling.samplers`), the one place of their defaults and range rules; a YAML sets only
  the values where the variant differs from them.

The variants are the YAML files (:func:`variant_names`; ``python -m bmimic.train --help`` lists
them), each with a header saying what it is; the kinds are those of the registry
(:mod:`bmimic.sampling.registry`).

``enabled: false`` draws start bins uniformly whatever the variant (the design's switch back to
uniform sampling); the run then equals ``sampler=uniform`` except for the recorded name.
"""

from __future__ import annotations

from dataclasses import asdict
from typing import TYPE_CHECKING, Any, Mapping, Sequence, Union, cast

from bmimic.sampling.checks import SamplerConfigError, check_choice, fail
from bmimic.sampling.registry import SAMPLERS, sampler_entry, schema_of
from bmimic.sampling.schemas import SamplerConfig

if TYPE_CHECKING:
    import torch
    from omegaconf import DictConfig

    from bmimic.sampling.base import BinSampler
    from bmimic.sampling.bins import Layout

SamplerNode = Union[SamplerConfig, "DictConfig"]
"""A sampler config: the schema's instance or the composed node (`sampler`)."""
SamplerLike = Union[SamplerConfig, "DictConfig", Mapping[str, Any]]
"""A sampler config, or a plain dict such as a run folder's."""

def sampler_class(kind: Any) -> type:
    """The sampler class registered for `kind`."""
    return sampler_entry(kind).cls


def sampler_config(cfg: SamplerLike) -> SamplerConfig:
    """`cfg` (a SamplerConfig, the composed node, or a plain dict such as a run folder's) as an
    instance of its kind's schema. SamplerConfigError names a key the schema does not have."""
    if isinstance(cfg, SamplerConfig):
        return cfg
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    node_type = OmegaConf.get_type(cfg) if isinstance(cfg, DictConfig) else None
    if isinstance(node_type, type) and issubclass(node_type, SamplerConfig):
        return cast(SamplerConfig, OmegaConf.to_object(cfg))
    plain = cast(dict, OmegaConf.to_container(cfg, resolve=True)) if isinstance(cfg, DictConfig) else dict(cfg)
    kind = plain.get("kind")
    try:
        return cast(SamplerConfig, OmegaConf.to_object(OmegaConf.merge(OmegaConf.structured(schema_of(kind)), plain)))
    except OmegaConfBaseException as e:
        key = getattr(e, "full_key", "") or "?"
        raise SamplerConfigError(f"sampler.{key}: does not fit the {kind} sampler's schema "
                                 f"({str(e).splitlines()[0]})") from None


CLIP_BALANCES = ("bins", "clips")


def validate_sampler_config(cfg: SamplerLike, motion_duration_s: float | None = None) -> None:
    """Check every key of a sampler config (a :class:`SamplerConfig`, the composed node or a dict).

    Raises :class:`SamplerConfigError` with a one-line message naming the first bad key.
    """
    from bmimic.sampling.bins import LAYOUTS, check_bin_size
    from bmimic.sampling.feedback import check_accounting

    cfg = sampler_config(cfg)
    if not (isinstance(cfg.name, str) and cfg.name):
        fail("name", "the variant's name (its file name in conf/sampler/)", cfg.name)
    if not isinstance(cfg.enabled, bool):
        fail("enabled", "true or false", cfg.enabled)
    check_choice("bins", cfg.bins, LAYOUTS)
    check_choice("clip_balance", cfg.clip_balance, CLIP_BALANCES)
    if cfg.bins == "time" or cfg.bin_size_seconds is not None:
        check_bin_size(cfg.bin_size_seconds, motion_duration_s if cfg.bins == "time" else None)
    cfg.check()
    check_accounting(cfg.accounting)
    if cfg.log_every is not None and not (isinstance(cfg.log_every, int) and not isinstance(cfg.log_every, bool)
                                          and cfg.log_every >= 1):
        fail("log_every", "an integer >= 1 or null", cfg.log_every)


def make_sampler(cfg: SamplerLike, num_bins: int, device: torch.device | str = "cpu", layout: Layout | None = None,
                 clip_weights: Sequence[float] | None = None) -> BinSampler:
    """Build the sampler ``cfg`` configures over ``num_bins`` bins on ``device`` (uniform when
    ``cfg.enabled`` is false); given the ``layout`` of a library (several clips), the sampler knows its
    clips (look-ahead stops at clip ends; ``cfg.clip_balance`` with ``clip_weights``)."""
    cfg = sampler_config(cfg)
    if cfg.enabled is False:
        sampler = sampler_class("uniform")(num_bins, device=device)
    else:
        sampler = sampler_class(cfg.kind)(num_bins, cfg, device=device)
    if layout is not None and layout.num_clips > 1:
        sampler.set_clips(layout.bin_clip, layout.bin_last_in_clip, layout.num_clips, cfg.clip_balance, clip_weights)
    return sampler


def layout_for(cfg: SamplerNode, num_frames: int, fps: float, device: torch.device | str = "cpu", clip_starts: Any = None,
               clip_names: Any = None) -> Layout:
    """The bin layout ``cfg.bins`` of a motion of ``num_frames`` frames at ``fps`` (of a library when
    ``clip_starts`` has several clips; ``clip_names`` label them)."""
    from bmimic.sampling.layouts import make_layout

    return make_layout(cfg.bins, num_frames, fps, cfg.bin_size_seconds, device=device, clip_starts=clip_starts,
                       clip_names=clip_names)


def min_motion_bin_s(cfg: SamplerNode) -> float:
    """The bin size a motion must be at least two of (0 with the released layout, whose bin count
    follows the motion)."""
    # validated: time bins have a size
    return float(cast(float, cfg.bin_size_seconds)) if cfg.bins == "time" else 0.0


def describe(cfg: SamplerLike, layout: Layout, sampler: BinSampler) -> list[str]:
    """The lines the run's log gets: the variant and every sampler value in force."""
    cfg = sampler_config(cfg)
    acc = cfg.accounting
    lines = []
    if cfg.enabled is False:
        lines.append(f"sampler {cfg.name}: sampler.enabled=false, so start bins are drawn uniformly "
                     "(as sampler=uniform; the values below only shape the per-bin diagnostics)")
    hp = " ".join(f"{k}={v}" for k, v in sampler.hparams().items())
    lines.append(
        f"sampler {cfg.name} ({type(sampler).__name__}): {layout.describe()}; {hp + '; ' if hp else ''}"
        f"attribution={acc.attribution} failure={acc.failure}"
        f"{f' failure_threshold={acc.failure_threshold:g}' if acc.failure == 'short' else ''} "
        f"update_every={acc.update_every} log_every={'null' if cfg.log_every is None else cfg.log_every}"
    )
    if cfg.bins == "released" and cfg.bin_size_seconds is not None:
        lines.append(f"sampler.bin_size_seconds={cfg.bin_size_seconds:g} does not apply to the released bins "
                     f"(sampler.bins=released: {layout.num_bins} bins from the motion's length); ignored")
    return lines


def variant_names() -> tuple[str, ...]:
    """The variants: the YAML files of conf/sampler/, sorted."""
    from bmimic import CONF_DIR

    return tuple(sorted(p.stem for p in (CONF_DIR / "sampler").glob("*.yaml")))


def load_variant(name: str) -> SamplerConfig:
    """The named variant ``conf/sampler/<name>.yaml`` as its schema's instance (without Hydra)."""
    from omegaconf import OmegaConf

    from bmimic import CONF_DIR

    check_choice("name", name, variant_names())
    node = cast(dict, OmegaConf.to_container(OmegaConf.load(CONF_DIR / "sampler" / f"{name}.yaml")))
    schemas = [d for d in node.pop("defaults", []) if isinstance(d, str) and d.endswith("_schema")]
    kinds = [k for k in SAMPLERS if f"{k}_schema" in schemas]
    if len(kinds) != 1:
        raise SamplerConfigError(f"conf/sampler/{name}.yaml: its defaults must name one sampler schema "
                                 f"(<kind>_schema, kinds: {', '.join(sorted(SAMPLERS))})")
    return sampler_config({**node, "kind": kinds[0]})


def as_dict(cfg: SamplerLike) -> dict[str, Any]:
    """The keys and values of `cfg` in today's layout (accounting nested), every schema default
    filled in: e.g. to compare a run folder's sampler with a new one on resume."""
    return asdict(sampler_config(cfg))


__all__ = [
    "SamplerConfig",
    "SamplerConfigError",
    "as_dict",
    "describe",
    "layout_for",
    "load_variant",
    "make_sampler",
    "min_motion_bin_s",
    "sampler_class",
    "sampler_config",
    "validate_sampler_config",
    "variant_names",
]
