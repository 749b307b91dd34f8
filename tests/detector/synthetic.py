"""Markers drawn by exact pixel area (no renderer): what a camera's pixels integrate, for tests of the
edge fit that must not depend on a renderer's own sampling."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def _coverage(lo: float, hi: float, n: int) -> NDArray[np.float64]:
    """(n,): how much of each pixel i (the unit interval about i, pixel-centre convention) lies in [lo, hi]."""
    i = np.arange(n)
    return np.clip(np.minimum(i + 0.5, hi) - np.maximum(i - 0.5, lo), 0.0, 1.0)


def marker_image(
    x0: float, y0: float, cell_px: float, size: tuple[int, int] = (120, 120), seed: int = 1
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A tag36h11-like marker along the pixel axes (8 cells of black border and data, one of white quiet
    zone, on a grey floor), its black square's corner at (x0, y0): the image (float, grey levels) with
    each pixel the exact mean over its area, and the four corners (4, 2) (TL, TR, BR, BL)."""
    h, w = size
    img = np.full((h, w), 90.0)

    def rect(a: float, b: float, c: float, d: float, value: float) -> None:
        cover = np.outer(_coverage(c, d, h), _coverage(a, b, w))
        img[:] = img * (1 - cover) + value * cover

    rect(x0 - cell_px, x0 + 9 * cell_px, y0 - cell_px, y0 + 9 * cell_px, 220.0)
    rect(x0, x0 + 8 * cell_px, y0, y0 + 8 * cell_px, 20.0)
    bits = np.random.default_rng(seed).random((6, 6)) < 0.5
    for r, c in zip(*np.nonzero(bits), strict=True):
        rect(x0 + (c + 1) * cell_px, x0 + (c + 2) * cell_px, y0 + (r + 1) * cell_px, y0 + (r + 2) * cell_px, 220.0)
    s = 8 * cell_px
    return img, np.array([[x0, y0], [x0 + s, y0], [x0 + s, y0 + s], [x0, y0 + s]])
