"""How precise a marker's refitted corners are (:mod:`atlas_onboard.detector.refine`): from the statistics of
each side's edge points about its fitted line, each marker's corner noise as one figure and as the (8, 8)
covariance of its four corners, for all markers of a frame at once.

The noise: a line fitted through n points spread evenly over the middle 70 % of an edge and extrapolated to
its end has the variance 7.1 s^2 / n across it (s: the points' scatter, pooled over the four edges), and a
corner lies on two lines crossing at an angle phi, which adds 1 / sin(phi); neighbouring points' errors are
correlated along the edge. What the scatter cannot show is added: the blur's inward pull
(:func:`edge_profile.contamination_px`) and the lens residual.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.detector.edge_profile import contamination_px

MAX_EDGE_CORRELATION = 0.9  # of neighbouring edge points' scatter: at most a tenth of them independent
PREVIOUS = [3, 0, 1, 2]  # side (or corner) i - 1 of i, around the quadrilateral
NEXT = [1, 2, 3, 0]
# Every corner moved alike: common @ common.T with common = np.tile(np.eye(2), (4, 1)), (8, 2).
_COMMON_SHIFT = np.tile(np.eye(2), (4, 4))
_CORNER, _LINE, _ROW = [0, 0, 1, 1, 2, 2, 3, 3], [3, 0, 0, 1, 1, 2, 2, 3], [0, 1] * 4  # corner k: lines k - 1, k

# Per side: its line's point (4, 2) and direction (4, 2); over the sides: the points' summed squared
# distances from their lines; per side: the points' counts (4,), spreads along the lines (4,), levels
# (4, 7); over the sides: the lag-0 and lag-1 sums of the points' distances from their lines.
SideStatistics = tuple[
    NDArray[np.float64], NDArray[np.float64], float, NDArray[np.float64], NDArray[np.float64], NDArray[np.float64],
    float, float,
]  # fmt: skip


def side_statistics(points: NDArray[np.float64], levels: NDArray[np.float64]) -> SideStatistics:
    """:func:`refine._side_statistics_each` of markers whose four sides have every point placed, stacked:
    ``points`` (M, 4, S, 2), ``levels`` (M, 4, S, 5); each element of the result has a leading axis M."""
    m, n = points.shape[0], points.shape[2]
    means = points.mean(axis=2)
    centred = points - means[:, :, None, :]
    _, svs, vts = np.linalg.svd(centred, full_matrices=False)
    d = vts[:, :, 0, :]  # each line's direction; its normal (-d_y, d_x)
    cx, cy = centred[..., 0], centred[..., 1]
    u = cx * d[:, :, None, 0] + cy * d[:, :, None, 1]
    r = cy * d[:, :, None, 0] - cx * d[:, :, None, 1]
    per_row = np.empty((m, 4, n, 4))
    per_row[..., :3] = levels[..., :3]
    per_row[..., 3] = levels[..., 3] + levels[..., 4]
    errors = 1.2533 * per_row[..., [0, 1, 3]].std(axis=2) / math.sqrt(n)
    # The median of each column: the middle one of the sorted values, or the mean of the two middle ones.
    ordered = np.sort(per_row, axis=2)
    median = ordered[:, :, n // 2] if n % 2 else (ordered[:, :, n // 2 - 1] + ordered[:, :, n // 2]) / 2.0
    edge_levels = np.concatenate([median, errors], axis=2)
    ss = (svs[:, :, 1] ** 2).sum(axis=1)
    lag0 = (r * r).sum(axis=(1, 2))
    lag1 = (r[:, :, 1:] * r[:, :, :-1]).sum(axis=(1, 2))
    return means, d, ss, np.full((m, 4), float(n)), (u * u).sum(axis=2), edge_levels, lag0, lag1  # type: ignore[return-value]


def corner_noise(
    corners: NDArray[np.float64], stats: SideStatistics, shift_px: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """M markers' corner noise: each marker's as one figure (M,) (px per axis, the edge fits' alone: the lens
    residual moves the four corners alike, which turns no pose; counted per corner it would blur the tilt a
    gravity check needs) and the (M, 8, 8) covariance of its ``corners`` (M, 4, 2), from its sides'
    statistics (stacked, ``SideStatistics`` with a leading axis M) and the lens residual's shift (M,)
    (undistorted px)."""
    means, dirs, ss, npts, spread, edge_levels, lag0, lag1 = stats
    n_all = npts.sum(axis=1)
    scatter2 = ss / np.maximum(n_all - 8, 1)  # two parameters a line
    # Two lines crossing at an angle phi place their crossing 1 / sin(phi) less precisely than
    # perpendicular ones (a marker seen obliquely has sharp corners in the image).
    following = dirs[:, NEXT]
    sin_min = np.abs(dirs[..., 0] * following[..., 1] - dirs[..., 1] * following[..., 0]).min(axis=1)
    # Neighbouring edge points share pixels, blur and aliasing, so their errors are correlated along the
    # edge: with a lag-one correlation rho, n points carry the information of n (1 - rho) / (1 + rho)
    # independent ones (an AR(1) sequence's effective sample size).
    ratio = lag1 / np.where(lag0 > 0, lag0, 1.0)
    rho = np.where(lag0 > 0, np.minimum(np.maximum(ratio, 0.0), MAX_EDGE_CORRELATION), 0.0)  # np.clip's value
    inflate = (1.0 + rho) / (1.0 - rho)
    n_eff = n_all / 4 / inflate
    sigma = np.sqrt(7.1 * scatter2 / n_eff) / np.maximum(sin_min, 0.2)
    shrink = contamination_px(edge_levels)
    return sigma, corner_covariances(means, dirs, corners, scatter2 * inflate, npts, spread, shrink, shift_px)


def corner_covariances(
    means: NDArray[np.float64],
    dirs: NDArray[np.float64],
    corners: NDArray[np.float64],
    var_px2: NDArray[np.float64],
    npts: NDArray[np.float64],
    spread: NDArray[np.float64],
    shrink_px: NDArray[np.float64] | None,
    shift_px: NDArray[np.float64],
) -> NDArray[np.float64]:
    """:func:`refine._corner_covariance` of M markers at once: their lines' points and directions (M, 4, 2), corners
    (M, 4, 2), ``var_px2`` (M,), ``npts`` and ``spread`` (M, 4), ``shrink_px`` (M, 4) or None, ``shift_px``
    (M,); (M, 8, 8)."""
    m = len(means)
    G = np.zeros((m, 8, 8))  # d(corners) / d(a_0, b_0, ..., a_3, b_3)
    N = np.empty((m, 4, 2, 2))  # corner k: the normals (-d_y, d_x) of lines k - 1 and k as rows
    N[:, :, 0, 0], N[:, :, 0, 1] = -dirs[:, PREVIOUS, 1], dirs[:, PREVIOUS, 0]
    N[:, :, 1, 0], N[:, :, 1, 1] = -dirs[:, :, 1], dirs[:, :, 0]
    Ninvs = np.linalg.inv(N)
    # Corner k's two lines: j = k - 1 (row 0 of its system) and k (row 1); t: its place along line j.
    t = ((corners[:, _CORNER] - means[:, _LINE]) * dirs[:, _LINE]).sum(axis=2)  # (M, 8)
    blocks = G.reshape(m, 4, 2, 4, 2)  # (marker, corner, x/y, line, offset/turn)
    # (8, M, 2): Ninv[:, row] of each corner's each line (the advanced indices' axis first)
    column = Ninvs[:, _CORNER, :, _ROW]
    blocks[:, _CORNER, :, _LINE, 0] = column
    blocks[:, _CORNER, :, _LINE, 1] = column * t.T[:, :, None]
    D = np.empty((m, 8))
    D[:, 0::2] = var_px2[:, None] / npts
    D[:, 1::2] = var_px2[:, None] / np.maximum(spread, 1e-9)
    out = (G * D[:, None, :]) @ np.swapaxes(G, 1, 2) + (shift_px**2)[:, None, None] * _COMMON_SHIFT
    if shrink_px is not None:
        s = G[:, :, 0::2] @ shrink_px[:, :, None]  # the corners' displacement when every line moves in by its shrink
        out += s @ np.swapaxes(s, 1, 2)
    return out
