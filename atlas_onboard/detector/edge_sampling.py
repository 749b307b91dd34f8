"""Where the corner refit (:mod:`atlas_onboard.detector.refine`) samples a frame's marker edges: the points
along each side, the search across it, laid out for all markers of a frame at once."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.detector.corner_noise import NEXT

# Edge points a side: one a pixel over the sampled 70 % of the shortest side (closer ones share pixels, so
# their errors are not independent), between these bounds (enough for the pixel grid's pattern along an
# edge to average out; no more than that costs).
MIN_SAMPLES_PER_SIDE, MAX_SAMPLES_PER_SIDE = 12, 24
HALF_WIDTH_PX = 3.0  # search this far on each side of the current edge
STEP_PX = 0.25


@dataclass(frozen=True)
class Sampling:
    """Where the edges of a frame's markers are sampled, one row per (marker, side, sample point) in that
    order: each row's base point on the side ``bases`` (R, 2), the side's outward unit normal ``normals``
    (R, 2), the offsets along it ``offsets`` (R, width) (a side with a shorter search than the longest of
    the frame repeats its outermost offset), the side's count of offsets ``counts`` (R,) and its cell
    across the edge ``cells`` (R,) (an eighth of its depth). ``markers``: the sampled markers (their index
    in the frame), ``samples``: each one's sample points a side, ``starts``: each one's first row."""

    markers: list[int]
    samples: list[int]
    starts: list[int]
    bases: NDArray[np.float64]
    normals: NDArray[np.float64]
    offsets: NDArray[np.float64]
    counts: NDArray[np.int64]
    cells: NDArray[np.float64]


def sampling(corners: list[NDArray[np.float64]]) -> Sampling | None:
    """Where the edges of the markers with undistorted corners ``corners`` ((4, 2) each) are sampled (the
    values :func:`atlas_onboard.detector.refine.sides` and its search give each marker alone, computed for
    all at once); None if
    no marker has every side long enough to fit."""
    if not corners:
        return None
    C = np.array(corners, dtype=np.float64).reshape(-1, 4, 2)
    vectors = C[:, NEXT] - C
    # Each side's length as :func:`sides` has it (np.dot's value, which may differ from the plain sum of
    # squares in its last bit), and as the sample count has it (the plain one).
    length = np.sqrt([d.dot(d) for d in vectors.reshape(-1, 2)]).reshape(-1, 4)
    fit = np.flatnonzero((length >= 8).all(axis=1))
    if not len(fit):
        return None
    C, vectors, length = C[fit], vectors[fit], length[fit]
    vx, vy = vectors[..., 0], vectors[..., 1]
    plain = np.sqrt(vx * vx + vy * vy)
    n = np.empty_like(vectors)
    n[..., 0], n[..., 1] = -vectors[..., 1] / length, vectors[..., 0] / length  # (d / length turned a quarter)
    inward = C.mean(axis=1)[:, None, :] - C
    n[n[..., 0] * inward[..., 0] + n[..., 1] * inward[..., 1] > 0] *= -1  # normals pointing out of the marker
    # Inside the black border (one cell deep) lie the data cells, outside it one white cell then the
    # background: search 0.8 of a cell each way, a cell being at least an eighth of the marker's depth
    # across this edge (8 cells across the black border for tag36h11, 6 for 4x4 ArUco).
    nx, ny, ax, ay = n[..., 0], n[..., 1], C[..., 0], C[..., 1]
    far = [C[:, [(i + k) % 4 for i in range(4)]] for k in (2, 3)]
    depth = np.minimum(*(np.abs(nx * (c[..., 0] - ax) + ny * (c[..., 1] - ay)) for c in far))
    half = np.minimum(np.maximum(0.1 * depth, 1.0), 2 * HALF_WIDTH_PX)  # np.clip's value
    # np.arange(-half, half + 1e-9, STEP_PX)'s values: its length, and start + i * its first step.
    counts = np.ceil(((half + 1e-9) - -half) / STEP_PX).astype(np.int64)
    delta = (-half + STEP_PX) - -half
    k = np.minimum(np.arange(int(counts.max())), (counts - 1)[..., None])  # beyond a side's count: its last
    offsets = -half[..., None] + k * delta[..., None]  # (M, 4, width)
    # Edge points a side: one a pixel over the sampled 70 % of the shortest side.
    samples = np.minimum(np.maximum(0.7 * plain.min(axis=1), MIN_SAMPLES_PER_SIDE), MAX_SAMPLES_PER_SIDE)
    samples = samples.astype(np.int64)  # int(np.clip(...))
    ts = np.concatenate([np.tile(sample_places(int(s)), 4) for s in samples])  # (R,)
    per_side = np.repeat(samples, 4)  # rows of each (marker, side)

    def side_rows(a: NDArray) -> NDArray:
        """A per-side array (M, 4, ...) repeated over each side's rows (R, ...)."""
        return np.repeat(a.reshape(len(per_side), *a.shape[2:]), per_side, axis=0)

    bases = side_rows(C) + ts[:, None] * side_rows(vectors)
    starts = np.concatenate([[0], np.cumsum(4 * samples)[:-1]])
    return Sampling(
        fit.tolist(),
        samples.tolist(),
        starts.tolist(),
        bases,
        side_rows(n),
        side_rows(offsets),
        side_rows(counts),
        side_rows(depth / 8.0),
    )


@functools.lru_cache(maxsize=32)
def sample_places(samples: int) -> NDArray[np.float64]:
    """Where along a side its edge is sampled (fractions of the side), read-only."""
    ts = np.linspace(0.15, 0.85, samples)
    ts.flags.writeable = False
    return ts
