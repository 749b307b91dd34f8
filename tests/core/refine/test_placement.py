"""The leave-one-out placement's rotation vectors (placement.rotvecs_from_matrices) against scipy's, which
they replace there: any rotation, near the identity (the Taylor branch) and near a half turn; and two poses,
each placed by the other alone: that other pose itself."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.refine.placement import leave_one_out, leave_one_out_many, rotvecs_from_matrices

angle = st.one_of(st.floats(0.0, 2e-3), st.floats(0.0, np.pi - 1e-6), st.floats(np.pi - 1e-3, np.pi - 1e-9))
axis = st.tuples(*[st.floats(-1.0, 1.0) for _ in range(3)]).filter(lambda v: float(np.dot(v, v)) > 1e-6)


@settings(max_examples=300, deadline=None)
@given(angles=st.lists(angle, min_size=1, max_size=12), axes=st.lists(axis, min_size=12, max_size=12), turn=axis)
def test_rotvecs_are_scipys(angles: list[float], axes: list[tuple[float, float, float]], turn: tuple) -> None:
    """Products of rotations (as the residuals have them): scipy's rotation vectors to a few ulps."""
    a = np.array(axes[: len(angles)], dtype=float)
    rotvecs = a / np.linalg.norm(a, axis=1, keepdims=True) * np.array(angles)[:, None]
    R_ref = Rotation.from_rotvec(np.array(turn, dtype=float)).as_matrix()
    R = R_ref.T @ (Rotation.from_rotvec(rotvecs).as_matrix() @ R_ref)
    want = Rotation.from_matrix(R).as_rotvec()
    np.testing.assert_allclose(rotvecs_from_matrices(R), want, rtol=0.0, atol=1e-14)


@settings(max_examples=200, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    scale=st.floats(1e-8, 1e-2),
    rotvecs=st.lists(axis, min_size=2, max_size=2),
)
def test_two_poses_each_placed_by_the_other_are_that_other(seed: int, scale: float, rotvecs: list) -> None:
    """Two candidate poses: the mean of each one's others is the other pose exactly (its position, its
    rotation, its covariance), and those others' chi-square about it is zero."""
    rng = np.random.default_rng(seed)
    P = rng.normal(0.0, 2.0, (2, 3))
    Rs = Rotation.from_rotvec(np.array(rotvecs, dtype=float) * 3.0).as_matrix()
    A = rng.normal(0.0, 1.0, (2, 6, 6))
    C = scale * (A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(6))
    got = leave_one_out(P, Rs, C)
    assert got is not None
    p, R, cov, chi2 = got
    assert np.array_equal(p, P[::-1]) and np.array_equal(R, Rs[::-1])
    np.testing.assert_allclose(cov, C[::-1], rtol=0.0, atol=1e-15 * scale)
    assert np.array_equal(chi2, np.zeros(2))


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), b=st.integers(1, 6), n=st.integers(2, 8), scale=st.floats(1e-8, 1e-2))
def test_many_images_at_once_are_each_image_alone(seed: int, b: int, n: int, scale: float) -> None:
    """b images of n candidates each through leave_one_out_many: every figure of each image bit for bit
    what leave_one_out gives that image alone, and one candidate of each image placed alone (``row``) that
    candidate's figures."""
    rng = np.random.default_rng(seed)
    P = rng.normal(0.0, 2.0, (b, n, 3))
    Rs = Rotation.from_rotvec(rng.normal(0.0, 1.0, (b * n, 3))).as_matrix().reshape(b, n, 3, 3)
    A = rng.normal(0.0, 1.0, (b, n, 6, 6))
    C = scale * (A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(6))
    many = leave_one_out_many(P, Rs, C)
    assert many is not None
    for j in range(b):
        alone = leave_one_out(P[j], Rs[j], C[j])
        assert alone is not None
        for got, want in zip(many, alone, strict=True):
            assert np.array_equal(got[j], want)
    row = rng.integers(0, n, b)
    one = leave_one_out_many(P, Rs, C, row)
    assert one is not None
    for got, want in zip(one, many, strict=True):
        assert got.shape[:2] == (b, 1)
        assert np.array_equal(got[:, 0], want[np.arange(b), row])
