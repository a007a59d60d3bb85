"""The evaluation's per-step measures (bmimic.envs.measures): every tracking error the run schema
declares is computed under its name, in the schema's order, with known answers on a planted state."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from bmimic.envs.measures import ERROR_TERMS, step_errors
from bmimic.runs.schema import ERROR_COLUMNS
from bmimic.sim2sim.rollout import Rollout


def test_every_declared_tracking_error_is_computed_by_name_in_the_evaluators_and_sim2sim():
    assert list(ERROR_TERMS) == list(ERROR_COLUMNS)
    assert all(callable(getattr(Rollout, f"_e_{name}", None)) for name in ERROR_COLUMNS)


def _planted_env(n: int = 3, bodies: int = 4, joints: int = 5):
    """Reference = robot moved 10 mm along x (anchor too), end-effector targets 20 mm along y, the same
    orientations, joints 0.1 rad and 0.5 rad/s off."""
    robot_pos = torch.randn(n, bodies, 3)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, bodies, 4)
    joint_pos, joint_vel = torch.randn(n, joints), torch.randn(n, joints)
    state = SimpleNamespace(
        robot_body_pos=robot_pos, ref_body_pos=robot_pos + torch.tensor([0.01, 0.0, 0.0]),
        robot_anchor_pos=robot_pos[:, 0], ref_anchor_pos=robot_pos[:, 0] + torch.tensor([0.01, 0.0, 0.0]),
        robot_body_quat=identity, ref_body_quat=identity, ref_body_quat_relative=identity,
        ref_body_pos_relative=robot_pos + torch.tensor([0.0, 0.02, 0.0]),
        joint_pos=joint_pos, ref_joint_pos=joint_pos + 0.1, joint_vel=joint_vel, ref_joint_vel=joint_vel - 0.5)
    return SimpleNamespace(state=state, bodies=SimpleNamespace(anchor=0, end_effectors=torch.tensor([2, 3])))


def test_planted_offsets_give_the_known_errors_in_the_schemas_units():
    errors = step_errors(_planted_env())
    assert errors.shape == (3, len(ERROR_COLUMNS))
    got = dict(zip(ERROR_COLUMNS, errors.T))
    expected = {"mpkpe_mm": 10.0, "mpkpe_rel_mm": 0.0, "anchor_ori_err_rad": 0.0, "body_ori_err_rad": 0.0,
                "joint_pos_err_rad": 0.1, "joint_vel_err_radps": 0.5, "ee_pos_err_mm": 20.0}
    assert set(got) == set(expected)
    for name, value in expected.items():
        assert got[name] == pytest.approx(torch.full((3,), value), abs=1e-4), name
