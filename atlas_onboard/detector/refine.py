"""Sub-pixel corner refinement by edge fitting (for OpenCV's ArUco corners, which sit inside the true
ones by a few tenths of a pixel).

Each side of the quadrilateral is sampled at points away from the corners; at each point the image is
sampled along the side's normal, the edge is placed at the sub-pixel maximum of the intensity gradient
(a parabola through the peak and its neighbours), a line is fitted through these edge points by least
squares, and the refined corners are the intersections of adjacent lines. The AprilTag library refines
its corners the same way.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.detector import edge_profiles
from atlas_onboard.detector.corner_noise import (
    NEXT,
    PREVIOUS,
    SideStatistics,
    corner_covariances,
    corner_noise,
    side_statistics,
)
from atlas_onboard.detector.edge_profile import place_edges
from atlas_onboard.detector.edge_sampling import sampling
from atlas_onboard.detector.lens import bend_px

MAX_MOVE_PX = 2.0  # a refitted corner farther than this from where it started (beyond the lens's bend): a wrong fit
# The library's sides are straight in the distorted image, so its corners are off by about the bend of those sides
# in undistorted pixels; a refit may rightly move them about that far (with a margin).
BEND_ALLOWANCE = 1.5


def sides(
    corners: NDArray[np.float64],
) -> list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]] | None:
    """The four sides of ``corners`` (4, 2), side i from corner i to corner i + 1: its first corner, its
    vector and its unit normal pointing out of the marker; None if a side is shorter than 8 px (no edge
    to fit)."""
    center = corners.mean(axis=0)
    vectors = corners[NEXT] - corners
    out = []
    for i in range(4):
        a, d = corners[i], vectors[i]
        length = math.sqrt(d.dot(d))  # np.linalg.norm's value
        if length < 8:
            return None
        n = np.array([-float(d[1]) / length, float(d[0]) / length])  # (d / length turned a quarter)
        if n @ (center - a) > 0:  # normal pointing out of the marker
            n = -n
        out.append((a, d, n))
    return out


def crossings(
    lines: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    corners: NDArray[np.float64],
    max_move_px: float = MAX_MOVE_PX,
) -> NDArray[np.float64] | None:
    """The corners (4, 2) where adjacent fitted edges (point, direction) cross; None where two are
    parallel or a corner moved more than ``max_move_px`` from ``corners`` (a fit that moves it this far
    is wrong)."""
    p = np.array([m for m, _ in lines])
    d = np.array([u for _, u in lines])
    p1, d1 = p[PREVIOUS], d[PREVIOUS]  # corner i: lines i - 1 and i
    A = np.empty((4, 2, 2))  # A[i] = [d1, -d2] as columns
    A[:, :, 0], A[:, :, 1] = d1, -d
    # (the cross product is np.linalg.det's value to a few ulps: only near the threshold is LAPACK's needed)
    cross = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    if np.abs(cross).min() < 2e-9 and np.any(np.abs(np.linalg.det(A)) < 1e-9):
        return None
    s = np.linalg.solve(A, (p - p1)[:, :, None])[:, 0, :]  # (4, 1): how far along d1
    out = p1 + s * d1
    if np.abs(out - corners).max() > max_move_px:
        return None
    return out


def refine_corners_undistorted(
    gray: NDArray[np.uint8],
    corners_und: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    fisheye: bool = False,
    lens_residual_px: float = 0.0,
) -> RefinedCorners | None:
    """Corners (4, 2) in undistorted pixels (an ideal pinhole with the same K), refitted on the edges,
    and their noise (pixels, per axis) measured from the scatter of the edge points about their lines.
    ``lens_residual_px``: the calibration's residual (image px, :attr:`Calibration.lens_residual_px`; 0: a
    lens known exactly), a shift of the four corners alike that no edge shows (the model is smooth over a
    marker).

    A marker's edges are straight only in the undistorted image; under barrel distortion they bend in
    the image, and corners fitted with straight lines in the image (as the AprilTag library does) are
    off by tenths of a pixel near the image edge, many times the corner noise. Here each edge is
    sampled where the straight undistorted edge falls in the image (along its undistorted normal), its
    sub-pixel gradient peaks are fitted with a straight line in undistorted pixels, and the corners are
    the crossings of adjacent lines. None where a fit fails (the caller keeps the corners it had).

    The noise: a line fitted through n points spread evenly over the middle 70 % of an edge and
    extrapolated to its end has the variance 7.1 s^2 / n across it (s: the points' scatter, pooled over
    the four edges), and a corner lies on two lines crossing at an angle phi, which adds 1 / sin(phi);
    blur and pixel noise raise s. What the scatter cannot show is added: the blur's inward pull
    (:func:`contamination_px`) and the lens residual.
    """
    return refine_markers_undistorted(gray, [corners_und], K, dist, fisheye, lens_residual_px)[0]


def refine_markers_undistorted(
    gray: NDArray[np.uint8],
    corners: list[NDArray[np.float64]],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    fisheye: bool = False,
    lens_residual_px: float = 0.0,
) -> list[RefinedCorners | None]:
    """:func:`refine_corners_undistorted` of every marker of a frame (undistorted corners (4, 2) each), in
    one pass: all their sample points laid out, sent through the lens and sampled in the image at once
    (:func:`edge_profiles.profiles`), every profile's edge placed at once, and the fits' statistics of markers with
    as many samples a side stacked. Each marker's result is what it gives alone."""
    out: list[RefinedCorners | None] = [None] * len(corners)
    plan = sampling(corners)
    if plan is None:
        return out
    # Every side's sample points through the lens, and the image along them, for all markers at once.
    sampled = edge_profiles.profiles(gray, plan, K, dist, fisheye)
    found_all, _, levels_all = place_edges(sampled.values, plan.offsets, plan.counts, plan.cells)
    # Each marker's edge points (where no edge was placed, NaN), grouped by samples a side for the fits.
    points_all = plan.bases + found_all[:, None] * plan.normals
    keep_all = np.isfinite(found_all)
    whole: dict[int, list[int]] = {}
    stats: dict[int, SideStatistics] = {}
    for k, (i, s, start) in enumerate(zip(plan.markers, plan.samples, plan.starts, strict=True)):
        keep = keep_all[start : start + 4 * s].reshape(4, s)
        kept = np.count_nonzero(keep, axis=1)
        if kept.min() < s // 2:
            continue
        if kept.min() == s:
            whole.setdefault(s, []).append(k)
        else:
            points = points_all[start : start + 4 * s].reshape(4, s, 2)
            levels = levels_all[start : start + 4 * s].reshape(4, s, 5)
            stats[i] = _side_statistics_each([q[m] for q, m in zip(points, keep, strict=True)], levels, keep)
    for s, group in whole.items():
        rows = np.concatenate([np.arange(plan.starts[k], plan.starts[k] + 4 * s) for k in group])
        batch = side_statistics(points_all[rows].reshape(-1, 4, s, 2), levels_all[rows].reshape(-1, 4, s, 5))
        for j, k in enumerate(group):
            stats[plan.markers[k]] = tuple(x[j] for x in batch)  # type: ignore[assignment]
    ids = sorted(stats)
    if ids:
        scale = dict(zip(plan.markers, sampled.scales.tolist(), strict=True))
        shifts = np.array([scale[i] * lens_residual_px for i in ids])
        got = _corners_and_noise(np.array([corners[i] for i in ids]), [stats[i] for i in ids], shifts, K, dist, fisheye)
        for i, refined in zip(ids, got, strict=True):
            out[i] = refined
    return out


