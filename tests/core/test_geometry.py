"""Geometry on scipy: property tests of inverse and composition, array helpers against scipy objects."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import geometry
from atlas_onboard.errors import GeometryError

vec3 = arrays(float, 3, elements=st.floats(-50, 50, allow_nan=False))
quat = arrays(float, 4, elements=st.floats(-1, 1, allow_nan=False)).filter(lambda q: np.linalg.norm(q) > 0.1)


def transform(p, q):
    return RigidTransform.from_components(p, Rotation.from_quat(q))


@given(vec3, quat)
def test_inverse_composes_to_identity(p, q):
    T = transform(p, q)
    np.testing.assert_allclose((T.inv() * T).as_matrix(), np.eye(4), atol=1e-9)
    np.testing.assert_allclose((T * T.inv()).as_matrix(), np.eye(4), atol=1e-9)


@given(vec3, quat, vec3, quat, vec3, quat)
def test_composition_is_associative_and_matches_matrices(p1, q1, p2, q2, p3, q3):
    A, B, C = transform(p1, q1), transform(p2, q2), transform(p3, q3)
    np.testing.assert_allclose(((A * B) * C).as_matrix(), (A * (B * C)).as_matrix(), atol=1e-8)
    np.testing.assert_allclose((A * B).as_matrix(), A.as_matrix() @ B.as_matrix(), atol=1e-9)


@given(vec3, quat, vec3, quat)
def test_compose_arrays_matches_scipy(p1, q1, p2, q2):
    p, q = geometry.compose_arrays(p1[None], (q1 / np.linalg.norm(q1))[None], p2[None], (q2 / np.linalg.norm(q2))[None])
    expected = transform(p1, q1) * transform(p2, q2)
    np.testing.assert_allclose(geometry.pose_from_arrays(p[0], q[0]).as_matrix(), expected.as_matrix(), atol=1e-9)


@given(vec3, quat)
def test_invert_arrays_matches_scipy(p, q):
    pi, qi = geometry.invert_arrays(p, q / np.linalg.norm(q))
    np.testing.assert_allclose(
        geometry.pose_from_arrays(pi, qi).as_matrix(), transform(p, q).inv().as_matrix(), atol=1e-9
    )


@given(quat)
def test_canonical_quat_picks_one_of_q_and_minus_q(q):
    a, b = geometry.canonical_quat(q), geometry.canonical_quat(-q)
    np.testing.assert_array_equal(a, b)
    assert a[3] >= 0


def test_rotation_from_wxyz_rejects_bad_quaternions():
    with pytest.raises(GeometryError, match="zero quaternion"):
        geometry.rotation_from_wxyz([0, 0, 0, 0])
    with pytest.raises(GeometryError, match="norm 2"):
        geometry.rotation_from_wxyz([2, 0, 0, 0])
    with pytest.raises(GeometryError, match="finite"):
        geometry.rotation_from_wxyz([np.nan, 0, 0, 1])
    with pytest.raises(GeometryError, match=r"shape \(4,\)"):
        geometry.rotation_from_wxyz([1, 0, 0])


def test_rotation_from_wxyz_is_w_first():
    R = geometry.rotation_from_wxyz([np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])  # 90 deg about z
    np.testing.assert_allclose(R.apply([1, 0, 0]), [0, 1, 0], atol=1e-12)


def test_angle_between_ignores_quaternion_sign():
    q = Rotation.from_euler("xyz", [10, 20, 30], degrees=True).as_quat()
    assert geometry.angle_between(Rotation.from_quat(q), Rotation.from_quat(-q)) == pytest.approx(0.0, abs=1e-7)


@given(quat, quat)
def test_quat_multiply_is_scipys_composition(q1, q2):
    a, b = q1 / np.linalg.norm(q1), q2 / np.linalg.norm(q2)
    expected = (Rotation.from_quat(a) * Rotation.from_quat(b)).as_quat()
    got = geometry.quat_multiply(a, b)
    assert np.linalg.norm(got) == pytest.approx(1.0, abs=1e-12)
    # Equal as rotations: q and -q are the same one, so compare up to sign.
    assert min(np.linalg.norm(got - expected), np.linalg.norm(got + expected)) < 1e-12


@given(quat)
def test_quat_matrix_is_scipys_matrix(q):
    u = q / np.linalg.norm(q)
    np.testing.assert_allclose(geometry.quat_matrix(u), Rotation.from_quat(u).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(geometry.quat_matrix(-u), Rotation.from_quat(u).as_matrix(), atol=1e-12)


def test_quaternion_helpers_batch_like_scipy():
    r1, r2 = Rotation.random(50, random_state=1), Rotation.random(50, random_state=2)
    got = Rotation.from_quat(geometry.quat_multiply(r1.as_quat(), r2.as_quat()))
    assert np.all((got.inv() * (r1 * r2)).magnitude() < 1e-12)
    stacked = geometry.quat_matrix(r1.as_quat().reshape(5, 10, 4))
    np.testing.assert_allclose(stacked.reshape(50, 3, 3), r1.as_matrix(), atol=1e-12)
