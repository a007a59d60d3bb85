"""A training run that can no longer learn stops with one line (issue 36): a policy turned non-finite
(`ppo.learning_rate=1e10`), or most world-steps broken (a motion 100 m below the floor)."""

from __future__ import annotations

import math

import pytest

from bmimic.training.health import BROKEN_ITERATIONS, Health, TrainingStoppedError


def row(broken: float = 0.0, loss: float = 0.1, std: float = 1.0) -> dict:
    return {"nonfinite_resets": broken / 2, "out_of_bounds_resets": broken / 2, "loss/surrogate": loss,
            "loss/value": 0.2, "action_std": std}


def test_a_non_finite_policy_stops_naming_the_learning_rate():
    h = Health(world_steps_per_iteration=100)
    assert h.problem(0, row(), 1e-3) is None
    with pytest.raises(TrainingStoppedError, match=r"iteration 1: the policy became non-finite \(action_std.*"
                                                   r"ppo.learning_rate=1e\+10"):
        h.check(1, row(loss=math.nan, std=math.nan), 1e10)


def test_mostly_broken_iterations_stop_the_run_a_transient_does_not():
    h = Health(world_steps_per_iteration=100)
    for it in range(5):
        assert h.problem(it, row(broken=10), 1e-3) is None  # 10% broken: a few blow-ups are harmless
    assert h.problem(5, row(broken=90), 1e-3) is None  # one mostly broken iteration mid-run
    assert h.problem(6, row(broken=0), 1e-3) is None  # ... and it recovered
    for it in range(7, 7 + BROKEN_ITERATIONS - 1):
        assert h.problem(it, row(broken=60), 1e-3) is None
    problem = h.problem(7 + BROKEN_ITERATIONS - 1, row(broken=60), 1e-3)
    assert problem and "60% of the world-steps were broken" in problem and "sim.max_abs_qvel" in problem


def test_a_launch_whose_first_iteration_is_all_broken_stops_at_once():
    h = Health(world_steps_per_iteration=100)
    with pytest.raises(TrainingStoppedError, match="100% of the world-steps were broken"):
        h.check(0, row(broken=100), 1e-3)


def test_overflowing_contact_buffers_stop_the_run_naming_sim_nconmax():
    """Issue 47: sim.nconmax too small overflowed the contact buffers on every step and the run ended
    "done". Above OVERFLOW_SHARE of an iteration's world-steps, BROKEN_ITERATIONS in a row, it stops."""
    from bmimic.training.health import OVERFLOW_SHARE

    h = Health(world_steps_per_iteration=100)
    for it in range(5):
        assert h.problem(it, {**row(), "overflow_worlds": 100 * OVERFLOW_SHARE}, 1e-3) is None  # at the share: kept
    for it in range(5, 5 + BROKEN_ITERATIONS - 1):
        assert h.problem(it, {**row(), "overflow_worlds": 50}, 1e-3) is None
    problem = h.problem(5 + BROKEN_ITERATIONS - 1, {**row(), "overflow_worlds": 50}, 1e-3)
    assert problem and "50% of the world-steps overflowed" in problem and "sim.nconmax" in problem
    with pytest.raises(TrainingStoppedError, match="100% of the world-steps overflowed"):
        Health(world_steps_per_iteration=10).check(0, {**row(), "overflow_worlds": 10}, 1e-3)
