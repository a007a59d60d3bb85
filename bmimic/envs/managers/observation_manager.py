"""`ObservationManager`: the observation groups (policy, critic), each the concatenation of its terms."""

from __future__ import annotations

from typing import Any, Mapping

import torch
from tensordict import TensorDict

from bmimic.envs.managers.terms import Terms
from bmimic.envs.noise import UniformNoise


class ObservationManager:
    """Groups of observation terms; a `noisy` group adds each term's uniform noise (half-width
    `noise`) when built. An empty group other than the first is left out of the TensorDict."""

    def __init__(self, groups: Mapping[str, tuple[Mapping[str, Any], bool]], uniform: UniformNoise,
                 num_envs: int, device: torch.device | str) -> None:
        self.groups = {name: Terms("observations", cfgs) for name, (cfgs, _) in groups.items()}
        self.noisy = {name: noisy for name, (_, noisy) in groups.items()}
        self.uniform = uniform
        self.num_envs = num_envs
        self.device = torch.device(device)

    def _group(self, env, name: str) -> torch.Tensor:
        parts = []
        for _, fn, params, cfg in self.groups[name]:
            x = fn(env, **params)
            if self.noisy[name] and cfg.noise > 0:
                x = x + self.uniform(x.shape, cfg.noise)
            parts.append(x)
        return torch.cat(parts, dim=-1)

    def compute(self, env) -> TensorDict:
        """Every group from the env's current state, as a TensorDict [num_envs]."""
        first = next(iter(self.groups))
        out = {name: self._group(env, name) for name, terms in self.groups.items() if name == first or len(terms)}
        return TensorDict(out, batch_size=[self.num_envs], device=self.device)

    def dims(self, env, name: str) -> list[int]:
        """Width of each term of group `name` (calls the terms once)."""
        return [int(fn(env, **params).shape[-1]) for _, fn, params, _ in self.groups[name]]


__all__ = ["ObservationManager"]
