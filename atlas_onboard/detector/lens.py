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
    (N, 2). A camera matrix without skew and the standard model (up to k3) take each point through the lens
    in plain arithmetic on whole arrays, in place (the same value to an ulp or two of its rays, which
    :func:`distort_homogeneous` finds by a matrix product); any other lens goes through that."""
    k = np.asarray(dist, dtype=np.float64).ravel()
    if fisheye or K[0, 1] != 0 or K[2].tolist() != [0.0, 0.0, 1.0] or len(k) not in (4, 5, 8) or any(k[5:]):
        return distort_homogeneous(np.column_stack([u, v, np.ones_like(u)]), K, dist, fisheye)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    k1, k2, p1, p2 = (float(c) for c in k[:4])
    k3 = float(k[4]) if len(k) > 4 else 0.0
    x = (u - cx) / fx  # in place below: each array once
    y = (v - cy) / fy
    r2 = x * x
    r2 += y * y
    radial = r2 * k3 if k3 != 0 else None
    if radial is not None:
        radial += k2
        radial *= r2
    else:
        radial = r2 * k2
    radial += k1
    radial *= r2
    radial += 1.0  # 1 + k1 r2 + k2 r4 + k3 r6
    out = np.empty((len(u), 2))
    xd, yd = x * radial, y * radial
    if p1 != 0 or p2 != 0:
        a1 = 2.0 * x * y
        xd += p1 * a1 + p2 * (r2 + 2.0 * x * x)
        yd += p1 * (r2 + 2.0 * y * y) + p2 * a1
    np.multiply(xd, fx, out=out[..., 0])
    out[..., 0] += cx
    np.multiply(yd, fy, out=out[..., 1])
    out[..., 1] += cy
    return out


def _project(
    rays: NDArray[np.float64], K: NDArray[np.float64], k: NDArray[np.float64], unit_z: bool = False
) -> NDArray[np.float64]:
    """Camera-frame points (N, 3) -> image pixels (N, 2) through OpenCV's standard lens model (radial,
    tangential, rational and thin-prism terms; 4 to 12 coefficients ``k``): cv2.projectPoints' value,
    evaluated in its order of operations (bit for bit) without the Jacobians it also computes."""
    k = k.tolist() + [0.0] * (12 - len(k))
    x, y, z = rays[:, 0], rays[:, 1], rays[:, 2]
    if not unit_z:
        z = np.where(z != 0, 1.0 / np.where(z != 0, z, 1.0), 1.0)
        x, y = x * z, y * z
    r2 = x * x + y * y
    r4 = r2 * r2
    # A group of terms whose coefficients are all zero is left out: adding its zeros (or dividing by its 1)
    # changes nothing but the sign of a zero.
    cdist = 1 + k[0] * r2 + k[1] * r4
    if k[4] != 0:
        cdist = cdist + k[4] * (r4 * r2)
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
    out = np.empty((len(rays), 2))
    out[:, 0], out[:, 1] = xd * K[0, 0] + K[0, 2], yd * K[1, 1] + K[1, 2]
    return out
