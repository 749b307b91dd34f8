"""Where the other markers of one image place the camera, each marker left out of its own placement.

Conventions as in :mod:`atlas_onboard.core.covariance`: a pose's error is ``[dp, dtheta]``, ``dp`` in the
parent frame (m) and ``dtheta`` about the child's own axes (rad).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation


def leave_one_out(P: NDArray, Rs: NDArray, C: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
    """For each of n candidate poses (p (n, 3), R (n, 3, 3), C (n, 6, 6)), the information-weighted
    mean of the others: p (n, 3), R (n, 3, 3), its covariance (n, 6, 6), and the chi-square of those
    others about it (6 (n - 2) degrees of freedom when they agree). Gauss-Newton, twice, each mean
    about its own reference (the first of its others to start); of two poses, each other's as it is."""
    got = leave_one_out_many(P[None], Rs[None], C[None])
    return None if got is None else (got[0][0], got[1][0], got[2][0], got[3][0])


def leave_one_out_many(
    P: NDArray, Rs: NDArray, C: NDArray, row: NDArray[np.int_] | None = None
) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
    """:func:`leave_one_out` of b images of n candidates each at once (every array with a leading axis
    of b, the results too), each image's figures those it gives alone; None if any is singular. With
    ``row`` (b,), only that candidate's placement by its others in each image (results of one row each)."""
    b, n = P.shape[:2]
    rows = np.broadcast_to(np.arange(n), (b, n)) if row is None else np.asarray(row)[:, None]
    pick = np.arange(b)[:, None]
    try:
        W = np.linalg.inv(C)
    except np.linalg.LinAlgError:
        return None
    if n == 2:  # each one's others are the other alone: their mean is that pose, its covariance that one's
        other = 1 - rows
        Cs = C[pick, other]
        return P[pick, other], Rs[pick, other], 0.5 * (Cs + np.swapaxes(Cs, -1, -2)), np.zeros(rows.shape)
    others = ~np.eye(n, dtype=bool)[rows]  # (b, i, k): whether candidate k is among i's others
    Wo = W[:, None] * others[..., None, None]  # (b, i, k, 6, 6): candidate k's weight in i's mean
    info = Wo.sum(axis=2)
    first = np.where(rows == 0, 1, 0)
    p_ref, R_ref = P[pick, first], Rs[pick, first]
    try:
        for _ in range(2):
            r = residuals_each(P, Rs, p_ref, R_ref)
            x = np.linalg.solve(info, np.einsum("bikac,bikc->bia", Wo, r)[..., None])[..., 0]
            p_ref = p_ref + x[..., :3]
            R_ref = R_ref @ Rotation.from_rotvec(x[..., 3:].reshape(-1, 3)).as_matrix().reshape(R_ref.shape)
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    r = residuals_each(P, Rs, p_ref, R_ref)
    values = np.einsum("bika,bikac,bikc->bi", r, Wo, r)
    return p_ref, R_ref, 0.5 * (cov + np.swapaxes(cov, -1, -2)), values


def residuals_each(P: NDArray, Rs: NDArray, p_ref: NDArray, R_ref: NDArray) -> NDArray[np.float64]:
    """(b, m, n, 6): each image's n poses' errors about each of its m references (:func:`residuals`)."""
    b, m, n = len(P), p_ref.shape[1], P.shape[1]
    rel = np.swapaxes(R_ref, -1, -2)[:, :, None] @ Rs[:, None]
    rot = rotvecs_from_matrices(rel.reshape(b * m * n, 3, 3)).reshape(b, m, n, 3)
    return np.concatenate([P[:, None] - p_ref[:, :, None], rot], axis=3)


def rotvecs_from_matrices(R: NDArray) -> NDArray[np.float64]:
    """``Rotation.from_matrix(R).as_rotvec()`` of rotation matrices (k, 3, 3) that are orthonormal to
    rounding (products of rotations), by scipy's formulas (Shepperd's quaternion, then its angle) without
    its per-call cost, which the n^2 residuals of a leave-one-out pay three times: its values to a few ulps."""
    k = len(R)
    trace = R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]
    choice = np.argmax(np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], trace], axis=1), axis=1)
    q = np.empty((k, 4))
    rows = np.arange(k)
    for i in range(3):  # the largest diagonal element: q_i from it, the others from off-diagonal sums
        sel = rows[choice == i]
        if len(sel):
            j, m = (i + 1) % 3, (i + 2) % 3
            Ri = R[sel]
            q[sel, i] = 1.0 - trace[sel] + 2.0 * Ri[:, i, i]
            q[sel, j] = Ri[:, j, i] + Ri[:, i, j]
            q[sel, m] = Ri[:, m, i] + Ri[:, i, m]
            q[sel, 3] = Ri[:, m, j] - Ri[:, j, m]
    sel = rows[choice == 3]  # the trace largest: w from it
    if len(sel):
        Ri = R[sel]
        q[sel, 0] = Ri[:, 2, 1] - Ri[:, 1, 2]
        q[sel, 1] = Ri[:, 0, 2] - Ri[:, 2, 0]
        q[sel, 2] = Ri[:, 1, 0] - Ri[:, 0, 1]
        q[sel, 3] = 1.0 + trace[sel]
    q /= np.sqrt(np.sum(q * q, axis=1))[:, None]
    q[q[:, 3] < 0] *= -1.0  # w >= 0: the angle in [0, pi]
    xyz_norm = np.sqrt(np.sum(q[:, :3] * q[:, :3], axis=1))
    angle = 2.0 * np.arctan2(xyz_norm, q[:, 3])
    small = angle <= 1e-3  # the Taylor series of angle / sin(angle / 2) there, as scipy
    a2 = angle * angle
    safe = np.where(small, 1.0, angle)
    scale = np.where(small, 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0, safe / np.sin(safe / 2.0))
    return scale[:, None] * q[:, :3]
