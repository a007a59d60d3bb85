"""bmimic.sim directly (no environment): known answers for the stepping and the kinematics, planted
broken worlds for the health checks, and the options written into the model."""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
import pytest
import torch

from bmimic import BmimicError
from bmimic.robot import load_mjmodel
from bmimic.sim import SimConfig, Simulator, apply_sim_options
from bmimic.sim.simulator import physics_bytes_per_world

WORLDS = 4


@pytest.fixture(scope="module")
def sim() -> Simulator:
    return Simulator(load_mjmodel(), SimConfig(), WORLDS, "cpu")


def _hold_pose(sim: Simulator) -> None:
    """Every position actuator's target = its joint's current angle (no actuator force at rest)."""
    m = sim.mjm
    joints = m.actuator_trnid[:, 0]
    sim.ctrl[:] = sim.qpos[:, torch.as_tensor(m.jnt_qposadr[joints])]


def test_free_fall_follows_semi_implicit_euler(sim):
    """Lifted 2 m above the floor at rest, every body falls alike: the root drops by g dt^2 n(n+1)/2 over
    the n = decimation physics steps of one control step, its velocity reaches -g n dt, the pose and the
    joints stay as they were."""
    sim.qpos[:] = sim.qpos0
    sim.qpos[:, 2] += 2.0
    sim.qvel.zero_()
    _hold_pose(sim)
    sim.forward()
    before = sim.qpos.clone()
    sim.step()
    g, dt, n = 9.81, sim.physics_dt, sim.decimation
    assert sim.mjm.opt.gravity[2] == pytest.approx(-g)
    drop = g * dt * dt * n * (n + 1) / 2
    torch.testing.assert_close(sim.qpos[:, 2], before[:, 2] - drop, atol=2e-5, rtol=0)
    torch.testing.assert_close(sim.qvel[:, 2], torch.full((WORLDS,), -g * n * dt), atol=2e-5, rtol=0)
    torch.testing.assert_close(sim.qpos[:, 3:], before[:, 3:], atol=1e-5, rtol=0)
    torch.testing.assert_close(sim.qpos[:, :2], before[:, :2], atol=1e-6, rtol=0)


def test_forward_kinematics_matches_native_mujoco(sim):
    """Body poses after a state write equal MuJoCo's own kinematics of the same qpos, world by world."""
    rng = np.random.default_rng(0)
    m = sim.mjm
    qpos = np.tile(m.qpos0, (WORLDS, 1))
    qpos[:, 7:] += rng.uniform(-0.3, 0.3, size=(WORLDS, m.nq - 7))
    qpos[:, :3] += rng.uniform(-1.0, 1.0, size=(WORLDS, 3))
    yaw = rng.uniform(-np.pi, np.pi, size=WORLDS)
    qpos[:, 3:7] = np.stack([np.cos(yaw / 2), 0 * yaw, 0 * yaw, np.sin(yaw / 2)], axis=-1)
    sim.qpos[:] = torch.as_tensor(qpos, dtype=torch.float32)
    sim.qvel.zero_()
    sim.forward_kinematics()
    d = mujoco.MjData(m)
    for w in range(WORLDS):
        d.qpos[:] = sim.qpos[w].double().numpy()  # the float32 state the simulator holds
        mujoco.mj_kinematics(m, d)
        np.testing.assert_allclose(sim.xpos[w].numpy(), d.xpos, atol=1e-4)
        same_sign = np.sign(np.sum(sim.xquat[w].numpy() * d.xquat, axis=-1, keepdims=True))
        np.testing.assert_allclose(sim.xquat[w].numpy() * same_sign, d.xquat, atol=1e-4)


def test_broken_worlds_are_found_and_only_they_are_reset(sim):
    sim.qpos[:] = sim.qpos0
    sim.qpos[:, 7:] += 0.1  # a pose that differs from the reset pose, to see what is kept
    sim.qvel[:] = 0.5
    sim.qvel[1, 8] = float("nan")  # non-finite
    sim.qvel[2, 10] = 2 * sim.max_abs_qvel  # blown up
    sim.qpos[3, 0] = 2 * sim.max_root_distance_m  # flown away
    assert sim.nonfinite_worlds().tolist() == [False, True, False, False]
    assert sim.out_of_bounds_worlds().tolist() == [False, False, True, True]
    kept_qpos, kept_qvel = sim.qpos[0].clone(), sim.qvel[0].clone()
    sim.sanitize(sim.nonfinite_worlds() | sim.out_of_bounds_worlds())
    torch.testing.assert_close(sim.qpos[1:], sim.qpos0.expand(WORLDS - 1, -1))
    assert torch.count_nonzero(sim.qvel[1:]) == 0
    assert torch.equal(sim.qpos[0], kept_qpos) and torch.equal(sim.qvel[0], kept_qvel)
    assert not (sim.nonfinite_worlds() | sim.out_of_bounds_worlds()).any()


def test_sim_options_are_written_into_the_model_and_unknown_ones_refused():
    mjm = load_mjmodel()
    cfg = dataclasses.replace(SimConfig(), timestep_s=0.002, integrator="euler", solver="cg", iterations=7)
    apply_sim_options(mjm, cfg)
    assert mjm.opt.timestep == 0.002 and mjm.opt.iterations == 7
    assert mjm.opt.integrator == mujoco.mjtIntegrator.mjINT_EULER and mjm.opt.solver == mujoco.mjtSolver.mjSOL_CG
    with pytest.raises(BmimicError, match=r"^sim.solver: unknown value 'pgs'"):
        apply_sim_options(mjm, dataclasses.replace(SimConfig(), solver="pgs"))


def test_bytes_per_world_grow_with_the_contact_and_constraint_buffers():
    mjm = load_mjmodel()
    small = physics_bytes_per_world(mjm, SimConfig())
    large = physics_bytes_per_world(mjm, dataclasses.replace(SimConfig(), nconmax=96, njmax=512))
    assert 0 < small < large
    # measured once per model and budgets: asked again, the same answers, each for its own key
    assert physics_bytes_per_world(mjm, SimConfig()) == small
    assert physics_bytes_per_world(mjm, dataclasses.replace(SimConfig(), nconmax=96, njmax=512)) == large


def test_bytes_per_world_are_measured_for_each_model_not_remembered_across_models():
    """A model of other sizes (one free ball) is measured, not answered from the G1's measurement."""
    mjm = load_mjmodel()
    spec = mujoco.MjSpec.from_string("<mujoco><worldbody><body><freejoint/><geom size='0.1'/></body></worldbody></mujoco>")
    ball = spec.compile()
    g1 = physics_bytes_per_world(mjm, SimConfig())
    one = physics_bytes_per_world(ball, SimConfig())
    assert 0 < one < g1
