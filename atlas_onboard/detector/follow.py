"""Following a tracked marker from its predicted corners, without the AprilTag library.

A marker found in the previous frame is predicted in this one (its motion, the camera's turn). Near
that prediction its square's four edges are looked for along their normals: each is the rise from the
black border to the white quiet zone, and within ``REACH_CELLS`` of a cell either side of the predicted
edge no other edge of the marker rises outward (the border is one cell wide inside, the quiet zone one
cell outside). A line through each side's edge points gives the corners; the marker's whole printed
pattern is then read at its cells' centres through those corners and must match the expected bitmap
cell for cell (every cell of the black border, and the data cells but for the bit errors the library's
decoding corrects, each on its side of a threshold fitted across the marker to its black and its white
cells). Anything short of that (an edge not found within reach, a side that is not straight, a cell
that does not match, too little contrast) leaves the marker to the library's search of its region, as
before. With the camera's calibration the sides are fitted where they are straight, in undistorted
pixels, and sampled where the lens bends them in the image; the corners are then where the lens puts
the true ones (the library fits straight lines in the image, off by the lens's bend).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.detector import lens, pose, refine
from atlas_onboard.detector.backends import Detection, accepted_bit_errors
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.corner_noise import NEXT
from atlas_onboard.detector.edge_profile import MIN_CONTRAST
from atlas_onboard.detector.edge_sampling import sample_places
from atlas_onboard.detector.families import family

MIN_CELL_PX = 3.0  # narrower cells are left to the library: their centres are not read clear of their edges
REACH_CELLS = 0.8  # how far (in cells) from its predicted place an edge is looked for, either side
SAMPLES_PER_SIDE = 8  # edge points on each side, spread between 15 % and 85 % of it (clear of the corners)
STEPS = 10  # samples along a side's normal on each side of the predicted edge, over the reach and a step more
LINE_TOLERANCE_PX = 1.0  # an edge point farther than this from its side's line is left out of the fit
BATCH = 256  # markers sampled at once at most (OpenCV's remap takes fewer than 32767 rows)
FINE_HALF_PX = 2.0  # the edges then placed within this of the lines found, at a quarter pixel:
FINE_STEPS = 8  # samples each way over it
FINE_SAMPLES_PER_SIDE = 16  # edge points on each side in that pass


@dataclass(frozen=True)
class Pattern:
    """A marker's cells as the detected square shows them, and what reading them needs."""

    white: NDArray[np.bool_]  # (cells * cells,) row by row: True where white
    to_white: NDArray[np.float64]  # (N, N): the cells' values to the plane fitted to the white cells, at every cell
    to_black: NDArray[np.float64]  # (N, N): the same for the black cells
    bit_errors: int  # data cells that may be read wrong (:func:`backends.accepted_bit_errors`)


_patterns: dict[tuple[str, int], Pattern | None] = {}
_centres: dict[int, NDArray[np.float64]] = {}


def _cell_centres(cells: int) -> NDArray[np.float64]:
    """The cells' centres (N, 3) in cell units, row by row, homogeneous."""
    if cells not in _centres:
        j, i = np.mgrid[0:cells, 0:cells]
        _centres[cells] = np.stack([i.ravel() + 0.5, j.ravel() + 0.5, np.ones(cells * cells)], axis=1)
    return _centres[cells]


def pattern(family_name: str, marker_id: int) -> Pattern | None:
    """Marker ``marker_id``'s pattern; None for a family whose pattern reaches outside the detected square (its
    square's outer neighbours are data cells, not a quiet zone) or with too few cells of a colour to fit a plane."""
    key = (family_name, marker_id)
    if key not in _patterns:
        fam = family(family_name)
        _patterns[key] = None
        if not fam.total_cells or fam.total_cells == fam.cells:
            white = (fam.bitmap(marker_id, cell_px=1, quiet_zone_cells=0) > 127).ravel()
            A = _cell_centres(fam.cells)
            if white.sum() >= 3 and (~white).sum() >= 3:
                to = [A @ np.linalg.pinv(A[sel]) @ np.eye(len(A))[sel] for sel in (white, ~white)]
                _patterns[key] = Pattern(white, to[0], to[1], accepted_bit_errors(family_name))
    return _patterns[key]


def _to_image(pts: NDArray[np.float64], cal: Calibration | None) -> NDArray[np.float64]:
    """Undistorted pixels (..., 2) where the lens puts them in the image (the same without a lens)."""
    if cal is None:
        return pts
    flat = pts.reshape(-1, 2)
    return lens.distort_uv(flat[:, 0], flat[:, 1], cal.K, cal.dist, cal.fisheye).reshape(pts.shape)


