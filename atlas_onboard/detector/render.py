"""A renderer of markers seen by a camera, for tests and the simulator.

Each marker is drawn with its white quiet zone, at sub-pixel accuracy: every output pixel is the
average of ``supersample`` x ``supersample`` samples, each mapped through the lens distortion and
the marker plane's homography into the marker bitmap. Only a region around each marker is rendered.
The background is a smooth random texture; motion blur and pixel noise can be added.

A rolling shutter exposes each row at its own instant: a :class:`MarkerView` with ``rows`` gives the
marker's pose at each row's instant, and every sample is mapped with the pose of its own row
(interpolated between rows, which a camera's motion over one row's 50 us changes by far less than
a thousandth of a pixel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform

from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.families import family
from atlas_onboard.errors import AtlasError

CELL_PX = 16


Camera = Calibration
"""The camera the renderer draws for: a calibration (pinhole intrinsics in OpenCV's pixel-centre
convention and distortion k1 k2 p1 p2 k3; the fisheye model is not rendered)."""


def _pinhole(camera: Camera) -> None:
    if camera.fisheye:
        raise AtlasError("the renderer draws pinhole cameras (distortion k1 k2 p1 p2 k3), not the fisheye model")


@dataclass(frozen=True)
class MarkerView:
    """A marker to draw: its family, id, size and its pose in the camera's optical frame."""

    family: str
    marker_id: int
    size_m: float
    T_camera_marker: RigidTransform
    rows: NDArray[np.float64] | None = None
    """Rolling shutter: (height, 4, 4) T_camera_marker at the instant each image row is exposed (None: every
    row at ``T_camera_marker``, a global shutter)."""


ROW_BOX_SAMPLES = 17  # poses of a rolling-shutter marker projected to bound its box (rows evenly spaced)


def _rows_at(rows: NDArray[np.float64], y_px: NDArray[np.float64]) -> NDArray[np.float64]:
    """The poses (len(y_px), 4, 4) at pixel rows ``y_px`` (pixel-centre convention, any real value):
    linear between the two nearest rows, the first or last beyond them."""
    y = np.clip(np.asarray(y_px, dtype=float), 0.0, len(rows) - 1.0)
    lo = np.minimum(np.floor(y).astype(int), len(rows) - 2) if len(rows) > 1 else np.zeros(len(y), int)
    f = (y - lo)[:, None, None]
    hi = np.minimum(lo + 1, len(rows) - 1)
    return (1.0 - f) * rows[lo] + f * rows[hi]


_bitmaps: dict[tuple[str, int], NDArray[np.float32]] = {}


def _bitmap(name: str, marker_id: int) -> NDArray[np.float32]:
    key = (name, marker_id)
    if key not in _bitmaps:
        _bitmaps[key] = family(name).bitmap(marker_id, CELL_PX).astype(np.float32)
    return _bitmaps[key]


_backgrounds: dict[tuple[int, int, int], NDArray[np.float32]] = {}


BACKGROUND_STYLES = ("smooth", "concrete")


def background(
    camera: Camera, seed: int = 0, mean: float = 140.0, contrast: float = 40.0, style: str = "smooth"
) -> NDArray[np.float32]:
    """A random texture of the camera's size (cached: made once per seed and style).

    ``smooth``: a smooth mottled surface. ``concrete``: a floor as a camera sees one (see
    :func:`concrete_texture`), which gives the detector edges, corners and false quads to reject.
    """
    if style not in BACKGROUND_STYLES:
        raise ValueError(f"expected a background style in {BACKGROUND_STYLES}, got {style!r}")
    key = (camera.width_px, camera.height_px, seed, style)
    if key not in _backgrounds:
        if len(_backgrounds) > 8:
            _backgrounds.clear()
        if style == "concrete":
            _backgrounds[key] = concrete_texture(camera.width_px, camera.height_px, seed)
        else:
            _backgrounds[key] = _texture(camera, seed, mean, contrast)
    return _backgrounds[key].copy()


