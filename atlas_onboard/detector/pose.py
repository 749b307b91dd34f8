"""Marker pose from corners: undistort, IPPE (both planar solutions), ambiguity ratio, and sigma.

Sigma is the standard deviation (metres) of what the graph actually uses from an observation: where
the camera is relative to the marker (eq. 1 inverts the marker's pose, so an error in the marker's
orientation swings the camera around it by range x angle). It comes from first-order propagation of
corner noise: the Jacobian J of the corners' projection with respect to the pose gives the pose
covariance sigma_px^2 (J^T J)^-1, and the camera position -R^T t its covariance; sigma is the square
root of the largest eigenvalue. A single marker seen face-on is the degenerate case: its tilt is then
determined only to second order, so sigma is capped at range x sqrt(2 sigma_px / side_px), what
second order gives. A poor fit (reprojection error above the corner noise) inflates sigma by
sqrt(1 + (e / sigma_px)^2). The corner noise sigma_px shrinks with the square root of the marker's
side in pixels (a corner is where two fitted edge lines cross): 0.08 px at a 50 px side for the
AprilTag library, 0.2 px for OpenCV's ArUco corners. The model is checked against truth on rendered
markers from 0.5 to 5 m and 0 to 60 degrees (tests/detector/test_sigma.py).

Sigma is the paper's scalar, and the weight of its fusion. Beside it the detector reports the whole
first-order covariance of the marker's pose in the camera frame (:func:`pose_covariance`), which a
scalar cannot carry: a marker seen from afar is placed within a fraction of a millimetre across the
line of sight, a few millimetres in depth, and poorly in tilt, and its tilt and the camera's position
seen from it are correlated, so a ceiling camera's view of a drone's tag is far more precise than
the camera's position relative to that tag. The listener carries it through eq. 1.

Honest at the image edge and on hard frames: corner noise is isotropic in the image, so with lens
distortion it is carried through the undistortion's Jacobian (:func:`undistortion_jacobian`); when the
detector refits the corners on the edges it measures their noise and passes it in (``measured_sigma_px``,
used instead of the model); and a single square's covariance adds the second moment of the other IPPE
solution, weighted by how well it fits (:func:`_flip_moment`), which the first order alone ignores.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.detector.families import family
from atlas_onboard.detector.rotations import matrix_from_quat, quat_from_rotvec, rotvec_from_matrix

SIGMA_PX_APRILTAG = 0.08  # corner noise at a 50 px side, scaled by sqrt(50 / side): corner_noise_px
SIGMA_PX_ARUCO = 0.2
MIN_SIGMA_M = 0.0001


@dataclass(frozen=True)
class MarkerPose:
    """The chosen (lowest reprojection error) solution and, for a single square, the other IPPE one."""

    p_m: NDArray[np.float64]
    q_xyzw: NDArray[np.float64]
    reprojection_error_px: float
    p_alt_m: NDArray[np.float64] | None
    q_alt_xyzw: NDArray[np.float64] | None
    ambiguity: float  # error of the chosen over the other solution (1: indistinguishable)
    sigma_m: float
    covariance: NDArray[np.float64] | None = None  # of the chosen solution: see pose_covariance


def model_sigma_px(family_name: str) -> float:
    """The corner noise model's ``sigma_px`` (at a 50 px side: :func:`corner_noise_px`) of a marker family."""
    return SIGMA_PX_APRILTAG if family(family_name).is_apriltag else SIGMA_PX_ARUCO