def _profiles(
    gray: NDArray[np.uint8], u: NDArray[np.float64], v: NDArray[np.float64], cal: Calibration | None
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """The image at the points whose undistorted pixels are ``u``, ``v`` (M, ..., K), where the lens ``cal``
    puts them, bilinear (0 outside the image); and per marker whether all lie inside it."""
    shape = u.shape
    if cal is not None:
        x, y = lens.distort_columns(u.ravel(), v.ravel(), cal.K, cal.dist, cal.fisheye)
    else:
        x, y = u.ravel(), v.ravel()
    h, w = gray.shape[:2]
    xm, ym = x.reshape(shape[0], -1), y.reshape(shape[0], -1)
    inside = (xm.min(axis=1) >= 0) & (ym.min(axis=1) >= 0) & (xm.max(axis=1) <= w - 1) & (ym.max(axis=1) <= h - 1)
    # Rows of one profile each (OpenCV's maps take fewer than 32767 columns).
    mx, my = x.reshape(-1, shape[-1]).astype(np.float32), y.reshape(-1, shape[-1]).astype(np.float32)
    out = cv2.remap(gray, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out.reshape(shape).astype(np.float64), inside


def _lines(x: NDArray[np.float64], y: NDArray[np.float64], ok: NDArray[np.bool_]) -> tuple[NDArray[np.float64], ...]:
    """Least-squares lines through the ``ok`` points ``x``, ``y`` (..., S): their centroid (x, y), unit
    direction (x, y) and how many points each has."""
    wt = ok.astype(np.float64)
    count = wt.sum(axis=-1)
    inv = 1.0 / np.maximum(count, 1)
    mx, my = (x * wt).sum(axis=-1) * inv, (y * wt).sum(axis=-1) * inv
    qx, qy = (x - mx[..., None]) * wt, (y - my[..., None]) * wt
    sxx, syy, sxy = (qx * qx).sum(axis=-1), (qy * qy).sum(axis=-1), (qx * qy).sum(axis=-1)
    angle = 0.5 * np.arctan2(2 * sxy, sxx - syy)  # the scatter's principal direction
    return mx, my, np.cos(angle), np.sin(angle), count


def _refit(
    gray: NDArray[np.uint8],
    quad: NDArray[np.float64],
    half_px: NDArray[np.float64],
    steps: int,
    samples: int,
    cal: Calibration | None,
    fine: bool,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Per marker (``quad`` (M, 4, 2), undistorted pixels: the sides are straight there, and each point
    is sampled where the lens ``cal`` puts it in the image): the corners where the lines through its
    sides' edge points cross, each edge point the rise (black border to white quiet zone) along the
    side's outward normal within ``half_px`` (M,) of the side, sampled ``steps`` times each way (and a
    step more); with ``samples`` points a side. Coarse (steps of about a pixel): the strongest rise
    within reach, not at its ends; ``fine`` (a quarter pixel): the centroid of the squared rise. Whether
    all four sides were found."""
    t, k_steps = sample_places(samples), np.arange(-steps, steps + 1, dtype=np.float64)
    dx, dy = quad[:, NEXT, 0] - quad[..., 0], quad[:, NEXT, 1] - quad[..., 1]  # each side (M, 4)
    length = np.sqrt(dx * dx + dy * dy)
    inv = 1.0 / np.maximum(length, 1e-9)
    nx, ny = -dy * inv, dx * inv
    centre = quad.mean(axis=1)
    flip = np.where(nx * (centre[:, None, 0] - quad[..., 0]) + ny * (centre[:, None, 1] - quad[..., 1]) > 0, -1.0, 1.0)
    nx, ny = nx * flip, ny * flip  # pointing out of the marker
    offsets = k_steps[None, :] * (half_px / (steps - 1))[:, None]  # (M, K)
    bx = quad[..., 0, None] + t * dx[..., None]  # (M, 4, S)
    by = quad[..., 1, None] + t * dy[..., None]
    along = offsets[:, None, None, :]
    values, inside = _profiles(
        gray, bx[..., None] + along * nx[..., None, None], by[..., None] + along * ny[..., None, None], cal
    )
    found = (length.min(axis=1) >= 8) & inside
    rise = values[..., 2:] - values[..., :-2]  # at offsets[1:-1]
    k = np.argmax(rise, axis=-1)
    ok = (k > 0) & (k < rise.shape[-1] - 1) & (rise.max(axis=-1) > 0)  # a rise within reach, not at its ends
    if fine:
        weight = np.maximum(rise, 0.0) ** 2
        s = (weight * along[..., 1:-1]).sum(axis=-1) / np.maximum(weight.sum(axis=-1), 1e-9)
    else:
        s = offsets[:, 1:-1][np.arange(len(quad))[:, None, None], k]
    ex, ey = bx + s * nx[..., None], by + s * ny[..., None]  # (M, 4, S)
    mx, my, ux, uy, _ = _lines(ex, ey, ok)
    off = np.abs((ey - my[..., None]) * ux[..., None] - (ex - mx[..., None]) * uy[..., None])
    ok &= off <= LINE_TOLERANCE_PX  # points off their side's line left out, and the lines fitted again
    mx, my, ux, uy, count = _lines(ex, ey, ok)
    found &= (count >= samples // 2 + 1).all(axis=1)
    corners, parallel = refine.crossings_many(np.stack([mx, my], axis=-1), np.stack([ux, uy], axis=-1))
    return corners, found & ~parallel


def _corners(
    gray: NDArray[np.uint8], predicted: NDArray[np.float64], reach_px: NDArray[np.float64], cal: Calibration | None
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Per marker (``predicted`` (M, 4, 2), undistorted pixels): its corners there, found near the prediction
    (the edges within ``reach_px`` (M,)) and then placed to a fraction of a pixel; and whether they were found."""
    coarse, found = _refit(gray, predicted, reach_px, STEPS, SAMPLES_PER_SIDE, cal, fine=False)
    found &= np.abs(coarse - predicted).max(axis=(1, 2)) <= reach_px * math.sqrt(2) + LINE_TOLERANCE_PX
    start = np.where(found[:, None, None], coarse, predicted)
    half = np.full(len(predicted), FINE_HALF_PX)
    placed, ok = _refit(gray, start, half, FINE_STEPS, FINE_SAMPLES_PER_SIDE, cal, fine=True)
    found &= ok & (np.abs(placed - coarse).max(axis=(1, 2)) <= FINE_HALF_PX)
    return placed, found


def _matching(
    gray: NDArray[np.uint8], corners: NDArray[np.float64], patterns: list[Pattern], cal: Calibration | None
) -> NDArray[np.bool_]:
    """Per marker (``corners`` (M, 4, 2), undistorted pixels, OpenCV order; the cells' centres read where the
    lens ``cal`` puts them): whether it shows its pattern: every cell's centre on
    its side of a threshold halfway between planes fitted to the black and to the white cells, with at least
    ``MIN_CONTRAST`` between them everywhere; every cell of the black border, and all but at most the
    pattern's ``bit_errors`` of the data cells (the errors the library's decoding corrects)."""
    M = len(corners)
    cells = math.isqrt(len(patterns[0].white))
    square = np.array([[0, 0], [cells, 0], [cells, cells], [0, cells]], np.float32)
    H = np.array([cv2.getPerspectiveTransform(square, c.astype(np.float32)) for c in corners])
    h = np.einsum("mij,nj->mni", H, _cell_centres(cells))
    centres = h[..., :2] / h[..., 2:]
    values, inside = _profiles(gray, centres[..., 0], centres[..., 1], cal)  # (M, N)
    white_plane = np.einsum("mij,mj->mi", np.array([p.to_white for p in patterns]), values)
    black_plane = np.einsum("mij,mj->mi", np.array([p.to_black for p in patterns]), values)
    w = np.array([p.white for p in patterns])
    wrong = ((values > 0.5 * (white_plane + black_plane)) != w).reshape(M, cells, cells)
    border = wrong[:, [0, -1], :].any(axis=(1, 2)) | wrong[:, :, [0, -1]].any(axis=(1, 2))
    data_wrong = wrong[:, 1:-1, 1:-1].sum(axis=(1, 2))
    enough = (white_plane - black_plane).min(axis=1) >= MIN_CONTRAST
    return inside & enough & ~border & (data_wrong <= np.array([p.bit_errors for p in patterns]))


def follow(
    gray: NDArray[np.uint8],
    predicted: dict[int, tuple[str, NDArray[np.float64]]],
    calibration: Calibration | None = None,
) -> dict[int, Detection]:
    """The markers found near their predicted corners (``predicted``: id -> (family, corners (4, 2)), image
    pixels); the others are left to the library. With a ``calibration`` whose lens distorts, the sides are
    fitted straight where they are straight, in undistorted pixels, and sampled where the lens bends them."""
    cal = calibration if calibration is not None and np.any(calibration.dist) else None
    groups: dict[int, list[tuple[int, str, NDArray[np.float64], Pattern]]] = {}
    for marker_id, (family_name, corners) in predicted.items():
        p = pattern(family_name, marker_id)
        if p is not None:
            groups.setdefault(len(p.white), []).append((marker_id, family_name, corners, p))
    out: dict[int, Detection] = {}
    batches = [(n, g[i : i + BATCH]) for n, g in groups.items() for i in range(0, len(g), BATCH)]
    for n, group in batches:  # the markers of one size of pattern at once
        P = np.array([g[2] for g in group], np.float64)
        cells = math.isqrt(n)
        cell_px = np.linalg.norm(P - P[:, NEXT], axis=2).mean(axis=1) / cells  # in the image
        if cal is not None:
            P = pose.undistort(P.reshape(-1, 2), cal.K, cal.dist, cal.fisheye).reshape(P.shape)
        reach = REACH_CELLS * np.linalg.norm(P - P[:, NEXT], axis=2).mean(axis=1) / cells
        corners, found = _corners(gray, P, reach, cal)
        idx = np.flatnonzero(found & (cell_px >= MIN_CELL_PX))
        if len(idx) == 0:
            continue
        same = _matching(gray, corners[idx], [group[k][3] for k in idx], cal)
        image = _to_image(corners[idx[same]], cal)
        for k, c in zip(idx[same], image, strict=True):
            out[group[k][0]] = Detection(group[k][0], group[k][1], c)
    return out
