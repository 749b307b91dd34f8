"""One rotation in plain floats (detector/rotations.py) against scipy's Rotation, which it replaces on the
detector's per-marker path."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.detector import rotations

axis = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=3, max_size=3).filter(
    lambda v: np.linalg.norm(v) > 1e-3
)
angle = st.one_of(st.floats(0.0, 1e-3), st.floats(1e-3, 3.1))


@settings(max_examples=300, deadline=None)
@given(axis=axis, angle=angle)
def test_each_conversion_gives_scipys_value(axis: list[float], angle: float):
    r = np.array(axis) / np.linalg.norm(axis) * angle
    q = Rotation.from_rotvec(r).as_quat()
    np.testing.assert_allclose(rotations.quat_from_rotvec(r), q, rtol=0, atol=1e-15)
    R = Rotation.from_quat(q).as_matrix()
    np.testing.assert_allclose(rotations.matrix_from_quat(q), R, rtol=0, atol=1e-15)
    q_m = rotations.quat_from_matrix(R)
    q_s = Rotation.from_matrix(R).as_quat()
    assert min(np.abs(q_m - q_s).max(), np.abs(q_m + q_s).max()) < 1e-14  # q and -q: one rotation
    np.testing.assert_allclose(rotations.rotvec_from_matrix(R), Rotation.from_matrix(R).as_rotvec(), rtol=0, atol=1e-13)


@settings(max_examples=100, deadline=None)
@given(
    q=st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=4, max_size=4).filter(lambda v: np.linalg.norm(v) > 0.1)
)
def test_a_quaternion_not_of_unit_length_is_normalised_as_scipy_does(q: list[float]):
    np.testing.assert_allclose(rotations.matrix_from_quat(np.array(q)), Rotation.from_quat(q).as_matrix(), atol=1e-15)


@settings(max_examples=100, deadline=None)
@given(quats=st.lists(st.lists(st.floats(-2.0, 2.0, allow_nan=False), min_size=4, max_size=4), min_size=1, max_size=8))
def test_stacked_quaternions_give_each_ones_matrix_bit_for_bit(quats: list[list[float]]):
    q = np.array(quats)
    q = q[np.linalg.norm(q, axis=1) > 1e-3]  # not normalisable
    got = rotations.matrices_from_quats(q)
    assert got.shape == (len(q), 3, 3)
    for k in range(len(q)):
        np.testing.assert_array_equal(got[k], rotations.matrix_from_quat(q[k]))
        np.testing.assert_allclose(got[k], Rotation.from_quat(q[k]).as_matrix(), rtol=0, atol=1e-15)
