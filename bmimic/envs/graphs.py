"""`StepGraphs`: the torch parts of a control step captured as CUDA graphs around the simulator's.

Everything on the step path has fixed shapes and no host synchronisation, so it can be replayed;
this removes the per-kernel launch cost that otherwise dominates at 4096+ envs. With
`sim.compile_env_step` the parts are first fused by torch.compile (fewer, larger kernels in the
graphs). Two warm-up steps (compiling, filling caches, creating the NCCL communicator under
torchrun, as NCCL capture requires) run before capture.
"""

from __future__ import annotations

import logging
from typing import Callable, Sequence

import torch

from bmimic.sim import Simulator

log = logging.getLogger(__name__)


def _run(parts: Sequence[Callable[[], None]], sim: Simulator) -> None:
    """One step through (pre, post, obs): pre, physics, post, kinematics, obs."""
    pre, post, obs = parts
    pre()
    sim.step()
    post()
    sim.forward_kinematics()
    obs()


class StepGraphs:
    """Captured (pre, post, obs) parts of a step; `replay()` runs one step."""

    def __init__(self, parts: Sequence[Callable[[], None]], sim: Simulator, compile_parts: bool) -> None:
        self.sim = sim
        parts = self._warmed_up(tuple(parts), compile_parts)
        pool = torch.cuda.graph_pool_handle()
        self.graphs = []
        for fn in parts:
            g = torch.cuda.CUDAGraph()
            with torch.cuda.graph(g, pool=pool):
                fn()
            self.graphs.append(g)

    def _warmed_up(self, parts: tuple, compile_parts: bool) -> tuple:
        if compile_parts:
            compiled = tuple(torch.compile(fn, dynamic=False) for fn in parts)
            try:
                self._warm_up(compiled)
                return compiled
            except Exception as e:  # a missing or broken compiler toolchain costs speed, not the run
                log.warning("sim.compile_env_step: torch.compile failed (%s: %s); capturing the step "
                            "uncompiled", type(e).__name__, str(e).splitlines()[0] if str(e) else "")
        self._warm_up(parts)
        return parts

    def _warm_up(self, parts: tuple) -> None:
        for _ in range(2):
            _run(parts, self.sim)
        torch.cuda.synchronize(self.sim.device)

    def replay(self) -> None:
        _run([g.replay for g in self.graphs], self.sim)

    def release(self) -> None:
        """Free the graphs (under torchrun before destroy_process_group: a live graph holding an
        NCCL all-reduce makes it hang, pytorch/pytorch#115388)."""
        torch.cuda.synchronize(self.sim.device)
        self.graphs = []


__all__ = ["StepGraphs"]
