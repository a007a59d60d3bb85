"""`RewardManager`: the reward terms, their weights, per-episode sums and logged episode means."""

from __future__ import annotations

import math
from typing import Any, Mapping

import torch

from bmimic.envs.managers.terms import Terms


class RewardManager:
    """Step reward per term = weight * term * step_dt (BeyondMimic). Terms of weight 0 are not
    computed: their column is zero, so they still appear, as 0, in the logs."""

    def __init__(self, cfgs: Mapping[str, Any], step_dt: float, num_envs: int, device: torch.device | str) -> None:
        self.terms = Terms("rewards", cfgs)
        self.active = [float(c.weight) != 0.0 for c in self.terms.cfgs]
        weights = torch.tensor([c.weight for c in self.terms.cfgs], dtype=torch.float32, device=device)
        self.scale = weights * step_dt
        self._zeros = torch.zeros(num_envs, device=device)
        self.episode_sums = torch.zeros(num_envs, len(self.terms), device=device)
        """Per env and term: the reward of the current episode so far."""
        self._finished_sums = torch.zeros(len(self.terms), device=device)

    def compute(self, env) -> torch.Tensor:
        """Weighted per-term rewards of this step, [num_envs, terms]."""
        parts = [fn(env, **params) if on else self._zeros
                 for (_, fn, params, _), on in zip(self.terms, self.active)]
        return torch.stack(parts, dim=-1) * self.scale

    def accumulate(self, rewards: torch.Tensor) -> None:
        self.episode_sums += rewards

    def end_episodes(self, dones: torch.Tensor) -> None:
        """Add the finished episodes' sums to the iteration's and start theirs again."""
        self._finished_sums += (self.episode_sums * dones.float()[:, None]).sum(0)
        self.episode_sums.masked_fill_(dones[:, None], 0.0)

    def pop_log(self, episodes: float) -> dict[str, float]:
        """`reward/<term>` (mean per finished episode) and `mean_episode_reward`; NaN without
        finished episodes. One host transfer, then cleared."""
        sums = (self._finished_sums / max(episodes, 1.0)).cpu().numpy()
        self._finished_sums.zero_()
        out = {f"reward/{name}": float(v) if episodes else math.nan for name, v in zip(self.terms.names, sums)}
        out["mean_episode_reward"] = float(sums.sum()) if episodes else math.nan
        return out


__all__ = ["RewardManager"]
