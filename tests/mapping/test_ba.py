"""Bundle adjustment on synthetic problems with known truth: accuracy, honest sigma, both Jacobians."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.mapping import ba
from tests.mapping.synthetic import make_problem


def _errors(sol: ba.Solution, M_true: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    dp = sol.M_world_marker[:, :3, 3] - M_true[:, :3, 3]
    # Rotation error as the rotation vector of R_est R_true^T (world axes, as the covariance).
    dr = Rotation.from_matrix(sol.M_world_marker[:, :3, :3] @ np.swapaxes(M_true[:, :3, :3], 1, 2)).as_rotvec()
    return dp, dr


def test_adjustment_recovers_the_map_and_its_sigma_is_honest() -> None:
    """Over seeds, each free marker's error against its reported covariance: the mean NEES of the
    position (3 dof) and of the rotation (3 dof) must be about 3, neither over- nor under-confident."""
    nees_p, nees_r, worst = [], [], []
    for seed in range(6):
        problem, M_true, _ = make_problem(seed, n_frames=40)
        sol = ba.solve(problem)
        dp, dr = _errors(sol, M_true)
        assert np.allclose(sol.M_world_marker[0], M_true[0])  # the fixed anchor stays put
        seen = np.bincount(problem.obs_marker, minlength=len(M_true))
        for m in range(1, len(M_true)):
            C = sol.covariance[m]
            if seen[m] < 4 or not np.all(np.isfinite(C)):  # not determined: an infinite covariance says so
                continue
            nees_p.append(dp[m] @ np.linalg.solve(C[3:, 3:], dp[m]))
            nees_r.append(dr[m] @ np.linalg.solve(C[:3, :3], dr[m]))
            worst.append(np.linalg.norm(dp[m]) / np.sqrt(np.trace(C[3:, 3:])))
        assert 0.2 < sol.sigma0_px / 0.3 < 1.3  # the residual sigma is the corner noise
    assert len(nees_p) > 30
    assert 1.8 < np.mean(nees_p) < 4.5, np.mean(nees_p)
    assert 1.8 < np.mean(nees_r) < 4.5, np.mean(nees_r)
    assert np.max(worst) < 5.0


def test_analytic_and_numeric_jacobians_agree() -> None:
    problem, _M_true, _ = make_problem(3, n_frames=30)
    a = ba.solve(problem, jacobian="analytic")
    n = ba.solve(problem, jacobian="numeric")
    # The same minimum, to far less than its uncertainty, and the same covariance.
    sigma = a.position_sigma_m()[1:]
    ok = np.all(np.isfinite(sigma), axis=1)
    dp = np.abs(a.M_world_marker[1:, :3, 3] - n.M_world_marker[1:, :3, 3])
    assert ok.sum() >= 8
    assert np.all(dp[ok] < 0.02 * sigma[ok])
    assert np.allclose(a.position_sigma_m()[1:][ok], n.position_sigma_m()[1:][ok], rtol=0.01)


def test_the_projection_matches_opencv() -> None:
    import cv2

    from tests.mapping.synthetic import DIST, K

    rng = np.random.default_rng(0)
    P = np.column_stack([rng.uniform(-1, 1, (50, 2)), rng.uniform(1, 4, 50)])
    ours = ba.project(np.concatenate([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], DIST, [0, 0, 0]]), P)
    cv, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, DIST)
    assert np.allclose(ours, cv.reshape(-1, 2), atol=1e-9)


def test_a_prior_on_two_anchors_holds_them_within_their_sigma() -> None:
    problem, M_true, _ = make_problem(5, n_frames=40)
    # Anchor 4 surveyed with 2 cm of error and a sigma of 1 mm: the corners pull it back towards the
    # truth only as far as the prior lets them; anchor 0 is fixed.
    surveyed = problem.M_world_marker.copy()
    surveyed[4] = M_true[4]
    surveyed[4, 0, 3] += 0.002
    problem.M_world_marker = surveyed
    problem.anchors = [ba.Anchor(0), ba.Anchor(4, sigma_m=0.001, sigma_rad=np.radians(0.1))]
    sol = ba.solve(problem)
    moved = abs(sol.M_world_marker[4, 0, 3] - surveyed[4, 0, 3])
    assert 0.0 < moved < 0.003
    assert sol.covariance[4, 3, 3] > 0 and np.sqrt(sol.covariance[4, 3, 3]) < 0.001


@pytest.mark.parametrize("size", [4, 5, 8])
def test_lens_accepts_opencv_distortion_sizes(size: int) -> None:
    assert ba.Lens(np.eye(3), np.zeros(size)).coefficients().shape == (8,)
