"""6x6 pose covariances carried along chains of transforms (the paper's future work: honest uncertainty).

Convention (the same everywhere in atlas-onboard, and what the autopilot message wants once turned
to NED/FRD): a pose T_a_b = (p, R) is uncertain as ``p_true = p + dp`` with ``dp`` in frame a, and
``R_true = R Exp(dtheta)`` with ``dtheta`` a small rotation about b's own axes. The 6-vector is
``[dp, dtheta]``; its covariance is (m^2, m rad, rad^2).

First-order propagation (derived in docs/covariance.md):

- composition ``T_w_c = T_w_p T_p_c``: ``C_c = Jp C_p Jp^T + Je C_e Je^T`` with
  ``Jp = [[I, -R_wp [p_pc]x], [0, R_pc^T]]`` and ``Je = blockdiag(R_wp, I)``;
- inverse ``T_b_a = T_a_b^-1``: ``C_ba = Ji C_ab Ji^T`` with ``Ji = [[-R_ab^T, [p_ba]x], [0, -R_ab]]``;
- a weighted mean of candidates that share a parent: the parent's error is common to all of them
  and does not average out, each edge's own error does.

Everything here is batched over a leading axis (numpy ``matmul``) and pure.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core import fusion

MIN_ATTITUDE_SIGMA_RAD = math.radians(0.1)
MAX_ATTITUDE_SIGMA_RAD = math.radians(30.0)


def skew(v: NDArray[np.float64]) -> NDArray[np.float64]:
    """Cross-product matrices of vectors, shape (..., 3) -> (..., 3, 3): ``skew(a) @ b == a x b``
    (linear in a: one product with a constant (3, 9) matrix)."""
    v = np.asarray(v, dtype=float)
    return (v @ _SKEW).reshape(*v.shape[:-1], 3, 3)


_SKEW = np.zeros((3, 9))
_SKEW[2, 1], _SKEW[1, 2], _SKEW[2, 3], _SKEW[0, 5], _SKEW[1, 6], _SKEW[0, 7] = -1, 1, 1, -1, -1, 1


ATTITUDE_PER_POSITION = 2.0
"""Attitude sigma (rad) per (position sigma / range): measured in the simulator's rendered detection
(paper-test1: candidates' attitude error 0.87 deg RMS where position sigma / range gave 0.46 deg)."""


def attitude_sigma_rad(
    sigma_m: NDArray[np.float64] | float, range_m: NDArray[np.float64] | float
) -> NDArray[np.float64]:
    """Attitude standard deviation of a marker observation from its camera-position sigma and range.

    A tag's camera-position error is mostly its tilt error swung over the range (lateral error =
    range x angle), so the angle's sigma scales with sigma / range (times ATTITUDE_PER_POSITION);
    clamped to [0.1, 30] degrees.
    """
    r = np.maximum(np.asarray(range_m, dtype=float), 0.05)
    s = ATTITUDE_PER_POSITION * np.asarray(sigma_m, dtype=float) / r
    return np.minimum(np.maximum(s, MIN_ATTITUDE_SIGMA_RAD), MAX_ATTITUDE_SIGMA_RAD)


@dataclass(frozen=True)
class Chain:
    """Edges ``T_a_b = T_a_s T_s_m T_m_b`` (eq. 1), batched over a leading axis: the sensor's fixed mounting
    rotation ``R_as`` (..., 3, 3), the detection ``(p_sm, R_sm)`` ((..., 3), (..., 3, 3)) and the fixed
    ``T_m_b`` (..., 4, 4)."""

    R_as: NDArray[np.float64]
    R_sm: NDArray[np.float64]
    p_sm: NDArray[np.float64]
    T_m_b: NDArray[np.float64]

    @cached_property
    def p_sb(self) -> NDArray[np.float64]:
        """(..., 3): b's origin in the sensor frame, ``p_sm + R_sm p_mb`` (eq. 1's translation needs it too)."""
        return self.p_sm + (self.R_sm @ self.T_m_b[..., :3, 3, None])[..., 0]

    def __getitem__(self, index: object) -> Chain:
        """The edges at ``index`` (an index of the leading axis)."""
        return Chain(self.R_as[index], self.R_sm[index], self.p_sm[index], self.T_m_b[index])


def observation(
    T_a_s: NDArray[np.float64], T_s_m: NDArray[np.float64], T_m_b: NDArray[np.float64], sigma_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Covariances of edges ``T_a_b = T_a_s T_s_m T_m_b`` (eq. 1; 4x4 matrices, batched) whose only
    uncertain factor is the detection ``T_s_m``.

    The detection's error is modelled where it arises: the camera's position in the marker frame
    (isotropic, ``sigma_m``, the detector's sigma) and the attitude (:func:`attitude_sigma_rad`).
    Carried through the fixed mountings it keeps its real geometry: an entity far from the marker
    it is known by inherits the attitude error over that lever arm, and nothing else does.
    """
    return observation_parts(Chain(T_a_s[..., :3, :3], T_s_m[..., :3, :3], T_s_m[..., :3, 3], T_m_b), sigma_m)


def observation_parts(chain: Chain, sigma_m: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`observation` of the edges of ``chain`` (the parts eq. 1 computes anyway)."""
    # C_ms is diagonal: (sigma^2 x3, att^2 x3). T_a_b's error is M times the detection's error, with M
    # the inverse's Jacobian (T_m_s -> T_s_m), then left by the fixed T_a_s (positions rotate into a,
    # rotations stay about m's axes), then right by the fixed T_m_b (the parent part of a composition).
    # Multiplied out (docs/covariance.md), M = [[-R_am, K], [0, -R_bs]] with K = R_as [p_sb]x, so
    # C = [[sigma^2 I + att^2 K K^T, -att^2 K R_sb], [., att^2 I]]: a handful of products, however
    # many observations (tested equal to the product of the three Jacobians).
    p_sm = chain.p_sm
    rng = np.sqrt(np.einsum("...i,...i->...", p_sm, p_sm))
    sigma = np.asarray(sigma_m, dtype=float)
    var_att = attitude_sigma_rad(sigma, rng) ** 2
    # With G = [[K], [-R_sb^T]] (6x3), C = att^2 G G^T + sigma^2 diag(1, 1, 1, 0, 0, 0).
    K = chain.R_as @ skew(chain.p_sb)
    G = np.concatenate((K, -np.swapaxes(chain.R_sm @ chain.T_m_b[..., :3, :3], -1, -2)), axis=-2)
    return var_att[..., None, None] * (G @ np.swapaxes(G, -1, -2)) + (sigma**2)[..., None, None] * _POSITION_BLOCK


_POSITION_BLOCK = np.diag([1.0, 1.0, 1.0, 0.0, 0.0, 0.0])


def detection(chain: Chain, C_sm: NDArray[np.float64]) -> NDArray[np.float64]:
    """Covariances of the edges of ``chain`` from the detector's own covariance of ``T_s_m`` (``C_sm``,
    batched (..., 6, 6): dp in the sensor frame, dtheta about the marker's axes), carried through the
    fixed mountings: left by ``T_a_s`` the position error turns into frame a, right by ``T_m_b`` the
    marker's rotation error swings b over the lever arm ``p_mb`` and turns into b's axes.
    ``J = [[R_as, -R_am [p_mb]x], [0, R_mb^T]]``, ``C_ab = J C_sm J^T``."""
    n = np.shape(C_sm)[:-2]
    J = np.zeros((*n, 6, 6))
    J[..., :3, :3] = chain.R_as
    J[..., :3, 3:] = -(chain.R_as @ chain.R_sm) @ skew(chain.T_m_b[..., :3, 3])
    J[..., 3:, 3:] = np.swapaxes(chain.T_m_b[..., :3, :3], -1, -2)
    return transform(J, C_sm)


def diagonal(sigma_m: NDArray[np.float64] | float, sigma_att_rad: NDArray[np.float64] | float) -> NDArray[np.float64]:
    """Covariances of isotropic position and attitude errors, shape (..., 6, 6)."""
    s = np.asarray(sigma_m, dtype=float)
    a = np.broadcast_to(np.asarray(sigma_att_rad, dtype=float), s.shape)
    out = np.zeros((*s.shape, 6, 6))
    i = np.arange(3)
    out[..., i, i] = (s**2)[..., None]
    out[..., i + 3, i + 3] = (a**2)[..., None]
    return out


def inverse_jacobian(p_ab: NDArray[np.float64], R_ab: NDArray[np.float64]) -> NDArray[np.float64]:
    """Jacobian of the inverse, shape (..., 6, 6): ``C_ba = Ji C_ab Ji^T``."""
    R_ba = np.swapaxes(R_ab, -1, -2)
    p_ba = -(R_ba @ np.asarray(p_ab, dtype=float)[..., None])[..., 0]
    J = np.zeros((*np.shape(p_ab)[:-1], 6, 6))
    J[..., 0:3, 0:3] = -R_ba
    J[..., 0:3, 3:6] = skew(p_ba)
    J[..., 3:6, 3:6] = -R_ab
    return J


def transform(J: NDArray[np.float64], C: NDArray[np.float64]) -> NDArray[np.float64]:
    """``J C J^T``, batched."""
    return J @ C @ np.swapaxes(J, -1, -2)


def compose_jacobians(
    R_wp: NDArray[np.float64], p_pc: NDArray[np.float64], R_pc: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Jacobians (Jp, Je) of ``T_w_c = T_w_p T_p_c`` with respect to the parent's and the edge's errors."""
    lead = np.shape(p_pc)[:-1]
    Jp = np.empty((*lead, 6, 6))
    Jp[...] = _JP_TEMPLATE
    Jp[..., 0:3, 3:6] = -(R_wp @ skew(p_pc))
    Jp[..., 3:6, 3:6] = np.swapaxes(R_pc, -1, -2)
    Je = np.empty((*lead, 6, 6))
    Je[...] = _JE_TEMPLATE
    Je[..., 0:3, 0:3] = R_wp
    return Jp, Je


_JP_TEMPLATE = np.eye(6)  # the identity block of Jp, zeros below it (the other blocks are written)
_JP_TEMPLATE[3:, 3:] = 0.0
_JE_TEMPLATE = np.eye(6)


def runs_by_parent(child: NDArray[np.intp], parent: NDArray[np.intp]) -> tuple[fusion.Runs, fusion.Runs]:
    """For candidates sorted by child, then parent: the runs of each child, and the runs of each
    (child, parent) pair (their ``ids`` are the parents; their ``sizes`` count pairs per child)."""
    kids = fusion.runs_of(child)
    change = np.concatenate(([True], (child[1:] != child[:-1]) | (parent[1:] != parent[:-1])))
    starts = np.flatnonzero(change)
    per_kid = np.add.reduceat(change.astype(np.intp), kids.starts)
    return kids, fusion.Runs(starts, parent[starts], per_kid)


def fuse_runs(
    kids: fusion.Runs,
    pairs: fusion.Runs,
    weights: NDArray[np.float64],
    Jp: NDArray[np.float64] | None,
    C_parent: NDArray[np.float64],
    edge_term: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Covariance of each child's weighted mean of candidates, for candidates sorted by child, then
    parent (:func:`runs_by_parent`): one 6x6 per child run. ``Jp`` None: the parents' poses are exact
    (the root of the graph).

    Candidate i comes from its parent (covariance ``C_parent[parent]``, Jacobian ``Jp[i]``) with its own
    edge error ``edge_term[i] = Je C_e Je^T``. With normalised weights w_i, the mean's error is
    ``sum_i w_i (Jp_i e_parent + Je_i e_edge_i)``: the edge terms add as ``w_i^2``, and each parent's
    term as ``(sum of w_i Jp_i over its candidates) C_parent (...)^T``.

    The fused position is the mean weighted by w_i, the fused rotation the chordal mean weighted by
    w_i^2 (eq. 5, :func:`fusion.fuse_runs`): to first order the rotation error is the mean of the
    candidates' rotation errors with the normalised weights w_i^2, so each candidate's error enters
    the fused one through ``W_i = diag(a_i, a_i, a_i, b_i, b_i, b_i)``, a and b the two normalised
    weights."""
    a = weights / np.repeat(np.add.reduceat(weights, kids.starts), kids.sizes)
    w2 = weights**2
    b = w2 / np.repeat(np.add.reduceat(w2, kids.starts), kids.sizes)
    W = np.concatenate((np.repeat(a[:, None], 3, axis=1), np.repeat(b[:, None], 3, axis=1)), axis=1)  # (n, 6)
    out = np.add.reduceat(W[:, :, None] * edge_term * W[:, None, :], kids.starts)
    if Jp is None:
        return out
    # Candidates sharing a parent: their parent Jacobians add before the parent's covariance.
    A = np.add.reduceat(W[:, :, None] * Jp, pairs.starts)
    first_pair = np.cumsum(pairs.sizes) - pairs.sizes
    return out + np.add.reduceat(transform(A, C_parent[pairs.ids]), first_pair)
