"""The robust mean of a marker's evidence against known answers: residuals about a reference, the
information-weighted mean with its outliers gated, the independent views and their scatter."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from atlas_onboard.core.refine.mean import independent_views, residuals, robust_mean, view_labels, view_scatter
from atlas_onboard.core.refine.records import Evidence


def _evidence(camera: str, t_us: int) -> Evidence:
    return Evidence(np.zeros(3), np.eye(3), np.eye(6), np.array([0.0, 0.0, 1.0]), camera, t_us)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 6))
def test_residuals_are_the_offsets_the_poses_were_built_with(seed, n):
    rng = np.random.default_rng(seed)
    p_ref, R_ref = rng.normal(size=3), Rotation.random(rng=rng).as_matrix()
    dp = rng.normal(size=(n, 3))
    axes = rng.normal(size=(n, 3))
    dtheta = axes / np.linalg.norm(axes, axis=1, keepdims=True) * rng.uniform(0.0, 3.0, (n, 1))
    P = p_ref + dp
    Rs = R_ref @ Rotation.from_rotvec(dtheta).as_matrix()  # dtheta about the reference's own axes
    np.testing.assert_allclose(residuals(P, Rs, p_ref, R_ref), np.hstack([dp, dtheta]), atol=1e-9)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(3, 12))
def test_equally_weighted_poses_have_their_arithmetic_mean_and_all_are_inliers(seed, n):
    # Offsets bounded within half a sigma of the centre: every pose lies inside the gate by construction
    # (Gaussian draws would put one outside it now and then, and rightly have it gated).
    rng = np.random.default_rng(seed)
    p0, R0 = rng.normal(size=3), Rotation.random(rng=rng)
    P = p0 + rng.uniform(-0.005, 0.005, (n, 3))
    Rs = (R0 * Rotation.from_rotvec(rng.uniform(-0.005, 0.005, (n, 3)))).as_matrix()
    W = np.broadcast_to(np.diag([1e4] * 3 + [1e4] * 3), (n, 6, 6)).copy()
    out = robust_mean(P, Rs, W, 1e-3)
    assert out is not None
    p, R, inlier, scale = out
    assert inlier.all() and scale >= 1.0
    np.testing.assert_allclose(p, P.mean(axis=0), atol=1e-9)
    # The rotation: the mean of the small rotations about it is zero.
    np.testing.assert_allclose(residuals(P, Rs, p, R)[:, 3:].mean(axis=0), 0.0, atol=1e-6)


def test_a_pose_a_metre_off_among_centimetre_scatter_is_gated_out_and_weighs_nothing():
    rng = np.random.default_rng(4)
    n = 10
    P = rng.normal(0.0, 0.01, (n, 3))
    P[3] = [1.0, 0.0, 0.0]
    Rs = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    W = np.broadcast_to(np.eye(6) / 0.01**2, (n, 6, 6)).copy()
    out = robust_mean(P, Rs, W, 1e-3)
    assert out is not None
    p, _, inlier, _ = out
    assert not inlier[3] and inlier.sum() == n - 1
    np.testing.assert_allclose(p, np.delete(P, 3, axis=0).mean(axis=0), atol=1e-9)


def test_fewer_than_two_inliers_is_no_mean():
    assert robust_mean(np.zeros((1, 3)), np.eye(3)[None], np.eye(6)[None], 1e-3) is None


def test_each_camera_starts_a_new_view_after_the_gap_and_outliers_belong_to_none():
    items = [
        _evidence("a", 0),
        _evidence("a", 100_000),  # 0.1 s later: the same view
        _evidence("b", 200_000),  # another camera: its own view
        _evidence("a", 1_000_000),  # 1 s after the view's start: a new one
        _evidence("a", 1_050_000),
        _evidence("a", 2_000_000),  # an outlier: no view
    ]
    inlier = np.array([True, True, True, True, True, False])
    np.testing.assert_array_equal(view_labels(items, inlier, 0.5), [0, 0, 1, 2, 2, -1])
    assert independent_views(items, inlier, 0.5) == 3
    assert independent_views(items, inlier, 2.0) == 2  # camera a's images all in one view
    assert independent_views(items, np.zeros(6, dtype=bool), 0.5) == 0


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), views=st.integers(1, 5))
def test_the_scatter_of_one_image_views_is_their_chi_square_about_their_mean(seed, views):
    rng = np.random.default_rng(seed)
    r = rng.normal(size=(views, 6))
    sig2 = rng.uniform(0.5, 2.0, (views, 6))
    W = np.stack([np.diag(1.0 / s) for s in sig2])
    out = view_scatter(r, W, np.arange(views))
    assert out is not None
    cov, chi2, dof = out
    # Independent views, information-weighted: per axis, 1 / sum(1 / sigma^2) and the weighted mean.
    expected_var = 1.0 / (1.0 / sig2).sum(axis=0)
    np.testing.assert_allclose(cov, np.diag(expected_var), atol=1e-12)
    mean = expected_var * (r / sig2).sum(axis=0)
    np.testing.assert_allclose(chi2, float(((r - mean) ** 2 / sig2).sum()), rtol=1e-9, atol=1e-12)
    assert dof == 6 * (views - 1)


def test_images_of_one_view_count_as_one_average_image():
    # Two identical images in view 0, one in view 1: view 0 is worth one image, not two.
    r = np.zeros((3, 6))
    W = np.broadcast_to(np.eye(6), (3, 6, 6)).copy()
    out = view_scatter(r, W, np.array([0, 0, 1]))
    assert out is not None
    np.testing.assert_allclose(out[0], np.eye(6) / 2.0, atol=1e-12)


def test_a_singular_information_is_no_scatter():
    assert view_scatter(np.zeros((1, 6)), np.zeros((1, 6, 6)), np.array([0])) is None
