"""The poses of all markers of a frame at once: :func:`pose.solve`'s arithmetic, its OpenCV calls marker by
marker and its small matrix algebra (whitening, the position sigma, the covariances and the other planar
solution's moment) stacked over the markers, each marker's result what :func:`pose.solve` gives it alone
(to an ulp or two of its matrix products)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.refine.placement import rotvecs_from_matrices
from atlas_onboard.detector.pose import (
    MIN_SIGMA_M,
    CornerFit,
    MarkerPose,
    corner_noise_px,
    object_corners,
    pose_covariance,
)
from atlas_onboard.detector.rotations import quat_from_rotvec

_UNSTRETCHED = np.tile(np.eye(2), (4, 1, 1))  # no distortion: each corner's undistortion Jacobian


@dataclass(frozen=True)
class _Fitted:
    """One marker's IPPE and Levenberg-Marquardt solve (OpenCV), before the stacked algebra."""

    index: int
    obj: NDArray[np.float64]  # (4, 3) object corners
    img: NDArray[np.float64]  # (4, 2) undistorted corners
    r0: NDArray[np.float64]
    t0: NDArray[np.float64]
    R0: NDArray[np.float64]
    dR: NDArray[np.float64]  # (3, 9): cv2.Rodrigues' Jacobian
    proj: NDArray[np.float64]  # (4, 2)
    J_proj: NDArray[np.float64]  # (8, 6): d(pixels) / d(rvec, tvec)
    alt: tuple[NDArray[np.float64], NDArray[np.float64]] | None
    ambiguity: float
    side_px: float


def _fit(index: int, corners: NDArray[np.float64], size_m: float, K: NDArray[np.float64]) -> _Fitted | None:
    """The OpenCV part of :func:`pose.solve` for one marker; None where it finds no pose in front."""
    obj = object_corners(size_m)
    img = np.ascontiguousarray(corners, dtype=np.float64).reshape(-1, 1, 2)
    ok, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not ok or len(rvecs) == 0:
        return None
    e = np.asarray(errs, dtype=float).ravel()
    r0, t0 = np.asarray(rvecs[0], float).ravel(), np.asarray(tvecs[0], float).ravel()
    if t0[2] <= 0:
        return None
    alt = (np.asarray(tvecs[1], float).ravel(), quat_from_rotvec(np.ravel(rvecs[1]))) if len(rvecs) > 1 else None
    ambiguity = float(e[0] / e[1]) if len(e) > 1 and e[1] > 0 else float("nan")
    r0, t0 = cv2.solvePnPRefineLM(obj, img, K, None, r0.reshape(3, 1).copy(), t0.reshape(3, 1).copy())
    r0, t0 = r0.ravel(), t0.ravel()
    proj, J_proj = cv2.projectPoints(obj.reshape(-1, 1, 3), r0, t0, K, None)
    R0, dR = cv2.Rodrigues(r0.reshape(3, 1))
    c = img.reshape(4, 2).tolist()
    sides = [(c[(i + 1) % 4][0] - a, c[(i + 1) % 4][1] - b) for i, (a, b) in enumerate(c)]
    side_px = sum(math.sqrt(dx * dx + dy * dy) for dx, dy in sides) / 4  # the mean side's length
    return _Fitted(
        index, obj, img.reshape(4, 2), r0, t0, R0, dR, proj.reshape(4, 2), J_proj[:, :6], alt, ambiguity, side_px
    )


def _whiten(stretch: NDArray[np.float64], J: NDArray[np.float64]) -> NDArray[np.float64]:
    """Rows of each marker's J ((M, 8, k), undistorted pixels per unit) in image pixels: each corner's two
    rows by the inverse of its undistortion Jacobian ``stretch`` (M, 4, 2, 2)."""
    m, _, k = J.shape
    return np.linalg.solve(stretch, J.reshape(m, 4, 2, k)).reshape(m, 8, k)