def concrete_texture(
    width_px: int, height_px: int, seed: int = 0, px_per_m: float = 500.0, mean: float = 128.0
) -> NDArray[np.float32]:
    """A grey image (height_px, width_px) of a worn concrete floor seen at ``px_per_m`` pixels per metre.

    Mottling at several scales, aggregate speckle, dark and light stains with soft edges, saw-cut joints
    (straight dark lines every 1-1.5 m, slightly irregular), scuffs and tyre marks (short dark strokes) and
    a few bright spots: the edges, corners and near-quads a real floor gives a detector. Values in [15, 240].
    """
    rng = np.random.default_rng(seed)
    h, w = height_px, width_px
    img = np.zeros((h, w), np.float32)
    # Mottling: sums of upsampled noise at 0.5 m, 10 cm and 2 cm.
    for scale_m, amp in ((0.5, 18.0), (0.1, 10.0), (0.02, 6.0)):
        cell = max(int(scale_m * px_per_m), 2)
        small = rng.normal(0.0, 1.0, (h // cell + 3, w // cell + 3)).astype(np.float32)
        img += (
            amp
            * cv2.resize(small, (small.shape[1] * cell, small.shape[0] * cell), interpolation=cv2.INTER_CUBIC)[:h, :w]
        )
    # Aggregate: fine speckle, a little blurred.
    img += cv2.GaussianBlur(rng.normal(0.0, 7.0, (h, w)).astype(np.float32), (0, 0), 0.7)
    area_m2 = w * h / px_per_m**2
    # Stains: soft-edged blobs, darker (oil, water) or lighter (dust).
    stains = np.zeros((h, w), np.float32)
    for _ in range(int(rng.poisson(6.0 * area_m2)) + 2):
        axes = (int(rng.uniform(0.03, 0.3) * px_per_m), int(rng.uniform(0.02, 0.2) * px_per_m))
        centre = (int(rng.uniform(0, w)), int(rng.uniform(0, h)))
        cv2.ellipse(stains, centre, axes, rng.uniform(0, 180), 0, 360, float(rng.choice([-1.0, 0.6])), -1)
    img += 30.0 * cv2.GaussianBlur(stains, (0, 0), max(0.015 * px_per_m, 1.0))
    # Saw-cut joints: dark lines in a grid every 1-1.5 m, each wavering by a pixel or two.
    spacing = rng.uniform(1.0, 1.5) * px_per_m
    angle = rng.uniform(0.0, np.pi)
    d = np.array([np.cos(angle), np.sin(angle)])
    joints = np.zeros((h, w), np.float32)
    diag = float(np.hypot(w, h))
    for direction in (d, np.array([-d[1], d[0]])):
        normal = np.array([-direction[1], direction[0]])
        offset = rng.uniform(0, spacing)
        for k in range(-int(diag / spacing) - 1, int(diag / spacing) + 2):
            c = np.array([w / 2, h / 2]) + normal * (offset + k * spacing)
            a, b = c - direction * diag, c + direction * diag
            width = max(round(0.004 * px_per_m), 1)
            cv2.line(joints, tuple(int(v) for v in a), tuple(int(v) for v in b), 1.0, width, cv2.LINE_AA)
    img -= 55.0 * cv2.GaussianBlur(joints, (0, 0), 0.6)
    # Scuffs and tyre marks: short dark strokes, some curved.
    scuffs = np.zeros((h, w), np.float32)
    for _ in range(int(rng.poisson(25.0 * area_m2)) + 3):
        p = np.array([rng.uniform(0, w), rng.uniform(0, h)])
        heading = rng.uniform(0, 2 * np.pi)
        length = rng.uniform(0.02, 0.25) * px_per_m
        turn = rng.normal(0.0, 1.5) / max(length, 1.0)
        pts = []
        for s in np.linspace(0.0, length, 12):
            pts.append(p + s * np.array([np.cos(heading + turn * s), np.sin(heading + turn * s)]))
        width = int(rng.integers(1, max(int(0.01 * px_per_m), 2) + 1))
        cv2.polylines(scuffs, [np.array(pts, np.int32)], False, float(rng.uniform(0.3, 1.0)), width, cv2.LINE_AA)
    img -= 45.0 * cv2.GaussianBlur(scuffs, (0, 0), 0.8)
    # Bright flecks: exposed aggregate, paint drops.
    flecks = (rng.random((h, w)) < 2e-4).astype(np.float32)
    img += 60.0 * cv2.GaussianBlur(flecks, (0, 0), 1.0) * 6.0
    return np.clip(mean + img, 15.0, 240.0).astype(np.float32)


def _texture(camera: Camera, seed: int, mean: float, contrast: float) -> NDArray[np.float32]:
    rng = np.random.default_rng(seed)
    small = rng.normal(0.0, 1.0, (camera.height_px // 16 + 2, camera.width_px // 16 + 2)).astype(np.float32)
    tex = cv2.resize(small, (camera.width_px, camera.height_px), interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.normal(0.0, 0.3, (camera.height_px, camera.width_px)).astype(np.float32), (0, 0), 1.0)
    return np.clip(mean + contrast * (tex + fine), 20, 235).astype(np.float32)


def _project(camera: Camera, pts_cam: NDArray[np.float64]) -> NDArray[np.float64]:
    _pinhole(camera)
    pts = np.ascontiguousarray(pts_cam, dtype=np.float64).reshape(-1, 1, 3)
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), camera.K, camera.dist)
    return px.reshape(-1, 2)


GRID_STEP = 4  # the lens undistortion is computed exactly on every GRID_STEP-th sample, interpolated between
# How far the rendered lens may be from its model (px): a bound on the error of the interpolated undistortion
# (GRID_STEP), which a simulated camera's calibration states as its reprojection error.
LENS_RESIDUAL_PX = 0.002

_grids: dict[tuple[object, ...], NDArray[np.float64]] = {}


def _undistorted_grid(camera: Camera, supersample: int) -> NDArray[np.float64]:
    """Normalized image coordinates (rows, cols, 2) of every ``GRID_STEP``-th sample of the whole image.

    Sample k (along x) sits at pixel (k + 0.5) / supersample - 0.5 (pixel-centre convention); grid
    point j is sample j * GRID_STEP. Computed once per camera and supersampling (cached), so that a
    frame costs no undistortion; :func:`draw_marker` starts each region on a grid point.
    """
    _pinhole(camera)
    key = (camera.width_px, camera.height_px, camera.K.tobytes(), np.asarray(camera.dist).tobytes(), supersample)
    grid = _grids.get(key)
    if grid is None:
        if len(_grids) > 8:
            _grids.clear()
        s, step = supersample, GRID_STEP
        gx = (np.arange(0, camera.width_px * s + 2 * step, step) + 0.5) / s - 0.5
        gy = (np.arange(0, camera.height_px * s + 2 * step, step) + 0.5) / s - 0.5
        pts = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
        norm = cv2.undistortPoints(pts, camera.K, camera.dist, None, None, criteria=crit)
        grid = norm.reshape(len(gy), len(gx), 2).astype(np.float64)
        _grids[key] = grid
    return grid


def prepare(camera: Camera, supersample: int = 4) -> None:
    """Compute what :func:`render` caches for this camera now (a simulated camera calls it before its
    first frame, so that the first frame is not late)."""
    _undistorted_grid(camera, supersample)


def _marker_box(camera: Camera, view: MarkerView) -> tuple[int, int, int, int] | None:
    """The pixel box (x0, y0, x1, y1, inclusive) the marker with its quiet zone covers, or None."""
    fam = family(view.family)
    h = view.size_m * fam.printed_cells / fam.cells / 2
    outline = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    if view.rows is None:
        M = view.T_camera_marker.as_matrix()
        pts = outline @ M[:3, :3].T + M[:3, 3]
    else:  # every row's pose could draw some of it: the union of the outlines at poses across the frame
        Ms = view.rows[np.linspace(0, len(view.rows) - 1, ROW_BOX_SAMPLES).round().astype(int)]
        pts = (np.einsum("kij,nj->kni", Ms[:, :3, :3], outline) + Ms[:, None, :3, 3]).reshape(-1, 3)
    if np.any(pts[:, 2] <= 0.01):
        return None
    px = _project(camera, pts)
    x0, y0 = np.floor(px.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 2
    x0, y0 = max(int(x0), 0), max(int(y0), 0)
    x1, y1 = min(int(x1), camera.width_px - 1), min(int(y1), camera.height_px - 1)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def draw_marker(
    img: NDArray[np.float32], camera: Camera, view: MarkerView, supersample: int = 4
) -> tuple[int, int, int, int] | None:
    """Paint one marker into ``img`` in place; the pixel box it covers, or None if it is behind the
    camera or out of the image."""
    box = _marker_box(camera, view)
    if box is None:
        return None
    bmp = _bitmap(view.family, view.marker_id)
    fam = family(view.family)
    n_px = bmp.shape[0]  # bitmap side in pixels, quiet zone included
    side_m = view.size_m * fam.printed_cells / fam.cells  # printed size with the quiet zone
    h = side_m / 2
    s, step = supersample, GRID_STEP
    # Start the region on a point of the cached grid: sample 0 of the region is global sample x0 * s,
    # a grid point when x0 * s is a multiple of the step.
    align = step // math.gcd(step, s)
    x0, y0, x1, y1 = box
    x0, y0 = x0 - x0 % align, y0 - y0 % align
    w, hgt = (x1 - x0 + 1) * s, (y1 - y0 + 1) * s
    # Distortion is smooth: the exact undistortion on every 4th sample, interpolated, is accurate to
    # well under 0.01 px.
    j0, i0 = x0 * s // step, y0 * s // step
    nx, ny = len(range(0, w + step, step)), len(range(0, hgt + step, step))
    norm = _undistorted_grid(camera, s)[i0 : i0 + ny, j0 : j0 + nx]
    # Ray through each sample hits the marker plane: solve in the marker frame.
    rays = np.concatenate([norm, np.ones((*norm.shape[:2], 1))], axis=-1)  # camera frame directions
    if view.rows is None:
        # The stored matrix (a rigid one already): scipy's .rotation would orthonormalize it again.
        M = view.T_camera_marker.as_matrix()
        R, t = M[:3, :3], M[:3, 3]
        rays_m = rays @ R  # = R^T ray, in marker frame
        origin_m = -R.T @ t
        lam = -origin_m[2] / rays_m[..., 2]
        hit = origin_m[None, None, :2] + lam[..., None] * rays_m[..., :2]
    else:  # each grid row with the pose of its pixel row (grid row i is sample row i * step)
        Ms = _rows_at(view.rows, ((i0 + np.arange(len(norm))) * step + 0.5) / s - 0.5)
        R, t = Ms[:, :3, :3], Ms[:, :3, 3]
        rays_m = np.einsum("ijk,ikl->ijl", rays, R)  # = R_i^T ray, in marker frame
        origin_m = -np.einsum("ikl,ik->il", R, t)
        lam = -origin_m[:, None, 2] / rays_m[..., 2]
        hit = origin_m[:, None, :2] + lam[..., None] * rays_m[..., :2]
    # Marker (x right, y up) -> bitmap pixel coordinates (pixel-centre convention).
    u = (hit[..., 0] + h) / side_m * n_px - 0.5
    v = (h - hit[..., 1]) / side_m * n_px - 0.5
    valid = lam > 0
    u[~valid] = -1e6
    # Interpolate the coarse grid to every sample: sample k of the region sits at k / step on it.
    ku, kv = np.meshgrid((np.arange(w) / step).astype(np.float32), (np.arange(hgt) / step).astype(np.float32))
    map_u = cv2.remap(u.astype(np.float32), ku, kv, cv2.INTER_LINEAR)
    map_v = cv2.remap(v.astype(np.float32), ku, kv, cv2.INTER_LINEAR)
    inside = (map_u >= -0.5) & (map_u <= n_px - 0.5) & (map_v >= -0.5) & (map_v <= n_px - 0.5)
    samples = cv2.remap(bmp, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    region = img[y0 : y1 + 1, x0 : x1 + 1]
    under = cv2.resize(region, (w, hgt), interpolation=cv2.INTER_NEAREST)
    mixed = np.where(inside, samples, under)
    region[:] = cv2.resize(mixed, (x1 - x0 + 1, y1 - y0 + 1), interpolation=cv2.INTER_AREA)
    return box


def render(
    camera: Camera,
    views: list[MarkerView],
    *,
    seed: int = 0,
    background_seed: int = 0,
    noise_sigma: float = 0.0,
    blur_px: tuple[float, float] = (0.0, 0.0),
    supersample: int = 4,
    background_style: str = "smooth",
) -> NDArray[np.uint8]:
    """A grey image of the markers (drawn far to near) over a textured background.

    ``blur_px`` is the motion of the image during the exposure (dx, dy in pixels): a linear blur.
    ``background_style``: see :func:`background`.
    """
    img = background(camera, background_seed, style=background_style)
    boxes = []
    for view in sorted(views, key=lambda v: -float(np.linalg.norm(v.T_camera_marker.translation))):
        box = draw_marker(img, camera, view, supersample)
        if box is not None:
            boxes.append(box)
    length = float(np.hypot(*blur_px))
    if length >= 0.5:
        k = int(np.ceil(length)) * 2 + 1
        kernel = np.zeros((k, k), np.float32)
        c = k // 2
        n = max(int(np.ceil(length * 4)), 2)
        for a in np.linspace(-0.5, 0.5, n):
            kernel[round(c + a * blur_px[1]), round(c + a * blur_px[0])] += 1.0
        kernel /= kernel.sum()
        # The background is a smooth texture that blur hardly changes: only the markers' regions
        # (grown by the blur's reach, merged where they overlap) are blurred, each from the whole image.
        height, width = img.shape[:2]
        grown = [
            (max(b[0] - k, 0), max(b[1] - k, 0), min(b[2] + k, width - 1), min(b[3] + k, height - 1)) for b in boxes
        ]
        if background_style != "smooth":  # a textured floor moves in the image too: blur all of it
            grown = [(0, 0, width - 1, height - 1)]
        blurred = img.copy()
        for x0, y0, x1, y1 in _merged(grown):
            # Source rows and columns k beyond the region (or the image border, replicated).
            sx0, sy0, sx1, sy1 = max(x0 - k, 0), max(y0 - k, 0), min(x1 + k, width - 1), min(y1 + k, height - 1)
            src = img[sy0 : sy1 + 1, sx0 : sx1 + 1]  # at the image border, replicated as before
            out = cv2.filter2D(src, -1, kernel, borderType=cv2.BORDER_REPLICATE)
            blurred[y0 : y1 + 1, x0 : x1 + 1] = out[y0 - sy0 : y1 - sy0 + 1, x0 - sx0 : x1 - sx0 + 1]
        img = blurred
    # Round to the nearest grey level (half to even) and saturate to 0..255, as
    # np.clip(np.rint(img), 0, 255): with noise, in the same pass as the sum.
    if noise_sigma > 0:
        noise = np.empty(img.shape, np.float32)
        cv2.setRNGSeed(seed)
        cv2.randn(noise, 0.0, noise_sigma)
        return cv2.add(img, noise, dtype=cv2.CV_8U)
    # convertScaleAbs rounds and saturates the absolute value: the maximum drops negatives first.
    np.maximum(img, 0.0, out=img)
    return cv2.convertScaleAbs(img)


def _merged(boxes: list[tuple[int, int, int, int]]) -> list[tuple[int, int, int, int]]:
    """Boxes (x0, y0, x1, y1, inclusive) merged into disjoint ones: overlapping boxes become their union."""
    out = list(boxes)
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                a, b = out[i], out[j]
                if a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]:
                    out[i] = (min(a[0], b[0]), min(a[1], b[1]), max(a[2], b[2]), max(a[3], b[3]))
                    del out[j]
                    merged = True
                    break
            if merged:
                break
    return out