def object_corners(size_m: float) -> NDArray[np.float64]:
    """OpenCV's marker corners (x right, y up, z out; TL, TR, BR, BL) for a side of ``size_m``."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


# cv2.undistortPoints stops after 5 iterations by default: with strong barrel distortion (k1 = -0.3 at
# 640x480) that leaves corners near the image edge off by 0.1-0.5 px, many times the corner noise.
UNDISTORT_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
JACOBIAN_STEP_PX = 0.5


def undistort(
    corners_px: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> NDArray[np.float64]:
    """Corners (N, 2) moved to where an ideal pinhole camera with the same K would see them."""
    pts = np.ascontiguousarray(corners_px, dtype=np.float64).reshape(-1, 1, 2)
    if fisheye:
        out = cv2.fisheye.undistortPoints(pts, K, dist, P=K, criteria=UNDISTORT_CRITERIA)
    elif np.any(dist):
        out = cv2.undistortPoints(pts, K, dist, None, None, K, criteria=UNDISTORT_CRITERIA)
    else:
        return pts.reshape(-1, 2)
    return out.reshape(-1, 2)


def undistortion_jacobian(
    corners_px: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> NDArray[np.float64] | None:
    """d(undistorted pixel) / d(image pixel) at each corner, (N, 2, 2); None without distortion.

    Corner noise is isotropic in the image, not in undistorted pixels: barrel distortion compresses the
    image's edge, so undistortion stretches a corner's noise there (radially more than tangentially).
    Central differences of :func:`undistort`.
    """
    if not np.any(dist):
        return None
    c = np.asarray(corners_px, dtype=np.float64).reshape(-1, 2)
    h = JACOBIAN_STEP_PX
    steps = np.array([[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
    moved = undistort((c[:, None, :] + steps[None]).reshape(-1, 2), K, dist, fisheye).reshape(-1, 4, 2)
    A = np.empty((len(c), 2, 2))
    A[:, :, 0] = (moved[:, 0] - moved[:, 1]) / (2 * h)
    A[:, :, 1] = (moved[:, 2] - moved[:, 3]) / (2 * h)
    return A


def _whiten(J: NDArray[np.float64], stretch: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """Rows of J ((2N, k), undistorted pixels per unit) scaled to image pixels: each corner's two rows by
    the inverse of its undistortion Jacobian, so that corner noise is isotropic again."""
    if stretch is None:
        return J
    Jc = J.reshape(len(stretch), 2, -1)
    return np.linalg.solve(stretch, Jc).reshape(J.shape)


def camera_position_sigma(
    rvec: NDArray[np.float64],
    tvec: NDArray[np.float64],
    obj: NDArray[np.float64],
    K: NDArray[np.float64],
    sigma_px: float,
    err_px: float,
    stretch: NDArray[np.float64] | None = None,
) -> float:
    """First-order standard deviation of the camera's position in the object's frame (metres).
    ``stretch``: :func:`undistortion_jacobian` of the corners (None: no distortion)."""
    _, J = cv2.projectPoints(obj.reshape(-1, 1, 3), rvec, tvec, K, None)
    return _position_sigma(J, rvec, tvec, sigma_px, err_px, stretch)


def _position_sigma(
    J: NDArray[np.float64],
    rvec: NDArray[np.float64],
    tvec: NDArray[np.float64],
    sigma_px: float,
    err_px: float,
    stretch: NDArray[np.float64] | None,
) -> float:
    """:func:`camera_position_sigma` from ``cv2.projectPoints``' Jacobian ``J`` of the corners at the pose."""
    J = _whiten(J[:, :6], stretch)  # d(image pixels) / d(rvec, tvec)
    try:
        cov = sigma_px**2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return math.inf
    # The camera's position c = -R^T t: dc/dt = -R^T, dc/dr_i = -(dR/dr_i)^T t (Rodrigues' Jacobian).
    R, dR = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))
    t = np.asarray(tvec, dtype=np.float64).ravel()
    Jc = np.empty((3, 6))
    Jc[:, :3] = -(np.swapaxes(dR.reshape(3, 3, 3), 1, 2) @ t).T  # column i: -(dR/dr_i)^T t
    Jc[:, 3:] = -R.T
    var = float(np.linalg.eigvalsh(Jc @ cov @ Jc.T).max())
    fit = math.sqrt(1.0 + (err_px / sigma_px) ** 2) if math.isfinite(err_px) else 2.0
    return math.sqrt(max(var, 0.0)) * fit