def _jacobians(
    R: NDArray[np.float64], p: NDArray[np.float64], obj: NDArray[np.float64], K: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:meth:`CornerFit.jacobian` (M, 8, 6) and :meth:`CornerFit.projected_px` (M, 4, 2) of M poses ``R``
    (M, 3, 3), ``p`` (M, 3) of objects with corners ``obj`` (M, 4, 3)."""
    m = len(R)
    P = obj @ np.swapaxes(R, 1, 2) + p[:, None, :]
    z = P[..., 2]
    fx, fy = K[0, 0], K[1, 1]
    D = np.zeros((m, 4, 2, 3))
    D[..., 0, 0], D[..., 1, 1] = fx / z, fy / z
    D[..., 0, 2], D[..., 1, 2] = -fx * P[..., 0] / z**2, -fy * P[..., 1] / z**2
    hat = np.zeros((m, 4, 3, 3))
    hat[..., 0, 1], hat[..., 0, 2], hat[..., 1, 2] = -obj[..., 2], obj[..., 1], -obj[..., 0]
    hat[..., 1, 0], hat[..., 2, 0], hat[..., 2, 1] = obj[..., 2], -obj[..., 1], obj[..., 0]
    dP = np.zeros((m, 4, 3, 6))
    dP[..., :3] = np.eye(3)
    dP[..., 3:] = -R[:, None] @ hat
    projected = (P @ K.T)[..., :2] / P[..., 2:]
    return (D @ dP).reshape(m, 8, 6), projected


def solve_markers(
    corners: Sequence[NDArray[np.float64]],
    sizes_m: Sequence[float],
    K: NDArray[np.float64],
    sigma_px: Sequence[float],
    stretches: Sequence[NDArray[np.float64] | None],
    measured_sigma_px: Sequence[float],
    corner_covs: Sequence[NDArray[np.float64] | None],
) -> list[MarkerPose | None]:
    """:func:`pose.solve` of each marker (its arguments one per marker), the algebra of all at once."""
    out: list[MarkerPose | None] = [None] * len(corners)
    fits = [f for i in range(len(corners)) if (f := _fit(i, corners[i], sizes_m[i], K)) is not None]
    if not fits:
        return out
    m = len(fits)
    given = [stretches[f.index] for f in fits]
    S = np.array([_UNSTRETCHED if s is None else s for s in given])  # solving with the identity changes nothing
    img = np.array([f.img for f in fits])
    residual = _whiten(S, (np.array([f.proj for f in fits]) - img).reshape(m, 8, 1))
    err = np.sqrt(np.sum(residual**2, axis=(1, 2)) / 4)
    side = np.array([f.side_px for f in fits])
    has_stretch = np.array([s is not None for s in given])
    if has_stretch.any():  # the side in image pixels: undistorted lengths shrunk by the local scale
        scale = np.sqrt(np.mean(np.abs(np.linalg.det(S[has_stretch])), axis=1))
        side[has_stretch] /= scale
    # The edge fit's measured corner noise, or the model's.
    noise = np.array(
        [
            measured_sigma_px[f.index] if measured_sigma_px[f.index] > 0 else corner_noise_px(sigma_px[f.index], s)
            for f, s in zip(fits, side, strict=True)
        ]
    )
    sigma = _position_sigmas(fits, S, noise, err)
    # Face-on, the first order says nothing about tilt; second order bounds it.
    t0 = np.array([f.t0 for f in fits])
    z = np.sqrt(np.sum(t0 * t0, axis=1))
    cap = z * np.sqrt((noise / side) ** 2 + 2.0 * noise / side)
    fit_scale = np.sqrt(1.0 + (err / noise) ** 2)
    sigma = np.maximum(np.minimum(sigma, cap * fit_scale), MIN_SIGMA_M)
    R0 = np.array([f.R0 for f in fits])
    obj = np.array([f.obj for f in fits])
    J, projected = _jacobians(R0, t0, obj, K)
    covs = _fitted_covariances(J, projected, img, [corner_covs[f.index] for f in fits])
    for k, f in enumerate(fits):
        if covs[k] is None:
            covs[k] = pose_covariance(CornerFit(f.R0, f.t0, f.obj, K), float(noise[k]), float(err[k]), given[k])
    _add_flip_moments(fits, covs, S, R0, t0, obj, img, noise, err, K)
    for k, f in enumerate(fits):
        p_alt, q_alt = f.alt if f.alt is not None else (None, None)
        out[f.index] = MarkerPose(
            f.t0, quat_from_rotvec(f.r0), float(err[k]), p_alt, q_alt, f.ambiguity, float(sigma[k]), covs[k]
        )
    return out


def _position_sigmas(
    fits: list[_Fitted], S: NDArray[np.float64], noise: NDArray[np.float64], err: NDArray[np.float64]
) -> NDArray[np.float64]:
    """:func:`pose.camera_position_sigma` of each marker (M,), from its projection's Jacobian."""
    Jw = _whiten(S, np.array([f.J_proj for f in fits]))  # d(image pixels) / d(rvec, tvec)
    A = np.swapaxes(Jw, 1, 2) @ Jw
    try:
        Ainv = np.linalg.inv(A)
        singular = np.zeros(len(fits), bool)
    except np.linalg.LinAlgError:  # one by one: the singular ones' sigma is infinite
        Ainv, singular = np.zeros_like(A), np.ones(len(fits), bool)
        for k in range(len(fits)):
            try:
                Ainv[k], singular[k] = np.linalg.inv(A[k]), False
            except np.linalg.LinAlgError:
                pass
    cov = noise[:, None, None] ** 2 * Ainv
    # The camera's position c = -R^T t: dc/dt = -R^T, dc/dr_i = -(dR/dr_i)^T t (Rodrigues' Jacobian).
    t = np.array([f.t0 for f in fits])
    dR = np.array([f.dR for f in fits]).reshape(-1, 3, 3, 3)  # [marker, i]: dR/dr_i
    Jc = np.empty((len(fits), 3, 6))
    Jc[:, :, :3] = -np.swapaxes((np.swapaxes(dR, 2, 3) @ t[:, None, :, None])[..., 0], 1, 2)
    Jc[:, :, 3:] = -np.swapaxes(np.array([f.R0 for f in fits]), 1, 2)
    var = np.linalg.eigvalsh(Jc @ cov @ np.swapaxes(Jc, 1, 2)).max(axis=1)
    fit = np.where(np.isfinite(err), np.sqrt(1.0 + (err / noise) ** 2), 2.0)
    return np.where(singular, math.inf, np.sqrt(np.maximum(var, 0.0)) * fit)


def _fitted_covariances(
    J: NDArray[np.float64],
    projected: NDArray[np.float64],
    img: NDArray[np.float64],
    corner_covs: list[NDArray[np.float64] | None],
) -> list[NDArray[np.float64] | None]:
    """:func:`pose.fitted_covariance` of each marker with its corners' covariance (None for the others, or
    where it is singular): ``J`` (M, 8, 6) and ``projected`` (M, 4, 2) of each pose, ``img`` (M, 4, 2)."""
    out: list[NDArray[np.float64] | None] = [None] * len(J)
    given = [k for k, c in enumerate(corner_covs) if c is not None]
    if not given:
        return out
    try:
        _fitted_into(out, given, J, projected, img, corner_covs)
    except np.linalg.LinAlgError:  # one by one, as alone: a singular one gets none
        for k in given:
            try:
                _fitted_into(out, [k], J, projected, img, corner_covs)
            except np.linalg.LinAlgError:
                out[k] = None
    return out


def _fitted_into(
    out: list[NDArray[np.float64] | None],
    given: list[int],
    J: NDArray[np.float64],
    projected: NDArray[np.float64],
    img: NDArray[np.float64],
    corner_covs: list[NDArray[np.float64] | None],
) -> None:
    """:func:`_fitted_covariances` of the markers ``given``, stacked, into ``out``; raises
    ``np.linalg.LinAlgError`` when a corner covariance is singular."""
    W = np.array([corner_covs[k] for k in given])
    Jg = J[given]
    r = (projected[given] - img[given]).reshape(len(given), 8)
    X = np.linalg.solve(W, np.concatenate([Jg, r[..., None]], axis=2))  # corner_cov^-1 [J, r] at once
    A = np.swapaxes(Jg, 1, 2) @ X[..., :6]
    finite = np.isfinite(A).all(axis=(1, 2))
    cond = np.full(len(given), np.inf)
    if finite.any():
        cond[finite] = np.linalg.cond(A[finite])
    usable = finite & (cond <= 1e14)
    if not usable.any():
        return
    C = np.linalg.inv(A[usable])
    C = (C + np.swapaxes(C, 1, 2)) / 2.0
    chi2 = np.einsum("mi,mi->m", r[usable], X[usable, :, 6])
    C *= np.maximum(1.0, chi2 / 2.0)[:, None, None]  # over 8 residuals less the pose's 6 parameters
    for k, c in zip(np.array(given)[usable], C, strict=True):
        out[int(k)] = c


def _add_flip_moments(
    fits: list[_Fitted],
    covs: list[NDArray[np.float64] | None],
    S: NDArray[np.float64],
    R0: NDArray[np.float64],
    t0: NDArray[np.float64],
    obj: NDArray[np.float64],
    img: NDArray[np.float64],
    noise: NDArray[np.float64],
    err: NDArray[np.float64],
    K: NDArray[np.float64],
) -> None:
    """Each covariance plus the second moment the other planar solution adds (:func:`pose.solve`'s
    flip moment), where there is one and the chosen solution is not ambiguous."""
    sel = [
        k
        for k, f in enumerate(fits)
        if covs[k] is not None and f.alt is not None and f.ambiguity <= AMBIGUITY_THRESHOLD
    ]
    if not sel:
        return
    t1 = np.array([fits[k].alt[0] for k in sel])  # type: ignore[index]
    R1 = Rotation.from_quat(np.array([fits[k].alt[1] for k in sel])).as_matrix()  # type: ignore[index]
    P = obj[sel] @ np.swapaxes(R1, 1, 2) + t1[:, None, :]
    projected = (P @ K.T)[..., :2] / P[..., 2:]
    res = _whiten(S[sel], (projected - img[sel]).reshape(len(sel), 8, 1))
    dchi2 = (np.sum(res**2, axis=(1, 2)) - 4.0 * err[sel] ** 2) / noise[sel] ** 2
    w = 1.0 / (1.0 + np.exp(np.minimum(np.maximum(dchi2, 0.0) / 2.0, 700.0)))
    d = np.concatenate([t1 - t0[sel], rotvecs_from_matrices(np.swapaxes(R0[sel], 1, 2) @ R1)], axis=1)
    moments = w[:, None, None] * (d[:, :, None] * d[:, None, :])
    for j, k in enumerate(sel):
        covs[k] = covs[k] + moments[j]  # type: ignore[operator]
