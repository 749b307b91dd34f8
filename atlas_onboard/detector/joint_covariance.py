"""The covariance of a joint solve (one pose fitted to the corners of several squares of an entity):
the unweighted fit's spread, each square's corners with their own covariance, the lens model's residual
where the square lies, and a square that the fit misses by more than its covariance allows grown."""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri  # chi-square's inverse survival function

from atlas_onboard.detector.pose import CornerFit

# How well a calibrated lens model is known, as a fraction of the correction it applies at a point: a
# calibration's residual (tenths of a pixel where the lens bends the image by a hundred) grows with the
# distortion it corrects, and differs between image regions.
LENS_RESIDUAL = 0.002


def lens_residual_covariance(
    corners_und: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> NDArray[np.float64]:
    """(8, 8) covariance (undistorted px^2) of one square's four corners ``corners_und`` (4, 2) moved
    alike along the radius by the lens model's residual where the square lies: standard deviation
    ``LENS_RESIDUAL`` times how far the model moves the square's centre (undistorted minus image
    pixels). Different for squares in different parts of the image, which a joint solve's rotation
    rests on; zero without distortion."""
    return lens_residual_covariances([corners_und], K, dist, fisheye)[0]


def lens_residual_covariances(
    squares: list[NDArray[np.float64]], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> list[NDArray[np.float64]]:
    """:func:`lens_residual_covariance` of several squares (undistorted corners (4, 2) each), their centres
    through the lens in one call."""
    if not np.any(dist):
        return [np.zeros((8, 8)) for _ in squares]
    c = np.array([np.asarray(q, dtype=float).reshape(4, 2).mean(axis=0) for q in squares])
    rays = np.column_stack([(c[:, 0] - K[0, 2]) / K[0, 0], (c[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(c))])
    if fisheye:
        img = cv2.fisheye.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)[0]
    else:
        img = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, dist)[0]
    v = np.tile(c - img.reshape(-1, 2), (1, 4))  # every corner along the radius, by the model's correction there
    return list(LENS_RESIDUAL**2 * (v[:, :, None] * v[:, None, :]))


SQUARE_MISFIT_LEVEL = 0.9  # a square's miss in a joint fit beyond this quantile of its chi-square grows its block


def joint_covariance(
    fit: CornerFit, img_px: NDArray[np.float64], square_covs: list[NDArray[np.float64]]
) -> NDArray[np.float64] | None:
    """6x6 covariance of the pose of ``fit`` that an unweighted least-squares fit (:func:`pose.solve_joint`)
    found from several squares' corners (``fit.obj_m`` (4M, 3), ``img_px`` (4M, 2) undistorted, square by
    square), each square's corners with their (8, 8) covariance in ``square_covs``.

    The fit weighs every corner alike, so its spread is the sandwich ``A^-1 J^T W J A^-1`` (A = J^T J,
    W the corners' block-diagonal covariance), not the weighted fit's ``(J^T W^-1 J)^-1``, which is
    smaller wherever the corners' noise differs. A square's edge fit can be off by more than its own
    scatter shows (its background, blur, place in the lens) and the other squares reveal it: its block
    grows by how much more the fit misses it than W allows (its residual's quadratic form over that
    form's expectation ``tr(W_m^-1 [(I - H) W (I - H)^T]_mm)``, H = J A^-1 J^T), when the miss is
    significant (``SQUARE_MISFIT_LEVEL``). None if J is singular."""
    J = fit.jacobian()
    A = J.T @ J
    if fit.n_corners < 3 or not np.all(np.isfinite(A)) or np.linalg.cond(A) > 1e14:
        return None
    Ai = np.linalg.inv(A)
    r = (np.asarray(img_px, dtype=float).reshape(-1, 2) - fit.projected_px()).ravel()
    covs = np.array(square_covs, dtype=float)  # (M, 8, 8)
    n = len(covs)
    M = np.eye(len(r)) - J @ Ai @ J.T
    # The diagonal blocks of M W M^T, W block-diagonal: M's rows of square k times each block, summed.
    Mb = M.reshape(n, 8, n, 8)
    MW = np.einsum("kajb,jbc->kajc", Mb, covs)
    expected = np.einsum("kajc,kdjc->kad", MW, Mb)
    try:  # each square's W_m^-1 [r_m, expected_mm] at once
        X = np.linalg.solve(covs, np.concatenate([r.reshape(n, 8, 1), expected], axis=2))
    except np.linalg.LinAlgError:
        return None
    seen = np.einsum("ka,ka->k", r.reshape(n, 8), X[:, :, 0])
    allowed = np.trace(X[:, :, 1:], axis1=1, axis2=2)
    # Grown only when the miss is unlikely under W (the form about chi-square with ``allowed`` degrees of
    # freedom): growing on every chance excess would make consistent squares cautious.
    positive = allowed > 0
    limit = chdtri(np.where(positive, allowed, 1.0), 1.0 - SQUARE_MISFIT_LEVEL)
    grow = np.where(positive & (seen > limit), seen / np.where(positive, allowed, 1.0), 1.0)
    Jb = J.reshape(n, 8, 6)
    inner = np.einsum("kai,kab,kbj->ij", Jb, covs * grow[:, None, None], Jb)  # J^T diag(grown) J
    C = Ai @ inner @ Ai
    return (C + C.T) / 2.0
