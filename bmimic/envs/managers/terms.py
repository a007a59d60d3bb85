"""`Terms`: the entries of one term table of the env config, resolved to their functions."""

from __future__ import annotations

from typing import Any, Callable, Mapping

from bmimic.envs.mdp import resolve_term


class Terms:
    """Enabled entries of a term table, in config order: `names`, `funcs`, `params` (dicts) and
    `cfgs` (the entries themselves)."""

    def __init__(self, kind: str, cfgs: Mapping[str, Any]) -> None:
        self.names: list[str] = []
        self.funcs: list[Callable] = []
        self.params: list[dict] = []
        self.cfgs: list[Any] = []
        for name, cfg in cfgs.items():
            if getattr(cfg, "enabled", True) is False:
                continue
            self.names.append(name)
            self.funcs.append(resolve_term(kind, cfg.func))
            self.params.append(dict(cfg.params) if cfg.params else {})
            self.cfgs.append(cfg)

    def __len__(self) -> int:
        return len(self.names)

    def __iter__(self):
        return iter(zip(self.names, self.funcs, self.params, self.cfgs))


__all__ = ["Terms"]
