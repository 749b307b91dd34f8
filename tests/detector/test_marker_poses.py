"""The poses of a frame's markers solved together (marker_poses.solve_markers) against pose.solve of each
alone, the scalar form it replaces in the detector: squares anywhere in view, any tilt, with and without
the lens's undistortion Jacobian and the corners' own covariance, a square behind the camera among them."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.detector import marker_poses, pose

K = np.array([[457.0, 0.0, 319.5], [0.0, 459.0, 241.25], [0.0, 0.0, 1.0]])
SIZE = 0.16


def _square(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy undistorted corners of a square in view, a stretch and a corner covariance for it."""
    T = RigidTransform.from_components(
        [rng.uniform(-0.5, 0.5), rng.uniform(-0.4, 0.4), rng.uniform(0.6, 4.0)],
        Rotation.from_euler(
            "xyz", [180 + rng.uniform(-60, 60), rng.uniform(-60, 60), rng.uniform(0, 360)], degrees=True
        ),
    )
    P = T.apply(pose.object_corners(SIZE))
    img = (P @ K.T)[:, :2] / P[:, 2:] + rng.normal(0, 0.1, (4, 2))
    stretch = np.eye(2) * rng.uniform(0.95, 1.1, (4, 1, 1)) + rng.normal(0, 0.02, (4, 2, 2))
    A = rng.normal(0, 0.05, (8, 8))
    return img, stretch, A @ A.T + 0.01 * np.eye(8)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**31),
    n=st.integers(1, 6),
    stretched=st.booleans(),
    own_cov=st.lists(st.booleans(), min_size=6, max_size=6),
    measured=st.booleans(),
)
def test_each_markers_pose_is_what_it_gets_alone(
    seed: int, n: int, stretched: bool, own_cov: list[bool], measured: bool
):
    rng = np.random.default_rng(seed)
    squares = [_square(rng) for _ in range(n)]
    corners = [s[0] for s in squares]
    if n > 1:
        corners[1] = corners[1] * np.array([-1.0, 1.0]) + np.array([640.0, 0.0])  # mirrored: maybe no pose
    stretches = [s[1] if stretched else None for s in squares]
    covs = [s[2] if own_cov[k] else None for k, s in enumerate(squares)]
    noise = [float(rng.uniform(0.05, 0.3)) if measured else 0.0 for _ in squares]
    sigmas = [pose.SIGMA_PX_APRILTAG] * n
    alone = [pose.solve(c, SIZE, K, sigmas[k], stretches[k], noise[k], covs[k]) for k, c in enumerate(corners)]
    together = marker_poses.solve_markers(corners, [SIZE] * n, K, sigmas, stretches, noise, covs)
    for a, b in zip(alone, together, strict=True):
        assert (a is None) == (b is None)
        if a is None or b is None:
            continue
        for name in ("p_m", "q_xyzw", "reprojection_error_px", "ambiguity", "p_alt_m", "q_alt_xyzw"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None) == (y is None)
            if x is not None:
                np.testing.assert_array_equal(x, y)  # the same OpenCV calls and formulas
        assert b.sigma_m == pytest.approx(a.sigma_m, rel=1e-12, abs=0.0)
        assert (a.covariance is None) == (b.covariance is None)
        if a.covariance is not None:
            scale = np.abs(a.covariance).max()
            np.testing.assert_allclose(b.covariance, a.covariance, rtol=0, atol=1e-12 * scale)
