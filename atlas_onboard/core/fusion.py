"""Filtering and fusion: the EMA of eq. 3 and the weighted means of eq. 4-7.

Positions are averaged component-wise (eq. 4). Quaternions cannot be: q and -q are the same rotation
and would cancel. The paper (eq. 5) stacks the weighted quaternions as Q = [w_1 q_1 ... w_n q_n] and
takes the eigenvector of Q Q^T with the largest eigenvalue. Q Q^T = sum w_i^2 q_i q_i^T, which is
exactly scipy's weighted chordal mean (``Rotation.mean``, Markley et al. 2007) with weights w_i^2;
we call scipy with those weights rather than re-implementing it. With the paper's weights
w_i = sigma_min / sigma_i this weighs rotations by inverse variance, which is also the maximum
likelihood choice.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.errors import GeometryError


def ema_position(prev_p: NDArray[np.float64], new_p: NDArray[np.float64], alpha: float) -> NDArray[np.float64]:
    """Eq. 3, Y_t = Z_t * alpha + Y_{t-1} * (1 - alpha), on a position; alpha = 1 passes Z_t through."""
    if alpha == 1.0:
        return np.array(new_p, dtype=float)
    return alpha * np.asarray(new_p, dtype=float) + (1.0 - alpha) * np.asarray(prev_p, dtype=float)


def ema_quaternion(prev_q: NDArray[np.float64], new_q: NDArray[np.float64], alpha: float) -> NDArray[np.float64]:
    """Eq. 3 on a unit quaternion (either order), safe for the sign ambiguity of q and -q.

    The new quaternion is first moved into the previous one's hemisphere, so that a measurement
    arriving as -q (the same rotation) does not drag the filter through zero; the blend is then
    re-normalised. alpha = 1 passes the new quaternion through unchanged.
    """
    new = np.asarray(new_q, dtype=float)
    if alpha == 1.0:
        return new.copy()
    prev = np.asarray(prev_q, dtype=float)
    if float(np.dot(prev, new)) < 0.0:
        new = -new
    blend = alpha * new + (1.0 - alpha) * prev
    return blend / np.linalg.norm(blend)


def sigma_min_weights(sigmas: NDArray[np.float64]) -> NDArray[np.float64]:
    """Eq. 6-7: w_i = sigma_min / sigma_i, so the best sensor has weight 1 and the others less."""
    s = _check_sigmas(sigmas)
    return s.min() / s


def inverse_variance_weights(sigmas: NDArray[np.float64]) -> NDArray[np.float64]:
    """w_i = 1 / sigma_i^2, normalised so the best sensor has weight 1 (the minimum-variance choice)."""
    s = _check_sigmas(sigmas)
    return (s.min() / s) ** 2


def _check_sigmas(sigmas: NDArray[np.float64]) -> NDArray[np.float64]:
    s = np.asarray(sigmas, dtype=float)
    if s.ndim != 1 or s.size == 0:
        raise GeometryError(f"expected a non-empty 1-D array of sigmas, got shape {s.shape}")
    if not np.all(np.isfinite(s)) or np.any(s <= 0.0):
        raise GeometryError(f"expected finite sigmas > 0, got {s.tolist()}")
    return s


def weighted_mean_position(p: NDArray[np.float64], weights: NDArray[np.float64]) -> NDArray[np.float64]:
    """Eq. 4 on positions of shape (N, 3)."""
    w = np.asarray(weights, dtype=float)
    return (w[:, None] * np.asarray(p, dtype=float)).sum(axis=0) / w.sum()


def weighted_mean_rotation(q_xyzw: NDArray[np.float64], weights: NDArray[np.float64]) -> Rotation:
    """Eq. 5: the largest eigenvector of Q Q^T with Q = [w_1 q_1 ... w_n q_n], by scipy.

    Invariant to the sign of each input quaternion; exact for identical inputs.
    """
    w = np.asarray(weights, dtype=float)
    return Rotation.from_quat(q_xyzw).mean(weights=w * w)


def fused_sigma(sigmas: NDArray[np.float64], weights: NDArray[np.float64]) -> float:
    """Standard deviation of the weighted mean of independent candidates: sqrt(sum a_i^2 sigma_i^2)."""
    w = np.asarray(weights, dtype=float)
    a = w / w.sum()
    return float(np.sqrt(np.sum((a * np.asarray(sigmas, dtype=float)) ** 2)))


def fuse(
    p: NDArray[np.float64], q_xyzw: NDArray[np.float64], sigmas: NDArray[np.float64], inverse_variance: bool = False
) -> tuple[NDArray[np.float64], Rotation, float]:
    """Fuse N candidate poses: (position (3,), rotation, sigma). The paper's weights unless told otherwise."""
    s = np.asarray(sigmas, dtype=float)
    w = inverse_variance_weights(s) if inverse_variance else sigma_min_weights(s)
    return weighted_mean_position(p, w), weighted_mean_rotation(q_xyzw, w), fused_sigma(s, w)


@dataclass(frozen=True, slots=True)
class Runs:
    """The runs of equal values in a sorted array of group ids: run k starts at ``starts[k]``, holds
    ``sizes[k]`` items of group ``ids[k]`` (the layout ``np.ufunc.reduceat`` sums over)."""

    starts: NDArray[np.intp]
    ids: NDArray[np.intp]
    sizes: NDArray[np.intp]


def runs_of(sorted_ids: NDArray[np.intp]) -> Runs:
    """The :class:`Runs` of a non-empty array whose equal values are contiguous."""
    g = np.asarray(sorted_ids)
    starts = np.flatnonzero(np.concatenate(([True], g[1:] != g[:-1])))
    return Runs(starts, g[starts], np.diff(np.append(starts, len(g))))


def fuse_runs(
    runs: Runs,
    p: NDArray[np.float64],
    q_xyzw: NDArray[np.float64],
    sigmas: NDArray[np.float64],
    weights: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Fuse many groups of candidates at once (eq. 4-7 per group), sorted by group (the graph sorts them
    once per shape of the graph): ``p``, ``q_xyzw``, ``sigmas``, ``weights`` (N, 3), (N, 4), (N,), (N,)
    candidates and their weights. Returns positions, quaternions and sigmas, one per run."""
    starts = runs.starts
    wsum = np.add.reduceat(weights, starts)
    pos = np.add.reduceat(weights[:, None] * p, starts) / wsum[:, None]
    a = weights / np.repeat(wsum, runs.sizes)
    sig = np.sqrt(np.add.reduceat((a * sigmas) ** 2, starts))
    # Eq. 5 per group: the eigenvector of the largest eigenvalue of Q Q^T = sum_i w_i^2 q_i q_i^T,
    # the same as scipy's weighted Rotation.mean (tested against it) written out with numpy, which
    # batches every group in one call where scipy takes one call per group.
    q = q_xyzw / np.sqrt(np.einsum("ij,ij->i", q_xyzw, q_xyzw))[:, None]
    outer = (weights**2)[:, None, None] * (q[:, :, None] * q[:, None, :])
    _, vectors = np.linalg.eigh(np.add.reduceat(outer, starts))
    mean = vectors[..., -1]
    return pos, np.where(mean[:, 3:] < 0.0, -mean, mean), sig  # the representative with w >= 0
