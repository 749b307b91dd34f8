"""Undistorted pixels (an ideal pinhole with the camera's K) into the distorted image, for many points at
once: the corner refit samples ~1,200 points per marker through the lens. OpenCV's ``projectPoints``
computes Jacobians on every call and has no Jacobian-free form for the standard model, so that model is
evaluated here in OpenCV's own order of operations (bit for bit its value); the fisheye model goes
through ``cv2.fisheye.distortPoints``, and a tilted sensor through OpenCV itself."""

from __future__ import annotations

import functools

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.detector.pose import undistort


@functools.lru_cache(maxsize=8)
def _inverse(K_bytes: bytes) -> NDArray[np.float64]:
    """np.linalg.inv of a camera matrix (its 9 float64 bytes): a camera's is computed once."""
    out = np.linalg.inv(np.frombuffer(K_bytes, dtype=np.float64).reshape(3, 3))
    out.flags.writeable = False
    return out


def distort(
    pts_und: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> NDArray[np.float64]:
    """Undistorted pixels (N, 2) (an ideal pinhole with the same K) -> image pixels (N, 2)."""
    return distort_homogeneous(np.column_stack([pts_und, np.ones(len(pts_und))]), K, dist, fisheye)


def distort_homogeneous(
    hom: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> NDArray[np.float64]:
    """:func:`distort` of undistorted pixels given as (N, 3) rows (u, v, 1)."""
    Kinv = _inverse(np.ascontiguousarray(K, dtype=np.float64).tobytes())
    rays = hom @ Kinv.T  # normalized, z = 1
    k = np.asarray(dist, dtype=np.float64).ravel()
    if fisheye and len(k) == 4:  # OpenCV's own, which computes no Jacobians (unlike projectPoints)
        return cv2.fisheye.distortPoints((rays[:, :2] / rays[:, 2:]).reshape(-1, 1, 2), K, k).reshape(-1, 2)
    if fisheye or len(k) not in (4, 5, 8, 12, 14) or (len(k) == 14 and np.any(k[12:])):
        # A tilted sensor (or coefficients OpenCV refuses, with its own error): OpenCV itself.
        project = cv2.fisheye.projectPoints if fisheye else cv2.projectPoints
        return project(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, k)[0].reshape(-1, 2)
    # An inverse whose last row is exactly (0, 0, 1) gives every ray a z of exactly 1 (nothing to divide).
    return _project(rays, K, k, unit_z=Kinv[2].tolist() == [0.0, 0.0, 1.0])


def distort_uv(
    u: NDArray[np.float64], v: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> NDArray[np.float64]:
    """:func:`distort` of undistorted pixels given as their coordinates ``u``, ``v`` (N,): image pixels
    (N, 2), bit for bit :func:`distort_homogeneous`'s."""
    return np.column_stack(distort_columns(u, v, K, dist, fisheye))


def distort_columns(
    u: NDArray[np.float64], v: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`distort_uv`'s image pixels as two contiguous coordinate arrays x, y (N,) (what the corner
    refit crops and samples by, without the strided reads of an (N, 2) array). A camera matrix without
    skew maps a pixel to its ray in two operations a coordinate (the values of the matrix product, whose
    zero terms add nothing), so the rows (u, v, 1) and their product are not built."""
    Kinv = _inverse(np.ascontiguousarray(K, dtype=np.float64).tobytes())
    k = np.asarray(dist, dtype=np.float64).ravel()
    plain = Kinv[0, 1] == 0 and Kinv[1, 0] == 0 and Kinv[2].tolist() == [0.0, 0.0, 1.0]
    if fisheye or not plain or len(k) not in (4, 5, 8, 12, 14) or (len(k) == 14 and np.any(k[12:])):
        out = distort_homogeneous(np.column_stack([u, v, np.ones_like(u)]), K, dist, fisheye)
        return np.ascontiguousarray(out[:, 0]), np.ascontiguousarray(out[:, 1])
    x = u * Kinv[0, 0]
    x += Kinv[0, 2]
    y = v * Kinv[1, 1]
    y += Kinv[1, 2]
    return _project_columns(x, y, K, k.tolist())


def _project(
    rays: NDArray[np.float64], K: NDArray[np.float64], k: NDArray[np.float64], unit_z: bool = False
) -> NDArray[np.float64]:
    """Camera-frame points (N, 3) -> image pixels (N, 2) through OpenCV's standard lens model (radial,
    tangential, rational and thin-prism terms; 4 to 12 coefficients ``k``): cv2.projectPoints' value,
    evaluated in its order of operations (bit for bit) without the Jacobians it also computes."""
    x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
    if not unit_z:
        z = np.where(z != 0, 1.0 / np.where(z != 0, z, 1.0), 1.0)
        x, y = x * z, y * z
    return _project_xy(x, y, K, k)


def _project_xy(
    x: NDArray[np.float64], y: NDArray[np.float64], K: NDArray[np.float64], k: NDArray[np.float64]
) -> NDArray[np.float64]:
    """:func:`_project` of normalised coordinates ``x``, ``y`` (N,) (z = 1)."""
    return np.column_stack(_project_columns(x, y, K, k.tolist()))


def _project_columns(
    x: NDArray[np.float64], y: NDArray[np.float64], K: NDArray[np.float64], coefficients: list[float]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`_project_xy`'s image pixels as two arrays x, y (N,), its operations in OpenCV's order (in
    place where that gives the same value)."""
    k = coefficients + [0.0] * (12 - len(coefficients))
    r2 = x * x
    r2 += y * y
    r4 = r2 * r2
    # A group of terms whose coefficients are all zero is left out: adding its zeros (or dividing by its 1)
    # changes nothing but the sign of a zero.
    cdist = k[0] * r2
    cdist += 1  # 1 + k1 r2
    cdist += k[1] * r4
    if k[4] != 0:
        cdist += k[4] * (r4 * r2)
    xd, yd = x * cdist, y * cdist
    if any(k[5:8]):  # the rational terms' denominator
        r6 = r4 * r2
        icdist2 = 1.0 / (1 + k[5] * r2 + k[6] * r4 + k[7] * r6)
        xd, yd = xd * icdist2, yd * icdist2
    if any(k[2:4]):
        a1 = 2 * x * y
        xd = xd + k[2] * a1 + k[3] * (r2 + 2 * x * x)
        yd = yd + k[2] * (r2 + 2 * y * y) + k[3] * a1
    if any(k[8:12]):  # thin prism
        xd = xd + k[8] * r2 + k[9] * r4
        yd = yd + k[10] * r2 + k[11] * r4
    xd *= K[0, 0]
    xd += K[0, 2]
    yd *= K[1, 1]
    yd += K[1, 2]
    return xd, yd


def bend_px(
    corners_und: NDArray[np.float64], K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> float:
    """How far a side drawn straight between the corners in the distorted image strays, in undistorted
    pixels, from the straight side between them there (the largest over the four sides): the lens's
    bend over the marker, 0 without distortion."""
    if not np.any(dist):
        return 0.0
    img = distort(corners_und, K, dist, fisheye)
    t = np.linspace(0.0, 1.0, 9)[1:-1, None]
    worst = 0.0
    for i in range(4):
        a, b = img[i], img[(i + 1) % 4]
        straight = undistort(a + t * (b - a), K, dist, fisheye)
        ua, ub = corners_und[i], corners_und[(i + 1) % 4]
        d = (ub - ua) / max(float(np.linalg.norm(ub - ua)), 1e-9)
        worst = max(worst, float(np.abs((straight - ua) @ np.array([-d[1], d[0]])).max()))
    return worst