def crossings_many(
    means: NDArray[np.float64], dirs: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """:func:`crossings` (without the move limit) of M markers' lines, points ``means`` and directions
    ``dirs`` (M, 4, 2): the corners (M, 4, 2) (NaN where two lines are parallel) and which are."""
    p1, d1 = means[:, PREVIOUS], dirs[:, PREVIOUS]  # corner i: lines i - 1 and i
    A = np.empty((len(means), 4, 2, 2))  # A[i] = [d1, -d2] as columns
    A[..., 0], A[..., 1] = d1, -dirs
    # (the cross product is np.linalg.det's value to a few ulps: only near the threshold is LAPACK's needed)
    cross = A[..., 0, 0] * A[..., 1, 1] - A[..., 0, 1] * A[..., 1, 0]
    parallel = np.abs(cross).min(axis=1) < 2e-9
    for k in np.flatnonzero(parallel):
        parallel[k] = bool(np.any(np.abs(np.linalg.det(A[k])) < 1e-9))
    # How far along d1, by Cramer's rule (the 2x2 systems' LAPACK solve costs more than the arithmetic).
    b = means - p1
    with np.errstate(divide="ignore", invalid="ignore"):  # parallel lines: NaN below
        s = (b[..., 0] * A[..., 1, 1] - A[..., 0, 1] * b[..., 1]) / cross
        out = p1 + s[..., None] * d1
    out[parallel] = np.nan
    return out, parallel


def _corners_and_noise(
    corners_und: NDArray[np.float64],
    stats: list[SideStatistics],
    shift_px: NDArray[np.float64],
    K: NDArray[np.float64],
    dist: NDArray[np.float64],
    fisheye: bool,
) -> list[RefinedCorners | None]:
    """The refitted corners of M markers (undistorted corners (M, 4, 2) before) where their sides' lines
    cross, and their noise, from the sides' statistics (:func:`_side_statistics_each`) and the lens
    residual's shift (M,) (undistorted px); None where lines are parallel or the corners moved too far."""
    means, dirs, ss, npts, spread, edge_levels, lag0, lag1 = (np.array([x[k] for x in stats]) for k in range(8))
    out, parallel = crossings_many(means, dirs)
    moves = np.abs(out - corners_und).max(axis=(1, 2))
    ok = ~parallel
    for k in np.flatnonzero(ok & (moves > MAX_MOVE_PX)):  # (the bend, which takes a while, only when needed)
        ok[k] = not moves[k] > MAX_MOVE_PX + BEND_ALLOWANCE * bend_px(corners_und[k], K, dist, fisheye)
    sigma, cov = corner_noise(out, (means, dirs, ss, npts, spread, edge_levels, lag0, lag1), shift_px)
    return [RefinedCorners(out[k], float(sigma[k]), cov[k]) if ok[k] else None for k in range(len(means))]


def _side_statistics_each(
    edges: list[NDArray[np.float64]], levels: NDArray[np.float64], keep: NDArray[np.bool_]
) -> SideStatistics:
    """Each side's line through its edge points ``edges`` (n_i, 2) (mean, direction), and what the corner
    noise is made of (see ``SideStatistics``; the levels: :func:`contamination_px`'s ``edge_levels``),
    from the points' ``levels`` (4, S, 5) where ``keep`` (4, S)."""
    ss, npts = 0.0, []
    lag0 = lag1 = 0.0
    spread: list[float] = []
    edge_levels: list[NDArray[np.float64]] = []
    fits = _principal_axes(edges)
    across = np.array([(-vt[0][1], vt[0][0]) for _, _, vt in fits])  # each line's normal
    for i, (e, (mean, sv, vt)) in enumerate(zip(edges, fits, strict=True)):
        ss += float(sv[1] ** 2)  # squared distances of the points from their line
        npts.append(len(e))
        centred = e - mean
        u = centred @ vt[0]
        spread.append(float(u @ u))  # sum of squared positions along the edge about the points' mean
        kept_levels = levels[i][keep[i]]
        # dark, light, window half width, how unevenly the profile settles at its two ends (a symmetric
        # ramp cut short alike at both ends moves no area); the standard errors of the three medians
        per_row = np.column_stack([kept_levels[:, :3], kept_levels[:, 3] + kept_levels[:, 4]])
        errors = 1.2533 * per_row[:, [0, 1, 3]].std(axis=0) / math.sqrt(len(per_row))
        edge_levels.append(np.concatenate([np.median(per_row, axis=0), errors]))
        r = centred @ across[i]  # signed distances from the line, in order along the edge
        lag0 += float(r @ r)
        lag1 += float(r[1:] @ r[:-1])
    means = np.array([f[0] for f in fits])
    dirs = np.array([f[2][0] for f in fits])
    return means, dirs, ss, np.array(npts, float), np.array(spread), np.array(edge_levels), lag0, lag1


def _principal_axes(
    edges: list[NDArray[np.float64]],
) -> list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]]:
    """Each point set's (n_i, 2) mean, and the singular values and right singular vectors (rows) of
    its points about it: one batched call where all have as many points (each set's result is the
    same as alone), otherwise one each."""
    if len({len(e) for e in edges}) == 1:
        stacked = np.array(edges)
        means = stacked.mean(axis=1)
        _, svs, vts = np.linalg.svd(stacked - means[:, None, :], full_matrices=False)
        return list(zip(means, svs, vts, strict=True))
    out = []
    for e in edges:
        mean = e.mean(axis=0)
        _, sv, vt = np.linalg.svd(e - mean, full_matrices=False)
        out.append((mean, sv, vt))
    return out


