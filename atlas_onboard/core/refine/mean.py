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


def view_labels(items: Sequence[Evidence], inlier: NDArray[np.bool_], gap_s: float) -> NDArray[np.int_]:
    """(n,) the independent view of each inlier (0, 1, ...; -1 for outliers): per camera, a view starts with
    the first image at least ``gap_s`` after the last view's start and holds the images until the next."""
    labels = np.full(len(items), -1, dtype=int)
    last: dict[Hashable, tuple[int, int]] = {}  # camera -> (its current view's start us, its label)
    n = 0
    gap_us = gap_s * 1e6
    for k in sorted(range(len(items)), key=lambda k: items[k].capture_time_us):
        if not inlier[k]:
            continue
        e = items[k]
        cur = last.get(e.camera)
        if cur is None or e.capture_time_us - cur[0] >= gap_us:
            cur = last[e.camera] = (e.capture_time_us, n)
            n += 1
        labels[k] = cur[1]
    return labels


def independent_views(items: Sequence[Evidence], inlier: NDArray[np.bool_], gap_s: float) -> int:
    """Independent views among the inliers: per camera, images at least ``gap_s`` after the last counted."""
    return int(view_labels(items, inlier, gap_s).max(initial=-1)) + 1


def view_scatter(r: NDArray, W: NDArray, labels: NDArray[np.int_]) -> tuple[NDArray[np.float64], float, int] | None:
    """The views' scatter about each other: residuals ``r`` (n, 6) about the mean, information ``W`` (n, 6, 6),
    each item's view ``labels`` (n,; -1 left out).

    Images of one view share their errors (the same placing markers at about the same geometry), so a view
    is worth one average image of it, not its count: its nominal information is its items' summed over their
    number. Returns the covariance of the views' combined mean under that nominal model (6, 6), the views'
    chi-square about their combined mean (if the nominal model is right up to a factor k, k times a
    chi-square variable) and its degrees of freedom (6 per view beyond the first); None when an information
    matrix is singular."""
    views = int(labels.max(initial=-1)) + 1
    info = np.zeros((views, 6, 6))
    x = np.zeros((views, 6))
    try:
        for j in range(views):
            sel = labels == j
            I_j = W[sel].sum(axis=0)
            x[j] = np.linalg.solve(I_j, np.einsum("nij,nj->i", W[sel], r[sel]))
            info[j] = I_j / sel.sum()
        cov = np.linalg.inv(info.sum(axis=0))
    except np.linalg.LinAlgError:
        return None
    mean = cov @ np.einsum("vij,vj->i", info, x)
    d = x - mean
    chi2 = float(np.einsum("vi,vij,vj->", d, info, d))
    return 0.5 * (cov + cov.T), chi2, 6 * (views - 1)
