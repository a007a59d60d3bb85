"""`TerminationManager`: the termination terms, which of them are time-outs, and how often each fired."""

from __future__ import annotations

from typing import Any, Mapping

import torch

from bmimic.envs.managers.terms import Terms


class TerminationManager:
    """Termination terms (disabled ones are not computed); a time-out term truncates (the value is
    bootstrapped, never a failure), the others terminate."""

    def __init__(self, cfgs: Mapping[str, Any], device: torch.device | str) -> None:
        self.terms = Terms("terminations", cfgs)
        self.time_out = torch.tensor([bool(c.time_out) for c in self.terms.cfgs], dtype=torch.bool, device=device)
        self._counts = torch.zeros(len(self.terms), device=device)

    def compute(self, env) -> torch.Tensor:
        """Bool[num_envs, terms]: which terms fire now; counted for the logs."""
        flags = torch.stack([fn(env, **params) for _, fn, params, _ in self.terms], dim=-1)
        self._counts += flags.float().sum(0)
        return flags

    def time_outs(self, flags: torch.Tensor) -> torch.Tensor:
        return (flags & self.time_out).any(-1)

    def terminations(self, flags: torch.Tensor) -> torch.Tensor:
        return (flags & ~self.time_out).any(-1)

    def pop_log(self, steps: float, num_envs: int) -> dict[str, float]:
        """`termination/<term>`: the fraction of env steps at which it fired; then cleared."""
        rates = (self._counts / (steps * num_envs)).cpu().numpy()
        self._counts.zero_()
        return {f"termination/{name}": float(v) for name, v in zip(self.terms.names, rates)}


__all__ = ["TerminationManager"]
