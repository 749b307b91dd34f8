"""The covariance and matrix helpers of eq. 1's edges (the listener's, :mod:`atlas_onboard.listener`): which detection
covariances are positive definite, which records' sigma contradicts their covariance, each edge's 6x6
covariance through eq. 1, a camera position's spread, a detection's attitude sigma, and 4x4 matrices of
poses."""

from __future__ import annotations

from typing import TypeVar

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core import covariance, geometry
from atlas_onboard.core.markerdata import MarkerData, Rejection, upper_to_matrix

Item = TypeVar("Item")  # what a valid record becomes in the caller's list (the listener's EdgeUpdate)


def positive_definite(
    valid: list[MarkerData], out: list[Item | Rejection]
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


SIGMA_COVARIANCE_TOLERANCE = 30.0
"""How far (a factor, either way) a record's ``sigma`` may be from the camera position spread its own
covariance implies (the square root of the largest eigenvalue of that position's covariance, which is
what the detector's sigma is: :mod:`atlas_onboard.detector.pose`). The two come from the same corners
by different routes (a face-on tag's sigma is capped by the second order, the covariance adds the
other solution's moment, refined corners and joint solves have their own noise models), so honest
records differ: from 0.12 to 11.2 over the simulated scenarios' rendered detections (every scenario,
30 frames each). 30 leaves a margin of about 3 on both sides."""


def inconsistent_sigma(
    valid: list[MarkerData],
    out: list[Item | Rejection],
    C_sm: NDArray[np.float64] | None,
    own_sensors: frozenset[int] = frozenset(),
) -> tuple[list[MarkerData], NDArray[np.float64] | None]:
    """``valid`` without the records whose ``sigma`` contradicts their covariance (beyond
    ``SIGMA_COVARIANCE_TOLERANCE``: those become ``inconsistent_sigma`` in ``out``), and ``C_sm`` (the
    covariances as matrices when every record has one) for those kept. A record without a covariance
    has nothing to contradict; one of the node's own sensors (``own_sensors``: its own detector, not
    a peer's claim) is not checked, which keeps the own camera's path as short as it was."""
    have = [j for j, md in enumerate(valid) if md.covariance and md.sensor_id not in own_sensors]
    if not have:
        return valid, C_sm
    C = C_sm[have] if C_sm is not None else upper_to_matrix(np.array([valid[j].covariance for j in have]))
    p = np.array([valid[j].p_sensor_marker_m for j in have])
    q = np.array([valid[j].q_sensor_marker_wxyz for j in have])[:, [1, 2, 3, 0]]
    R = geometry.quat_matrix(q / np.sqrt(np.einsum("ij,ij->i", q, q))[:, None])
    spread = np.sqrt(np.maximum(np.linalg.eigvalsh(_camera_position_cov(p, R, C))[:, -1], 0.0))
    sigma = np.array([valid[j].sigma_m for j in have])
    ok = (sigma * SIGMA_COVARIANCE_TOLERANCE >= spread) & (sigma <= spread * SIGMA_COVARIANCE_TOLERANCE)
    if ok.all():
        return valid, C_sm
    bad = {id(valid[j]) for j, good in zip(have, ok.tolist(), strict=True) if not good}
    for i, item in enumerate(out):
        if id(item) in bad:
            out[i] = Rejection.INCONSISTENT_SIGMA
    kept = [md for md in valid if id(md) not in bad]
    if C_sm is None:
        return kept, None
    keep = np.ones(len(valid), dtype=bool)
    keep[np.array(have)[~ok]] = False
    return kept, C_sm[keep]


def _camera_position_cov(
    p_sm: NDArray[np.float64], R_sm: NDArray[np.float64], C_sm: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(N, 3, 3): the covariance of the camera's position in the marker frame, -R^T p, from N
    T_sensor_marker covariances (core.covariance convention): J = [-R^T, -[R^T p]x]."""
    Rt = np.swapaxes(R_sm, 1, 2)
    v = np.einsum("nij,nj->ni", Rt, p_sm)
    J = np.concatenate([-Rt, -covariance.skew(v)], axis=2)
    return J @ C_sm @ np.swapaxes(J, 1, 2)


def edge_covariances(
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


def camera_spread(p_sm: NDArray[np.float64], R_sm: NDArray[np.float64], C_sm: NDArray[np.float64]) -> float:
    """Trace (m^2) of the covariance of the camera's position in the marker frame, -R^T p, from a
    T_sensor_marker covariance (core.covariance convention): J = [-R^T, -[R^T p]x]."""
    v = R_sm.T @ p_sm
    J = np.hstack([-R_sm.T, -covariance.skew(v)])
    return float(np.trace(J @ C_sm @ J.T))


def rotation_sigma(md: MarkerData, range_m: float) -> float:
    """A detection's attitude standard deviation (rad) about its own solution: its camera position
    sigma over the range (a single tag's camera position error is range x angle). Not the covariance's,
    which may hold the spread between the two solutions (the second moment of the other)."""
    return md.sigma_m / max(range_m, 1e-3)


def pose_matrices(p: NDArray[np.float64], q_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """4x4 matrices of N poses given as positions (N, 3) and x-first quaternions (N, 4)."""
    M = np.tile(np.eye(4), (len(p), 1, 1))
    M[:, :3, :3] = Rotation.from_quat(q_xyzw).as_matrix()
    M[:, :3, 3] = p
    return M
