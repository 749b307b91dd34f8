"""The edge fit against markers drawn by exact pixel area (a single tag's covariance honest, not
only safe): pixels integrate the image over their area, so an edge is where a step of the same area
would be; the half-level crossing of interpolated pixels misses a sharp edge by up to a tenth of a pixel
by where it falls between pixel centres, alike all along an edge that lies along a pixel axis, which no
scatter shows and the covariance then cannot cover."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from atlas_onboard.detector import refine
from tests.detector.synthetic import marker_image

K = np.array([[300.0, 0.0, 59.5], [0.0, 300.0, 59.5], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize("cell_px", [4.0, 6.0, 9.0])
@pytest.mark.parametrize("phase", [0.0, 0.1, 0.25, 0.4])
def test_a_sharp_marker_along_the_pixel_axes_is_placed_exactly(cell_px: float, phase: float):
    """Without noise, wherever its edges fall between pixel centres, the corners are where they are drawn
    (to the grey levels' rounding), from a start half a pixel off."""
    img, truth = marker_image(20.0 + phase, 23.0 + phase / 2, cell_px)
    gray = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    refined = refine.refine_corners_undistorted(gray, truth + np.array([0.4, -0.3]), K, np.zeros(5))
    assert refined is not None
    assert np.abs(refined.corners - truth).max() < 0.01


@pytest.mark.parametrize("blur_px", [0, 3])
def test_the_corners_covariance_is_honest_over_noise_blur_and_place(blur_px: int):
    """Monte Carlo of markers at random sub-pixel places, cells of 5-8 px, pixel noise of 3 grey levels,
    sharp or with a symmetric motion blur across three pixels: the corners' error against their reported
    (8, 8) covariance has the chi-square mean of its eight degrees of freedom, within three standard
    errors of the Monte Carlo (an overconfident covariance gives several times more)."""
    rng = np.random.default_rng(0)
    n = 150
    nees = []
    for _ in range(n):
        img, truth = marker_image(*rng.uniform(12.0, 18.0, 2), rng.uniform(5.0, 8.0))
        if blur_px:
            img = cv2.blur(img, (blur_px, 1), borderType=cv2.BORDER_REPLICATE)
        gray = np.clip(np.rint(img + rng.normal(0.0, 3.0, img.shape)), 0, 255).astype(np.uint8)
        refined = refine.refine_corners_undistorted(gray, truth + rng.uniform(-0.5, 0.5, (4, 2)), K, np.zeros(5))
        assert refined is not None
        e = (refined.corners - truth).ravel()
        nees.append(float(e @ np.linalg.solve(refined.covariance, e)))
    standard_error = np.sqrt(2 * 8 / n)  # of the mean of n chi-square(8) draws
    assert abs(np.mean(nees) - 8.0) <= 3 * standard_error, np.mean(nees)