@dataclass(frozen=True)
class CornerFit:
    """A pose ``T_s_m = (p_sm, R_sm)`` of an object (a square, or the squares of an entity) in an undistorted
    pinhole camera ``K`` (3, 3), with the object's corners ``obj_m`` ((N, 3), object frame): what the
    covariances of this module are computed about, made once where the pose is fitted."""

    R_sm: NDArray[np.float64]
    p_sm: NDArray[np.float64]
    obj_m: NDArray[np.float64]
    K: NDArray[np.float64]

    def jacobian(self) -> NDArray[np.float64]:
        """(2N, 6): the corners' undistorted pixels with respect to the pose error ``[dp, dtheta]``."""
        X = np.asarray(self.obj_m, dtype=float).reshape(-1, 3)
        P = X @ self.R_sm.T + self.p_sm
        z = P[:, 2]
        fx, fy = self.K[0, 0], self.K[1, 1]
        # d(pixel)/dP, (N, 2, 3): [[fx / z, 0, -fx x / z^2], [0, fy / z, -fy y / z^2]]
        D = np.zeros((len(X), 2, 3))
        D[:, 0, 0], D[:, 1, 1] = fx / z, fy / z
        D[:, 0, 2], D[:, 1, 2] = -fx * P[:, 0] / z**2, -fy * P[:, 1] / z**2
        # dP/d[dp, dtheta], (N, 3, 6): [I, -R [X]x]; R [X]x dtheta = R (X x dtheta) = -(R [dtheta]x X)
        dP = np.zeros((len(X), 3, 6))
        dP[:, :, :3] = np.eye(3)
        hat = np.zeros((len(X), 3, 3))
        hat[:, 0, 1], hat[:, 0, 2], hat[:, 1, 2] = -X[:, 2], X[:, 1], -X[:, 0]
        hat[:, 1, 0], hat[:, 2, 0], hat[:, 2, 1] = X[:, 2], -X[:, 1], X[:, 0]
        dP[:, :, 3:] = -self.R_sm @ hat
        return (D @ dP).reshape(-1, 6)

    def projected_px(self) -> NDArray[np.float64]:
        """(N, 2): where the pose puts the corners, in undistorted pixels."""
        P = np.asarray(self.obj_m, dtype=float).reshape(-1, 3) @ self.R_sm.T + self.p_sm
        return (P @ self.K.T)[:, :2] / P[:, 2:]

    @property
    def n_corners(self) -> int:
        return len(np.asarray(self.obj_m).reshape(-1, 3))


def pose_covariance(
    fit: CornerFit, sigma_px: float, err_px: float, stretch: NDArray[np.float64] | None = None
) -> NDArray[np.float64] | None:
    """First-order 6x6 covariance of the pose of ``fit`` found from its corners with independent corner
    noise ``sigma_px``: ``sigma_px^2 (J^T J)^-1``, with J the corners' pixels with respect to
    atlas-onboard's error vector ``[dp, dtheta]`` (dp in the camera frame, dtheta about the object's
    own axes: :mod:`atlas_onboard.core.covariance`). A corner X moves by ``dp - R [X]x dtheta``, and
    its pixel by the pinhole's derivative. A poor fit (RMS error ``err_px``) inflates it as sigma is
    inflated (``1 + (err / sigma_px)^2``). ``stretch``: :func:`undistortion_jacobian` of the corners, whose
    noise is ``sigma_px`` in the distorted image (None: no distortion). None if J is singular (fewer
    than three distinct corners)."""
    J = _whiten(fit.jacobian(), stretch)
    A = J.T @ J
    if fit.n_corners < 3 or np.linalg.cond(A) > 1e14:
        return None
    fit_scale = 1.0 + (err_px / sigma_px) ** 2 if math.isfinite(err_px) else 4.0
    C = sigma_px**2 * fit_scale * np.linalg.inv(A)
    return (C + C.T) / 2.0


