"""Known answers and invariants of the batched quaternion helpers."""

from __future__ import annotations

import math

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from bmimic.envs.quat import (
    first_two_columns,
    matrix_from_quat,
    normalize,
    quat_apply,
    quat_apply_inverse,
    quat_conj,
    quat_error_magnitude,
    quat_from_euler_xyz,
    quat_mul,
    yaw_quat,
)

Z90 = torch.tensor([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)])


def test_rotation_about_z():
    v = torch.tensor([1.0, 0.0, 0.0])
    assert torch.allclose(quat_apply(Z90, v), torch.tensor([0.0, 1.0, 0.0]), atol=1e-6)
    assert torch.allclose(quat_apply_inverse(Z90, v), torch.tensor([0.0, -1.0, 0.0]), atol=1e-6)


def test_euler_and_yaw():
    q = quat_from_euler_xyz(torch.tensor(0.3), torch.tensor(-0.2), torch.tensor(1.1))
    y = yaw_quat(q)
    assert torch.allclose(y, quat_from_euler_xyz(torch.tensor(0.0), torch.tensor(0.0), torch.tensor(1.1)), atol=1e-6)
    assert math.isclose(float(quat_error_magnitude(Z90, torch.tensor([1.0, 0, 0, 0]))), math.pi / 2, rel_tol=1e-6)


def test_six_d_layout():
    m = matrix_from_quat(Z90)
    six = first_two_columns(Z90)
    assert torch.allclose(six, torch.stack([m[0, 0], m[0, 1], m[1, 0], m[1, 1], m[2, 0], m[2, 1]]))


quats = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(lambda x: sum(v * v for v in x) > 0.1)


@settings(max_examples=100, deadline=None)
@given(quats, quats, st.lists(st.floats(-5, 5), min_size=3, max_size=3))
def test_invariants(a, b, v):
    qa, qb, v = normalize(torch.tensor(a, dtype=torch.float64)), normalize(torch.tensor(b, dtype=torch.float64)), torch.tensor(v, dtype=torch.float64)
    # composition matches matrix product; rotation preserves length; inverse undoes
    assert torch.allclose(matrix_from_quat(quat_mul(qa, qb)), matrix_from_quat(qa) @ matrix_from_quat(qb), atol=1e-9)
    assert torch.allclose(quat_apply(qa, v).norm(), v.norm(), atol=1e-9)
    assert torch.allclose(quat_apply_inverse(qa, quat_apply(qa, v)), v, atol=1e-9)
    assert torch.allclose(quat_apply(qa, v), matrix_from_quat(qa) @ v, atol=1e-9)
    err = quat_error_magnitude(qa, qb)
    assert 0 <= float(err) <= math.pi + 1e-9
    assert math.isclose(float(err), float(quat_error_magnitude(qb, qa)), abs_tol=1e-7)
    assert float(quat_error_magnitude(qa, -qa)) < 1e-6  # q and -q are the same rotation
    yq = yaw_quat(qa)
    assert abs(float(yq[1])) < 1e-12 and abs(float(yq[2])) < 1e-12
    assert torch.allclose(quat_mul(qa, quat_conj(qa))[1:], torch.zeros(3, dtype=torch.float64), atol=1e-9)
