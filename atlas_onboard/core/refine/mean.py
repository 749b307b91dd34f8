"""The robust mean of a marker's evidence: poses with covariances, outliers gated against their own scatter.

Conventions as in :mod:`atlas_onboard.core.covariance`: a pose's error is ``[dp, dtheta]``, ``dp`` in the
parent frame (m) and ``dtheta`` about the child's own axes (rad).
"""

from __future__ import annotations

from collections.abc import Hashable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.special import chdtri  # chi-square's inverse survival function (scipy.stats costs 0.6 s to import)

from atlas_onboard.core.refine.records import Evidence


def robust_mean(
    P: NDArray, Rs: NDArray, W: NDArray, outlier_p: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], float] | None:
    """The information-weighted mean of n poses (p (n, 3), R (n, 3, 3), information W (n, 6, 6)) with
    outliers gated: p (3,), R (3, 3), the inliers (n,) and the scatter factor (None: fewer than two inliers).

    A robust start (the median position, the rotation of the item nearest it), then the mean, iterated:
    an item is an outlier when its Mahalanobis distance, after scaling every item's covariance by the
    evidence's own scatter (the median distance over the chi-square median, at least 1), has a tail
    probability below ``outlier_p``."""
    med = np.median(P, axis=0)
    k0 = int(np.argmin(np.linalg.norm(P - med, axis=1)))
    p_ref, R_ref = med, Rs[k0]
    inlier = np.ones(len(P), dtype=bool)
    scale = 1.0
    gate = chdtri(6, outlier_p)
    for _ in range(5):
        r = residuals(P, Rs, p_ref, R_ref)  # (n, 6) about the reference
        x = np.linalg.solve(W[inlier].sum(axis=0), np.einsum("nij,nj->i", W[inlier], r[inlier]))
        p_ref, R_ref = p_ref + x[:3], R_ref @ Rotation.from_rotvec(x[3:]).as_matrix()
        r = residuals(P, Rs, p_ref, R_ref)
        d2 = np.einsum("ni,nij,nj->n", r, W, r)
        scale = max(1.0, float(np.median(d2[inlier])) / chdtri(6, 0.5))
        new = d2 / scale <= gate
        if new.sum() < 2:
            return None
        if np.array_equal(new, inlier):
            break
        inlier = new
    return p_ref, R_ref, inlier, scale


def residuals(P: NDArray, Rs: NDArray, p_ref: NDArray, R_ref: NDArray) -> NDArray[np.float64]:
    """(n, 6) errors ``[p - p_ref, Log(R_ref^T R)]`` of poses about a reference (dtheta in its axes)."""
    rot = Rotation.from_matrix(np.swapaxes(R_ref, -1, -2) @ Rs).as_rotvec()
    return np.concatenate([P - p_ref, rot], axis=1)


def independent_views(items: Sequence[Evidence], inlier: NDArray[np.bool_], gap_s: float) -> int:
    """Independent views among the inliers: per camera, images at least ``gap_s`` after the last counted."""
    last: dict[Hashable, int] = {}
    n = 0
    gap_us = gap_s * 1e6
    for e, ok in sorted(zip(items, inlier, strict=True), key=lambda t: t[0].capture_time_us):
        if not ok:
            continue
        t = last.get(e.camera)
        if t is None or e.capture_time_us - t >= gap_us:
            last[e.camera] = e.capture_time_us
            n += 1
    return n
