"""Marker pose from corners: undistort, IPPE (both planar solutions), ambiguity ratio, and sigma.

The sigma model (metres, the standard deviation of the marker's position in the camera frame):

    sigma = k * z^2 * sigma_px / (f * s) * (1 + (e_reproj / sigma_px)^2)^0.5 / max(cos(theta), 0.26)^0.5

where z is the range, f the focal length in pixels, s the marker side in metres, sigma_px the corner
noise (0.1 px for the AprilTag library on sharp images), e_reproj the RMS reprojection error of the
chosen solution and theta the viewing angle off the marker's normal. The first factor is the range
error of a square of s metres seen at z metres with corners that wobble by sigma_px; a poor fit or an
oblique view inflates it. ``k`` is calibrated in simulation against truth (tests/detector).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

SIGMA_PX = 0.1
SIGMA_K = 1.0
MIN_SIGMA_M = 0.0005


@dataclass(frozen=True)
class MarkerPose:
    """The chosen (lowest reprojection error) IPPE solution and the other one."""

    p_m: NDArray[np.float64]
    q_xyzw: NDArray[np.float64]
    reprojection_error_px: float
    p_alt_m: NDArray[np.float64] | None
    q_alt_xyzw: NDArray[np.float64] | None
    ambiguity: float  # error of the chosen over the other solution (1: indistinguishable)
    sigma_m: float


def object_corners(size_m: float) -> NDArray[np.float64]:
    """OpenCV's marker corners (x right, y up, z out; TL, TR, BR, BL) for a side of ``size_m``."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def undistort(
    corners_px: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> NDArray[np.float64]:
    """Corners moved to where an ideal pinhole camera with the same K would see them."""
    pts = np.ascontiguousarray(corners_px, dtype=np.float64).reshape(-1, 1, 2)
    if fisheye:
        out = cv2.fisheye.undistortPoints(pts, K, dist, P=K)
    elif np.any(dist):
        out = cv2.undistortPoints(pts, K, dist, P=K)
    else:
        return pts.reshape(-1, 2)
    return out.reshape(-1, 2)


def sigma_model(
    p_m: NDArray[np.float64], q_xyzw: NDArray[np.float64], size_m: float, f_px: float, err_px: float
) -> float:
    z = float(np.linalg.norm(p_m))
    normal = Rotation.from_quat(q_xyzw).apply([0.0, 0.0, 1.0])
    cos_theta = abs(float(normal @ (-p_m / max(z, 1e-9))))
    base = SIGMA_K * z * z * SIGMA_PX / (f_px * size_m)
    fit = math.sqrt(1.0 + (err_px / SIGMA_PX) ** 2) if math.isfinite(err_px) else 2.0
    return max(base * fit / math.sqrt(max(cos_theta, 0.26)), MIN_SIGMA_M)


def solve(corners_px: NDArray[np.float64], size_m: float, K: NDArray[np.float64]) -> MarkerPose | None:
    """IPPE on undistorted corners; None if OpenCV finds no solution."""
    obj = object_corners(size_m)
    ok, rvecs, tvecs, errs = cv2.solvePnPGeneric(
        obj,
        np.ascontiguousarray(corners_px, dtype=np.float64).reshape(-1, 1, 2),
        K,
        None,
        flags=cv2.SOLVEPNP_IPPE_SQUARE,
    )
    if not ok or len(rvecs) == 0:
        return None
    e = np.asarray(errs, dtype=float).ravel()
    sols = [
        (Rotation.from_rotvec(np.asarray(r).ravel()).as_quat(), np.asarray(t, dtype=float).ravel())
        for r, t in zip(rvecs, tvecs, strict=True)
    ]
    q0, p0 = sols[0]
    if p0[2] <= 0:
        return None
    alt = sols[1] if len(sols) > 1 else None
    ambiguity = float(e[0] / e[1]) if len(e) > 1 and e[1] > 0 else float("nan")
    sigma = sigma_model(p0, q0, size_m, float(K[0, 0] + K[1, 1]) / 2, float(e[0]))
    return MarkerPose(p0, q0, float(e[0]), alt[1] if alt else None, alt[0] if alt else None, ambiguity, sigma)
