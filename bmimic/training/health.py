"""Stopping a training run that can no longer learn, with one line saying why: a policy whose losses
or action noise turned non-finite (e.g. `ppo.learning_rate=1e10`), or an environment in which most
world-steps are broken (non-finite state, |qvel| above `sim.max_abs_qvel`, the root out of bounds,
a reward overflow: e.g. a motion 100 m below the floor, or `sim.max_abs_qvel=1e-6`). A broken world
is reset and counted as a failure, so a few are harmless; a run made mostly of them trains nothing.
Likewise a simulation that loses contacts or constraints on many steps (`sim.nconmax` / `sim.njmax`
too small: the buffers overflow and MuJoCo-Warp drops what does not fit) simulates another robot.

The checks read the iteration's train_metrics row, which the trainer reads from the device once per
iteration anyway: nothing is added to the step.
"""

from __future__ import annotations

import math

from bmimic import BmimicError

BROKEN_SHARE = 0.5
"""Share of an iteration's world-steps above which the iteration counts as mostly broken."""
BROKEN_ITERATIONS = 3
"""The run stops after this many mostly broken iterations in a row (fewer at the start of a launch)."""
OVERFLOW_SHARE = 0.1
"""Share of an iteration's world-steps whose contact or constraint buffers overflowed above which the
iteration counts as overflowing (no committed run overflowed at all with the default buffers)."""


class TrainingStoppedError(BmimicError):
    """Training can no longer learn (one line saying why); the run is recorded as failed."""


class Health:
    """Per-iteration checks of one training launch (one per rank; the stop is agreed on by all ranks)."""

    def __init__(self, world_steps_per_iteration: int) -> None:
        self.world_steps = max(int(world_steps_per_iteration), 1)
        """World-steps one rank simulates per iteration (num_envs x ppo.num_steps_per_env)."""
        self.iterations = 0
        self.broken_in_a_row = 0
        self.overflow_in_a_row = 0

    def problem(self, it: int, row: dict, learning_rate: float) -> str | None:
        """Why training must stop after iteration `it` (its train_metrics `row`), or None."""
        self.iterations += 1
        bad = [k for k in ("action_std", *sorted(k for k in row if k.startswith("loss/")))
               if not math.isfinite(float(row.get(k, 0.0)))]
        if bad:
            return (f"iteration {it}: the policy became non-finite ({', '.join(bad[:3])} is {row[bad[0]]}); "
                    f"ppo.learning_rate={learning_rate:g} is likely too large, or the observations are not finite")
        broken = float(row["nonfinite_resets"]) + float(row["out_of_bounds_resets"])
        share = broken / self.world_steps
        self.broken_in_a_row = self.broken_in_a_row + 1 if share > BROKEN_SHARE else 0
        if self.broken_in_a_row >= min(BROKEN_ITERATIONS, self.iterations):
            return (f"iteration {it}: {share:.0%} of the world-steps were broken (non-finite, |qvel| above "
                    f"sim.max_abs_qvel, root beyond sim.max_root_distance_m or reward above "
                    f"env.max_abs_step_reward) in {self.broken_in_a_row} iteration(s) in a row: nothing can be "
                    "learned; check the motion (root height, velocities), those limits and the policy")
        overflow = float(row.get("overflow_worlds", 0.0)) / self.world_steps
        self.overflow_in_a_row = self.overflow_in_a_row + 1 if overflow > OVERFLOW_SHARE else 0
        if self.overflow_in_a_row >= min(BROKEN_ITERATIONS, self.iterations):
            return (f"iteration {it}: {overflow:.0%} of the world-steps overflowed the contact/constraint buffers "
                    f"(more than {OVERFLOW_SHARE:.0%}) in {self.overflow_in_a_row} iteration(s) in a row: the "
                    "simulation drops contacts, so the results would be wrong; raise sim.nconmax / sim.njmax")
        return None

    def check(self, it: int, row: dict, learning_rate: float, distributed: bool = False, device=None) -> None:
        """Raise TrainingStoppedError when `problem` finds one (on every rank when any rank does)."""
        problem = self.problem(it, row, learning_rate)
        if distributed:
            import torch

            flag = torch.tensor(float(problem is not None), device=device)
            torch.distributed.all_reduce(flag, op=torch.distributed.ReduceOp.MAX)
            if problem is None and flag.item() > 0:
                problem = f"iteration {it}: another rank stopped (see its log)"
        if problem is not None:
            raise TrainingStoppedError(problem)
