"""The joint pose of a moving rolling-shutter camera: the pose at the frame's stamp, the camera's angular
rate and its velocity solved together from several squares' corners, each corner at the instant its row
was read (:mod:`atlas_onboard.core.shutter`).

A corner ``X`` (object frame) is at ``P0 = R X + p`` in the camera at the stamp and is seen ``dt`` later at
``P = exp(-[omega] dt) (P0 - v dt)``. The rate and velocity have priors (the autopilot's gyro with its noise,
bias and age; the camera's own velocity estimate), and the image measures what they leave uncertain: squares
at different rows and depths see the motion as a shear that no rigid pose explains. The fit weighs each
square's corners by their (8, 8) covariance (edge fit and lens residual); the pose's covariance is the
posterior's, marginal over the rate and velocity, with a square that the fit misses beyond its covariance
grown as :func:`atlas_onboard.detector.joint_covariance.joint_covariance` grows it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.special import chdtri

from atlas_onboard.core.shutter import CameraMotion
from atlas_onboard.detector.joint_covariance import SQUARE_MISFIT_LEVEL

ITERATIONS = 6
STEP_TOL = 1e-9  # a Gauss-Newton step whose largest component (m, rad, rad/s, m/s) is below this ends them
MIN_PRIOR_VAR = 1e-12  # a prior variance no smaller than this (an exact prior is a very tight one)


@dataclass(frozen=True, slots=True)
class MovingPose:
    """The pose at the stamp (``R``, ``p``: object in camera), the rate ``omega`` (rad/s) and velocity
    ``velocity`` (m/s), both camera frame; ``covariance`` (12, 12) of ``[dp, dtheta, omega, v]`` (dtheta
    about the object's axes); the RMS corner residual (undistorted px) and each square's growth factor."""

    R: NDArray[np.float64]
    p: NDArray[np.float64]
    omega: NDArray[np.float64]
    velocity: NDArray[np.float64]
    covariance: NDArray[np.float64]
    rms_px: float

    def pose_covariance(self) -> NDArray[np.float64]:
        """(6, 6) of ``[dp, dtheta]``, marginal over the motion."""
        return self.covariance[:6, :6]


def _project(
    R: NDArray[np.float64],
    p: NDArray[np.float64],
    w: NDArray[np.float64],
    v: NDArray[np.float64],
    obj: NDArray[np.float64],
    dt: NDArray[np.float64],
    K: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Undistorted pixels (N, 2) of ``obj`` (N, 3) seen at ``dt`` (N,) and their Jacobian (2N, 12)."""
    P0 = obj @ R.T + p
    Q = P0 - dt[:, None] * v
    E = Rotation.from_rotvec(-dt[:, None] * w[None, :]).as_matrix()  # (N, 3, 3)
    P = np.einsum("nij,nj->ni", E, Q)
    z = P[:, 2]
    fx, fy = K[0, 0], K[1, 1]
    uv = np.column_stack([fx * P[:, 0] / z + K[0, 2], fy * P[:, 1] / z + K[1, 2]])
    D = np.zeros((len(P), 2, 3))
    D[:, 0, 0], D[:, 1, 1] = fx / z, fy / z
    D[:, 0, 2], D[:, 1, 2] = -fx * P[:, 0] / z**2, -fy * P[:, 1] / z**2
    X = obj
    hat = np.zeros((len(X), 3, 3))  # [X]x
    hat[:, 0, 1], hat[:, 0, 2], hat[:, 1, 2] = -X[:, 2], X[:, 1], -X[:, 0]
    hat[:, 1, 0], hat[:, 2, 0], hat[:, 2, 1] = X[:, 2], -X[:, 1], X[:, 0]
    dP = np.zeros((len(X), 3, 12))
    DE = np.einsum("nij,njk->nik", D, E)  # (N, 2, 3)
    J = np.zeros((len(X), 2, 12))
    J[:, :, :3] = DE
    J[:, :, 3:6] = -np.einsum("nij,jk,nkl->nil", DE, R, hat)
    # d(exp(-[w] dt) Q)/dw = dt [Q]x to first order in |w dt| (thousandths of a radian over a readout).
    Qh = np.zeros((len(X), 3, 3))
    Qh[:, 0, 1], Qh[:, 0, 2], Qh[:, 1, 2] = -Q[:, 2], Q[:, 1], -Q[:, 0]
    Qh[:, 1, 0], Qh[:, 2, 0], Qh[:, 2, 1] = Q[:, 2], -Q[:, 1], Q[:, 0]
    J[:, :, 6:9] = dt[:, None, None] * np.einsum("nij,njk->nik", D, Qh)
    J[:, :, 9:] = -dt[:, None, None] * DE
    del dP
    return uv, J.reshape(-1, 12)


def solve_moving(
    obj: NDArray[np.float64],
    img_px: NDArray[np.float64],
    dt_s: NDArray[np.float64],
    square_covs: list[NDArray[np.float64]],
    K: NDArray[np.float64],
    motion: CameraMotion,
    R0: NDArray[np.float64],
    p0: NDArray[np.float64],
) -> MovingPose | None:
    """The pose (from ``R0``, ``p0``), rate and velocity that fit the squares' corners ``img_px`` (4M, 2,
    undistorted, not moved to the stamp) of ``obj`` (4M, 3, object frame) seen ``dt_s`` (4M,) after the
    stamp, square by square with their (8, 8) covariances, given the priors of ``motion`` (the rate and
    velocity the image is corrected by, and what they leave uncertain: :meth:`CameraMotion.omega_error`).
    None when the fit is singular or leaves the object behind the camera."""
    obj = np.asarray(obj, dtype=float).reshape(-1, 3)
    img = np.asarray(img_px, dtype=float).reshape(-1, 2)
    dt = np.asarray(dt_s, dtype=float).reshape(-1)
    n = len(square_covs)
    covs = np.asarray(square_covs, dtype=float)
    try:
        Linv = np.linalg.inv(np.linalg.cholesky(covs))  # (M, 8, 8): whitens each square's residual
    except np.linalg.LinAlgError:
        return None
    w_prior, v_prior = motion.omega_used(), motion.velocity_used()
    prior_cov = np.zeros((6, 6))
    prior_cov[:3, :3], prior_cov[3:, 3:] = motion.omega_error(), motion.velocity_error()
    prior_cov += MIN_PRIOR_VAR * np.eye(6)
    try:
        prior_info = np.linalg.inv(prior_cov)
    except np.linalg.LinAlgError:
        return None
    prior_mean = np.concatenate([w_prior, v_prior])
    R, p = np.asarray(R0, dtype=float), np.asarray(p0, dtype=float)
    m = prior_mean.copy()
    for _ in range(ITERATIONS):
        uv, J = _project(R, p, m[:3], m[3:], obj, dt, K)
        if np.any(~np.isfinite(uv)):
            return None
        r = (img - uv).reshape(n, 8)
        rw = np.einsum("kab,kb->ka", Linv, r).ravel()
        Jw = np.einsum("kab,kbj->kaj", Linv, J.reshape(n, 8, 12)).reshape(-1, 12)
        H = Jw.T @ Jw
        H[6:, 6:] += prior_info
        g = Jw.T @ rw
        g[6:] += prior_info @ (prior_mean - m)
        try:
            step = np.linalg.solve(H, g)
        except np.linalg.LinAlgError:
            return None
        p = p + step[:3]
        R = R @ Rotation.from_rotvec(step[3:6]).as_matrix()
        m = m + step[6:]
        if np.max(np.abs(step)) < STEP_TOL:
            break
    uv, J = _project(R, p, m[:3], m[3:], obj, dt, K)
    if np.any((obj @ R.T + p)[:, 2] <= 0) or not np.all(np.isfinite(uv)):
        return None
    r = (img - uv).reshape(n, 8)
    Jb = J.reshape(n, 8, 12)
    Jw = np.einsum("kab,kbj->kaj", Linv, Jb).reshape(-1, 12)
    H = Jw.T @ Jw
    H[6:, 6:] += prior_info
    if not np.all(np.isfinite(H)) or np.linalg.cond(H) > 1e14:
        return None
    Hi = np.linalg.inv(H)
    grow = _growth(Jb, Linv, covs, r, Hi)
    # The posterior's spread with each misfitting square's block grown (the sandwich H^-1 B H^-1, B the
    # information the fit weighed, its image part scaled per square).
    Jwb = Jw.reshape(n, 8, 12)
    B = np.einsum("kai,k,kaj->ij", Jwb, grow, Jwb)
    B[6:, 6:] += prior_info
    C = Hi @ B @ Hi
    C = (C + C.T) / 2.0
    rms = float(np.sqrt(np.mean(np.sum(r.reshape(-1, 2) ** 2, axis=1))))
    return MovingPose(R, p, m[:3], m[3:], C, rms)


def _growth(
    Jb: NDArray[np.float64],
    Linv: NDArray[np.float64],
    covs: NDArray[np.float64],
    r: NDArray[np.float64],
    Hi: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Each square's factor (M,): its whitened residual's square over what the weighted fit leaves it
    (``8 - tr`` of its block of the whitened hat matrix), when that miss is unlikely under its covariance
    (beyond the ``SQUARE_MISFIT_LEVEL`` quantile of the chi-square); else 1."""
    n = len(covs)
    Jw = np.einsum("kab,kbj->kaj", Linv, Jb)  # (M, 8, 12)
    rw = np.einsum("kab,kb->ka", Linv, r)
    seen = np.sum(rw**2, axis=1)
    lev = np.einsum("kai,ij,kaj->k", Jw, Hi, Jw)  # trace of each square's block of Jw H^-1 Jw^T
    allowed = np.maximum(8.0 - lev, 0.0)
    positive = allowed > 1e-9
    safe = np.where(positive, allowed, 1.0)
    limit = chdtri(safe, 1.0 - SQUARE_MISFIT_LEVEL)
    return np.where(positive & (seen > limit), seen / safe, 1.0) if n else np.ones(0)