def pose_covariance_from_corners(fit: CornerFit, corner_cov: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The 6x6 covariance of :func:`pose_covariance` from the corners' own (2N, 2N) covariance in
    undistorted pixels (x0 y0 x1 y1 ..., correlated: :class:`refine.RefinedCorners`), by generalised
    least squares: ``(J^T corner_cov^-1 J)^-1``. None if it is singular."""
    J = fit.jacobian()
    try:
        A = J.T @ np.linalg.solve(corner_cov, J)
    except np.linalg.LinAlgError:
        return None
    if fit.n_corners < 3 or not np.all(np.isfinite(A)) or np.linalg.cond(A) > 1e14:
        return None
    C = np.linalg.inv(A)
    return (C + C.T) / 2.0


def fitted_covariance(
    fit: CornerFit, img_px: NDArray[np.float64], corner_cov: NDArray[np.float64]
) -> NDArray[np.float64] | None:
    """:func:`pose_covariance_from_corners` of the pose of ``fit`` fitted to the undistorted corners
    ``img_px`` (N, 2), scaled by how well it fits them: a fit worse than the corners' covariance
    explains (its chi-square over the 2N - 6 degrees of freedom the pose leaves) scales the covariance
    by that ratio, as least squares with an unknown noise scale does; a better one changes nothing."""
    J = fit.jacobian()
    r = (fit.projected_px() - np.asarray(img_px, dtype=float).reshape(-1, 2)).ravel()
    try:  # corner_cov^-1 [J, r] at once (pose_covariance_from_corners' and the chi-square's solves)
        S = np.linalg.solve(corner_cov, np.column_stack([J, r]))
    except np.linalg.LinAlgError:
        return None
    A = J.T @ S[:, :6]
    if fit.n_corners < 3 or not np.all(np.isfinite(A)) or np.linalg.cond(A) > 1e14:
        return None
    C = np.linalg.inv(A)
    C = (C + C.T) / 2.0
    dof = max(len(r) - 6, 1)
    chi2 = float(r @ S[:, 6])
    return C * max(1.0, chi2 / dof)


def corner_noise_px(base_px: float, side_px: float) -> float:
    """Corner noise of a marker whose side spans ``side_px``: a corner is the crossing of two lines
    fitted along the edges, so its error shrinks with the square root of the edge length
    (``base_px`` at a 50 px side)."""
    return float(np.clip(base_px * math.sqrt(50.0 / max(side_px, 1.0)), 0.02, 0.5))


def solve(
    corners_px: NDArray[np.float64],
    size_m: float,
    K: NDArray[np.float64],
    sigma_px: float,
    stretch: NDArray[np.float64] | None = None,
    measured_sigma_px: float = 0.0,
    corner_cov: NDArray[np.float64] | None = None,
) -> MarkerPose | None:
    """IPPE on undistorted corners of one square; None if OpenCV finds no solution in front.

    The corner noise is the ``measured_sigma_px`` of the corners' edge fit
    (:func:`refine.refine_corners_undistorted`, which includes what its scatter cannot show) when given,
    otherwise the model's (``sigma_px`` at a 50 px side, :func:`corner_noise_px`).

    ``stretch``: :func:`undistortion_jacobian` of the corners (None: an undistorted camera); the
    corner noise ``sigma_px``, the marker's side and the reprojection error are then in image pixels."""
    obj = object_corners(size_m)
    img = np.ascontiguousarray(corners_px, dtype=np.float64).reshape(-1, 1, 2)
    ok, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if not ok or len(rvecs) == 0:
        return None
    e = np.asarray(errs, dtype=float).ravel()
    r0, t0 = np.asarray(rvecs[0], float).ravel(), np.asarray(tvecs[0], float).ravel()
    if t0[2] <= 0:
        return None
    alt = (
        (np.asarray(tvecs[1], float).ravel(), quat_from_rotvec(np.ravel(rvecs[1]))) if len(rvecs) > 1 else (None, None)
    )
    ambiguity = float(e[0] / e[1]) if len(e) > 1 and e[1] > 0 else float("nan")
    # IPPE solves the homography in closed form, which is not the least-squares pose: a few
    # Levenberg-Marquardt steps from it reach the minimum of the reprojection error, whose spread
    # the first-order covariance describes (IPPE alone has more tilt variance:
    # tests/detector/test_pose.py).
    r0, t0 = cv2.solvePnPRefineLM(obj, img, K, None, r0.reshape(3, 1).copy(), t0.reshape(3, 1).copy())
    r0, t0 = r0.ravel(), t0.ravel()
    proj, J_proj = cv2.projectPoints(obj.reshape(-1, 1, 3), r0, t0, K, None)
    residual = _whiten((proj.reshape(-1, 2) - img.reshape(-1, 2)).reshape(-1, 1), stretch)
    e[0] = float(np.sqrt(np.sum(residual**2) / 4))
    c = img.reshape(4, 2).tolist()
    side_px = (
        sum(math.sqrt((c[(i + 1) % 4][0] - a) ** 2 + (c[(i + 1) % 4][1] - b) ** 2) for i, (a, b) in enumerate(c)) / 4
    )
    if stretch is not None:  # the side in image pixels: undistorted lengths shrunk by the local scale
        side_px /= float(np.sqrt(np.mean(np.abs(np.linalg.det(stretch)))))
    # The edge fit's measured corner noise, or the model's.
    if measured_sigma_px > 0:
        sigma_px = measured_sigma_px
    else:
        sigma_px = corner_noise_px(sigma_px, side_px)
    sigma = _position_sigma(J_proj, r0, t0, sigma_px, float(e[0]), stretch)  # camera_position_sigma's
    # Face-on, the first order says nothing about tilt; second order bounds it.
    z = float(np.linalg.norm(t0))
    cap = z * math.sqrt((sigma_px / side_px) ** 2 + 2.0 * sigma_px / side_px)
    fit = math.sqrt(1.0 + (e[0] / sigma_px) ** 2)
    sigma = max(min(sigma, cap * fit), MIN_SIGMA_M)
    fitted = CornerFit(cv2.Rodrigues(r0)[0], t0, obj, K)
    cov = None
    if corner_cov is not None:
        cov = fitted_covariance(fitted, img.reshape(-1, 2), corner_cov)
    if cov is None:
        cov = pose_covariance(fitted, sigma_px, float(e[0]), stretch)
    if cov is not None and alt[0] is not None and ambiguity <= AMBIGUITY_THRESHOLD:
        other = CornerFit(matrix_from_quat(alt[1]), alt[0], obj, K)
        cov = cov + _flip_moment(fitted, other, img, sigma_px, float(e[0]), stretch)
    return MarkerPose(t0, quat_from_rotvec(r0), float(e[0]), alt[0], alt[1], ambiguity, sigma, cov)


def _flip_moment(
    chosen: CornerFit,
    other: CornerFit,
    img: NDArray[np.float64],
    sigma_px: float,
    err_px: float,
    stretch: NDArray[np.float64] | None,
) -> NDArray[np.float64]:
    """The second moment, about the ``chosen`` solution, that the ``other`` planar solution adds: w d d^T.

    A small or near face-on square has two poses that fit its corners ``img`` almost equally (IPPE's pair,
    mirrored in tilt). The first-order covariance describes the neighbourhood of the chosen one only;
    with the corner noise, the other is the truth with the posterior weight
    w = 1 / (1 + exp((chi2_alt - chi2_chosen) / 2)), chi2 = sum of squared residuals / sigma_px^2, and
    d its offset in the error convention [dp, dtheta] of :func:`pose_covariance`.
    """
    res = _whiten((other.projected_px() - img.reshape(-1, 2)).reshape(-1, 1), stretch)
    dchi2 = (float(np.sum(res**2)) - 4.0 * err_px**2) / sigma_px**2
    w = 1.0 / (1.0 + math.exp(min(max(dchi2, 0.0) / 2.0, 700.0)))
    d = np.concatenate([other.p_sm - chosen.p_sm, rotvec_from_matrix(chosen.R_sm.T @ other.R_sm)])
    return w * np.outer(d, d)


def solve_joint(
    obj_entity: NDArray[np.float64],
    img: NDArray[np.float64],
    K: NDArray[np.float64],
    sigma_px: float,
    guess: tuple[NDArray[np.float64], NDArray[np.float64]],
) -> tuple[NDArray[np.float64], NDArray[np.float64], float, float] | None:
    """Pose of an entity from the corners of several of its markers at once.

    ``obj_entity``: (N, 3) corners in the entity frame; ``img``: (N, 2) undistorted pixels; ``guess``:
    rvec, tvec to start from (the best single-marker solution). Returns rvec, tvec, RMS error, sigma
    (the covariance, of whichever frame the caller reports, is :func:`pose_covariance`'s).
    """
    ok, rvec, tvec = cv2.solvePnP(
        obj_entity.reshape(-1, 1, 3), img.reshape(-1, 1, 2), K, None, guess[0].copy(), guess[1].copy(),
        useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE,
    )  # fmt: skip
    if not ok:
        return None
    rvec, tvec = rvec.ravel(), tvec.ravel()
    proj, _ = cv2.projectPoints(obj_entity.reshape(-1, 1, 3), rvec, tvec, K, None)
    err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    sigma = max(camera_position_sigma(rvec, tvec, obj_entity, K, sigma_px, err), MIN_SIGMA_M)
    return rvec, tvec, err, sigma