def _corner_covariance(
    lines: list[tuple[NDArray[np.float64], NDArray[np.float64]]],
    corners: NDArray[np.float64],
    var_px2: float,
    npts: NDArray[np.float64],
    spread: NDArray[np.float64],
    shrink_px: NDArray[np.float64] | None = None,
    shift_px: float = 0.0,
) -> NDArray[np.float64]:
    """(8, 8) covariance of the four corners (x0 y0 x1 y1 ...) that the four fitted lines place.

    Line l (through its points' mean m_l, direction d_l, normal n_l) errs by an offset a_l across it
    (variance var / n_l) and a turn b_l about m_l (variance var / sum of squared positions along it),
    independent of each other and of the other lines. A point x of the line then moves across it by
    a_l + b_l (x - m_l) . d_l, and corner k, the crossing of lines k-1 and k, by dx with
    n_{k-1} . dx and n_k . dx those two shifts. Adjacent corners share a line, so they are correlated.
    ``shrink_px`` (4,): each line's possible inward offset from blur (:func:`contamination_px`), one cause for
    all four lines, so their offsets are fully correlated in it (the quadrilateral too small).
    ``shift_px``: the standard deviation of a shift of every corner alike
    (the lens model's residual over the marker), undistorted px.
    """
    means = np.array([m for m, _ in lines])[None]
    dirs = np.array([d for _, d in lines])[None]
    shrink = None if shrink_px is None else np.asarray(shrink_px, dtype=float)[None]
    return corner_covariances(
        means, dirs, corners[None], np.array([var_px2]), npts[None], spread[None], shrink, np.array([shift_px])
    )[0]


@dataclass(frozen=True)
class RefinedCorners:
    """Corners (4, 2) refitted on the marker's edges, in undistorted pixels; ``sigma_px``: their noise
    per axis as one figure (the sigma model's); ``covariance``: (8, 8) of x0 y0 ... x3 y3 (px^2), the
    edge fits' own, corners sharing an edge correlated."""

    corners: NDArray[np.float64]
    sigma_px: float
    covariance: NDArray[np.float64]
