"""A renderer of markers seen by a camera, for tests and the simulator.

Each marker is drawn with its white quiet zone, at sub-pixel accuracy: every output pixel is the
average of ``supersample`` x ``supersample`` samples, each mapped through the lens distortion and
the marker plane's homography into the marker bitmap. Only a region around each marker is rendered.
The background is a smooth random texture; motion blur and pixel noise can be added.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform

from atlas_onboard.detector.families import family

CELL_PX = 16


@dataclass(frozen=True)
class Camera:
    """Pinhole intrinsics (OpenCV pixel-centre convention) and distortion k1 k2 p1 p2 k3."""

    width_px: int
    height_px: int
    K: NDArray[np.float64]
    dist: NDArray[np.float64]


@dataclass(frozen=True)
class MarkerView:
    """A marker to draw: its family, id, size and its pose in the camera's optical frame."""

    family: str
    marker_id: int
    size_m: float
    T_camera_marker: RigidTransform


_bitmaps: dict[tuple[str, int], NDArray[np.float32]] = {}


def _bitmap(name: str, marker_id: int) -> NDArray[np.float32]:
    key = (name, marker_id)
    if key not in _bitmaps:
        _bitmaps[key] = family(name).bitmap(marker_id, CELL_PX).astype(np.float32)
    return _bitmaps[key]


_backgrounds: dict[tuple[int, int, int], NDArray[np.float32]] = {}


def background(camera: Camera, seed: int = 0, mean: float = 140.0, contrast: float = 40.0) -> NDArray[np.float32]:
    """A smooth random texture (a floor, a wall) of the camera's size (cached: made once per seed)."""
    key = (camera.width_px, camera.height_px, seed)
    if key not in _backgrounds:
        if len(_backgrounds) > 8:
            _backgrounds.clear()
        _backgrounds[key] = _texture(camera, seed, mean, contrast)
    return _backgrounds[key].copy()


def _texture(camera: Camera, seed: int, mean: float, contrast: float) -> NDArray[np.float32]:
    rng = np.random.default_rng(seed)
    small = rng.normal(0.0, 1.0, (camera.height_px // 16 + 2, camera.width_px // 16 + 2)).astype(np.float32)
    tex = cv2.resize(small, (camera.width_px, camera.height_px), interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.normal(0.0, 0.3, (camera.height_px, camera.width_px)).astype(np.float32), (0, 0), 1.0)
    return np.clip(mean + contrast * (tex + fine), 20, 235).astype(np.float32)


def _project(camera: Camera, pts_cam: NDArray[np.float64]) -> NDArray[np.float64]:
    pts = np.ascontiguousarray(pts_cam, dtype=np.float64).reshape(-1, 1, 3)
    px, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), camera.K, camera.dist)
    return px.reshape(-1, 2)


def draw_marker(img: NDArray[np.float32], camera: Camera, view: MarkerView, supersample: int = 4) -> bool:
    """Paint one marker into ``img`` in place; False if it is behind the camera or out of the image."""
    bmp = _bitmap(view.family, view.marker_id)
    fam = family(view.family)
    n_px = bmp.shape[0]  # bitmap side in pixels, quiet zone included
    cells_total = fam.cells + 2
    side_m = view.size_m * cells_total / fam.cells  # printed size with the quiet zone
    h = side_m / 2
    outline = np.array([[-h, h, 0], [h, h, 0], [h, -h, 0], [-h, -h, 0]])
    pts = view.T_camera_marker.apply(outline)
    if np.any(pts[:, 2] <= 0.01):
        return False
    px = _project(camera, pts)
    x0, y0 = np.floor(px.min(axis=0)).astype(int) - 2
    x1, y1 = np.ceil(px.max(axis=0)).astype(int) + 2
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, camera.width_px - 1), min(y1, camera.height_px - 1)
    if x1 <= x0 or y1 <= y0:
        return False
    s = supersample
    w, hgt = (x1 - x0 + 1) * s, (y1 - y0 + 1) * s
    # Sample positions (pixel-centre convention) on a coarse grid; distortion is smooth, so the
    # exact undistortion on a grid of every 4th sample, resized, is accurate to well under 0.01 px.
    step = 4
    gx = x0 + (np.arange(0, w + step, step) + 0.5) / s - 0.5  # sample k: x0 + (k + 0.5) / s - 0.5
    gy = y0 + (np.arange(0, hgt + step, step) + 0.5) / s - 0.5
    grid = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 1, 2)
    norm = cv2.undistortPoints(
        grid, camera.K, camera.dist, None, None, criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-10)
    ).reshape(len(gy), len(gx), 2)
    # Ray through each sample hits the marker plane: solve in the marker frame.
    R = view.T_camera_marker.rotation.as_matrix()
    t = view.T_camera_marker.translation
    rays = np.concatenate([norm, np.ones((*norm.shape[:2], 1))], axis=-1)  # camera frame directions
    rays_m = rays @ R  # = R^T ray, in marker frame
    origin_m = -R.T @ t
    lam = -origin_m[2] / rays_m[..., 2]
    hit = origin_m[None, None, :2] + lam[..., None] * rays_m[..., :2]
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
    return True


def render(
    camera: Camera,
    views: list[MarkerView],
    *,
    seed: int = 0,
    background_seed: int = 0,
    noise_sigma: float = 0.0,
    blur_px: tuple[float, float] = (0.0, 0.0),
    supersample: int = 4,
) -> NDArray[np.uint8]:
    """A grey image of the markers (drawn far to near) over a textured background.

    ``blur_px`` is the motion of the image during the exposure (dx, dy in pixels): a linear blur.
    """
    img = background(camera, background_seed)
    for view in sorted(views, key=lambda v: -float(np.linalg.norm(v.T_camera_marker.translation))):
        draw_marker(img, camera, view, supersample)
    length = float(np.hypot(*blur_px))
    if length >= 0.5:
        k = int(np.ceil(length)) * 2 + 1
        kernel = np.zeros((k, k), np.float32)
        c = k // 2
        n = max(int(np.ceil(length * 4)), 2)
        for a in np.linspace(-0.5, 0.5, n):
            kernel[round(c + a * blur_px[1]), round(c + a * blur_px[0])] += 1.0
        img = cv2.filter2D(img, -1, kernel / kernel.sum(), borderType=cv2.BORDER_REPLICATE)
    if noise_sigma > 0:
        noise = np.empty(img.shape, np.float32)
        cv2.setRNGSeed(seed)
        cv2.randn(noise, 0.0, noise_sigma)
        img += noise
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
