"""What `ppo.overlap_update` adds to GraphPPO (bmimic.training.ppo): the behaviour policy that acts while
an update runs, and the staged copy of the rollout that the update reads.

Update k runs on a side CUDA stream while rollout k+1 collects on the main one. The rollout acts with
copies of actor and critic taken before update k (one update of policy lag, as in asynchronous PPO: the
importance ratio is taken against the policy that acted, which the storage records), and update k reads
its own copy of rollout k, so rollout k+1 may overwrite the storage.
"""

from __future__ import annotations

import copy
from contextlib import contextmanager
from typing import Any, Iterator

import torch
import torch.nn as nn

BEHAVIOUR_KEYS = ("behaviour_actor_state_dict", "behaviour_critic_state_dict")
"""Where a checkpoint holds the behaviour actor and critic (a resume continues the lag exactly)."""


class Behaviour:
    """The acting copies of actor and critic: weights and normaliser statistics, written in place (a
    captured act graph reads their addresses)."""

    def __init__(self, actor: nn.Module, critic: nn.Module) -> None:
        self.raw: tuple[nn.Module, nn.Module] = (copy.deepcopy(actor), copy.deepcopy(critic))
        """Uncompiled: what a checkpoint saves and loads."""
        self.modules: tuple[Any, Any] = self.raw
        """What acts: the raw copies, or torch.compile's wrappers of them (`compile`)."""

    def compile(self, mode: str | None) -> None:
        """Compile the acting copies as rsl-rl compiles the learner's."""
        from rsl_rl.utils import compile_model

        actor, critic = (compile_model(m, mode) for m in self.raw)
        self.modules = (actor, critic)

    @contextmanager
    def acting(self, alg: Any) -> Iterator[None]:
        """rsl-rl's acting code (act, compute_returns) reads `alg.actor` and `alg.critic`: let it see these."""
        actor, critic = alg.actor, alg.critic
        alg.actor = self.modules[0]
        alg.critic = self.modules[1]
        try:
            yield
        finally:
            alg.actor = actor
            alg.critic = critic

    def copy_from(self, actor: nn.Module, critic: nn.Module) -> None:
        """Take the learner's actor and critic (uncompiled modules), in place."""
        with torch.no_grad():
            for mine, theirs in zip(self.raw, (actor, critic)):
                for b, x in zip(mine.state_dict(keep_vars=True).values(), theirs.state_dict(keep_vars=True).values()):
                    b.data.copy_(x.data)

    def state_dict(self) -> dict[str, dict]:
        return {key: m.state_dict() for key, m in zip(BEHAVIOUR_KEYS, self.raw)}

    def load(self, state: dict, strict: bool, actor: nn.Module, critic: nn.Module) -> None:
        """From a checkpoint; one without a behaviour policy (a run without overlap) acts with its learner's."""
        if BEHAVIOUR_KEYS[0] in state:
            for key, m in zip(BEHAVIOUR_KEYS, self.raw):
                m.load_state_dict(state[key], strict=strict)
        else:
            self.copy_from(actor, critic)


class StagedRollout:
    """A persistent copy of the flattened rollout and its advantages (captured update graphs read it)."""

    def __init__(self) -> None:
        self.flat: dict | None = None
        self.advantages: torch.Tensor | None = None

    def stage(self, flat: dict, advantages: torch.Tensor) -> tuple[dict, torch.Tensor]:
        """Copy `flat` (tensors, and a tuple of them under "dist") and `advantages` into the buffers."""
        if self.flat is None or self.advantages is None:
            self.flat = {k: (tuple(torch.empty_like(p) for p in v) if isinstance(v, tuple) else torch.empty_like(v))
                         for k, v in flat.items()}
            self.advantages = torch.empty_like(advantages)
        for k, v in flat.items():
            for dst, src in zip(*((self.flat[k], v) if isinstance(v, tuple) else ((self.flat[k],), (v,)))):
                dst.copy_(src)
        self.advantages.copy_(advantages)
        return self.flat, self.advantages
