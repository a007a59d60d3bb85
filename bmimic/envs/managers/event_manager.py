"""`EventManager`: the event terms (domain randomisation, pushes) by mode, and the per-world timers
of the interval terms."""

from __future__ import annotations

from typing import Any, Mapping

import torch

from bmimic.envs.managers.terms import Terms


class EventManager:
    """Runs `startup` terms once (`startup`), `interval` terms in each world when its timer runs out
    (`interval`, every step; the timer is then drawn anew from the term's interval_range_s) and
    `reset` terms in the worlds that start an episode (`reset`). Within a mode, config order.

    Every call applies to all worlds through a mask, so interval and reset terms run inside the
    captured step with fixed shapes; the timers are written in place."""

    def __init__(self, cfgs: Mapping[str, Any], num_envs: int, device: torch.device | str) -> None:
        self.num_envs = num_envs
        self.device = torch.device(device)
        self.modes = {mode: Terms("events", {k: c for k, c in cfgs.items() if c.mode == mode})
                      for mode in ("startup", "interval", "reset")}
        self.time_left_s = [torch.zeros(num_envs, device=self.device) for _ in self.modes["interval"].names]
        """Per interval term: seconds until it fires in each world."""

    @property
    def model_fields(self) -> tuple[str, ...]:
        """Model fields some term randomises per world (the simulator allocates them per world)."""
        fields = [f for terms in self.modes.values() for fn in terms.funcs for f in getattr(fn, "model_fields", ())]
        return tuple(dict.fromkeys(fields))

    @property
    def has_interval(self) -> bool:
        return len(self.modes["interval"]) > 0

    def _draw_interval_s(self, cfg: Any) -> torch.Tensor:
        lo, hi = cfg.interval_range_s
        return lo + (hi - lo) * torch.rand(self.num_envs, device=self.device)

    def startup(self, env) -> None:
        """The startup terms in every world, then the first interval of each interval term."""
        everyone = torch.ones(self.num_envs, dtype=torch.bool, device=self.device)
        for _, fn, params, _ in self.modes["startup"]:
            fn(env, everyone, **params)
        for time_left, cfg in zip(self.time_left_s, self.modes["interval"].cfgs):
            time_left.copy_(self._draw_interval_s(cfg))

    def interval(self, env, dt: float) -> None:
        """Advance the timers by `dt`; each term runs in the worlds whose timer ran out."""
        for time_left, (_, fn, params, cfg) in zip(self.time_left_s, self.modes["interval"]):
            time_left -= dt
            due = time_left <= 0
            fn(env, due, **params)
            time_left.copy_(torch.where(due, self._draw_interval_s(cfg), time_left))

    def reset(self, env, envs: torch.Tensor) -> None:
        """The reset terms in the worlds `envs` (Bool[num_envs]) that start an episode."""
        for _, fn, params, _ in self.modes["reset"]:
            fn(env, envs, **params)


__all__ = ["EventManager"]
