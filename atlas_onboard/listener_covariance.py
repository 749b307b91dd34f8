"""The listener's covariance and matrix helpers (:mod:`atlas_onboard.listener`): which detection
covariances are positive definite, each edge's 6x6 covariance through eq. 1, a camera position's spread,
a detection's attitude sigma, and 4x4 matrices of poses."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core import covariance
from atlas_onboard.core.markerdata import MarkerData, Rejection, upper_to_matrix

if TYPE_CHECKING:
    from atlas_onboard.listener import EdgeUpdate


def _positive_definite(
    valid: list[MarkerData], out: list[EdgeUpdate | Rejection]
) -> tuple[list[MarkerData], NDArray[np.float64] | None]:
    """``valid`` without the records whose covariance is not positive definite (those become
    ``bad_covariance`` in ``out``), and the covariances of those kept as matrices when every one
    has one (else None). One batched Cholesky factorisation, which fails if any does (half the
    cost of eigenvalues); only then eigenvalues say which."""
    have = [md for md in valid if md.covariance]
    C = upper_to_matrix(np.array([md.covariance for md in have]))
    try:
        np.linalg.cholesky(C)
        return valid, C if len(have) == len(valid) else None
    except np.linalg.LinAlgError:
        lowest = np.linalg.eigvalsh(C)[:, 0]
    bad = {id(md) for md, low in zip(have, lowest.tolist(), strict=True) if not low > 0.0}
    for i, item in enumerate(out):
        if id(item) in bad:
            out[i] = Rejection.BAD_COVARIANCE
    return [md for md in valid if id(md) not in bad], None


def _covariances(
    valid: list[MarkerData], chain: covariance.Chain, C_sm: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """Each edge's 6x6 covariance (``chain``: eq. 1's parts of each record in ``valid``): the detector's own,
    carried through eq. 1's mountings, where the record has one; otherwise modelled from its sigma and
    range (:func:`covariance.observation_parts`). ``C_sm``: the records' detection covariances as matrices,
    if already made (every record has one)."""
    have = [i for i, md in enumerate(valid) if md.covariance]
    if len(have) == len(valid):
        if C_sm is None:
            C_sm = upper_to_matrix(np.array([md.covariance for md in valid]))
        return covariance.detection(chain, C_sm)
    cov = covariance.observation_parts(chain, np.array([md.sigma_m for md in valid]))
    if have:
        C_sm = upper_to_matrix(np.array([valid[i].covariance for i in have]))
        cov[have] = covariance.detection(chain[have], C_sm)
    return cov


def _camera_spread(p_sm: NDArray[np.float64], R_sm: NDArray[np.float64], C_sm: NDArray[np.float64]) -> float:
    """Trace (m^2) of the covariance of the camera's position in the marker frame, -R^T p, from a
    T_sensor_marker covariance (core.covariance convention): J = [-R^T, -[R^T p]x]."""
    v = R_sm.T @ p_sm
    J = np.hstack([-R_sm.T, -covariance.skew(v)])
    return float(np.trace(J @ C_sm @ J.T))


def _rotation_sigma(md: MarkerData, range_m: float) -> float:
    """A detection's attitude standard deviation (rad) about its own solution: its camera position
    sigma over the range (a single tag's camera position error is range x angle). Not the covariance's,
    which may hold the spread between the two solutions (the second moment of the other)."""
    return md.sigma_m / max(range_m, 1e-3)


def _matrices(p: NDArray[np.float64], q_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """4x4 matrices of N poses given as positions (N, 3) and x-first quaternions (N, 4)."""
    M = np.tile(np.eye(4), (len(p), 1, 1))
    M[:, :3, :3] = Rotation.from_quat(q_xyzw).as_matrix()
    M[:, :3, 3] = p
    return M
