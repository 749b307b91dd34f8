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
    about its own reference (the first of its others to start)."""
    n = len(P)
    try:
        W = np.linalg.inv(C)
    except np.linalg.LinAlgError:
        return None
    others = ~np.eye(n, dtype=bool)
    Wo = W[None] * others[:, :, None, None]  # (i, k, 6, 6): candidate k's weight in i's mean
    info = Wo.sum(axis=1)
    first = np.where(np.arange(n) == 0, 1, 0)
    p_ref, R_ref = P[first], Rs[first]
    try:
        for _ in range(2):
            r = residuals_each(P, Rs, p_ref, R_ref)
            x = np.linalg.solve(info, np.einsum("ikab,ikb->ia", Wo, r)[..., None])[..., 0]
            p_ref = p_ref + x[:, :3]
            R_ref = R_ref @ Rotation.from_rotvec(x[:, 3:]).as_matrix()
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    r = residuals_each(P, Rs, p_ref, R_ref)
    values = np.einsum("ika,ikab,ikb->i", r, Wo, r)
    return p_ref, R_ref, 0.5 * (cov + np.swapaxes(cov, -1, -2)), values


def residuals_each(P: NDArray, Rs: NDArray, p_ref: NDArray, R_ref: NDArray) -> NDArray[np.float64]:
    """(m, n, 6): the n poses' errors about each of m references (:func:`residuals`)."""
    m, n = len(p_ref), len(P)
    rel = np.swapaxes(R_ref, -1, -2)[:, None] @ Rs[None]
    rot = Rotation.from_matrix(rel.reshape(m * n, 3, 3)).as_rotvec().reshape(m, n, 3)
    return np.concatenate([P[None] - p_ref[:, None], rot], axis=2)
