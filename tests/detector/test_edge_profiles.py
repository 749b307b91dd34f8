"""The image along the corner refit's sample rows (edge_profiles.profiles), against the image read by hand:
every sample point sent through OpenCV's own lens model, the image interpolated bilinearly there (the
border replicated), for markers in the middle of the image and one whose samples run past its border."""

from __future__ import annotations

import cv2
import numpy as np

from atlas_onboard.detector.edge_profiles import profiles
from atlas_onboard.detector.edge_sampling import STEP_PX, sampling

K = np.array([[457.0, 0.0, 319.5], [0.0, 457.0, 239.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.2, 0.05, 0.001, -0.002, 0.0])


def square(x0: float, y0: float, side: float) -> np.ndarray:
    return np.array([[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side]])


def bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The image at (x, y), linear between pixel centres, the border replicated."""
    h, w = img.shape
    x, y = np.clip(x, 0, w - 1), np.clip(y, 0, h - 1)
    i, j = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = x - i, y - j
    f = img.astype(float)
    top = f[j, i] * (1 - fx) + f[j, i + 1] * fx
    bottom = f[j + 1, i] * (1 - fx) + f[j + 1, i + 1] * fx
    return top * (1 - fy) + bottom * fy


def lens(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undistorted pixels -> image pixels through cv2.projectPoints."""
    rays = np.column_stack([u, v, np.ones_like(u)]) @ np.linalg.inv(K).T
    px = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, DIST)[0].reshape(-1, 2)
    return px[:, 0], px[:, 1]


def test_profiles_are_the_image_at_the_sample_points_through_the_lens():
    rng = np.random.default_rng(4)
    gray = cv2.GaussianBlur(rng.integers(0, 256, (480, 640)).astype(np.uint8), (0, 0), 2.0)
    corners = [square(100, 120, 80), square(400, 300, 40), square(700, -60, 40), square(300, 60, 3)]
    plan = sampling(corners)
    assert plan is not None and plan.markers == [0, 1, 2]  # the 3 px square has no side to fit
    got = profiles(gray, plan, K, DIST, False)
    assert got.values.shape == plan.offsets.shape
    u = (plan.bases[:, 0, None] + plan.offsets * plan.normals[:, 0, None]).ravel()
    v = (plan.bases[:, 1, None] + plan.offsets * plan.normals[:, 1, None]).ravel()
    x, y = lens(u, v)
    assert x.max() > 639 and y.min() < 0  # the third marker's samples run past the image's corner
    expected = bilinear(gray, x, y).reshape(plan.offsets.shape)
    # float32 sample positions: a 1e-5 px error on gradients of at most a few tens of grey levels a pixel
    np.testing.assert_allclose(got.values, expected, atol=0.01)
    # Each marker's scale: undistorted pixels per image pixel, the mean over its rows' first step.
    x, y = x.reshape(plan.offsets.shape), y.reshape(plan.offsets.shape)
    step = np.hypot(x[:, 1] - x[:, 0], y[:, 1] - y[:, 0])
    for k, (start, n) in enumerate(zip(plan.starts, plan.samples, strict=True)):
        np.testing.assert_allclose(got.scales[k], np.mean(STEP_PX / step[start : start + 4 * n]), rtol=1e-5)
    assert got.scales[0] > 1.0  # barrel distortion shrinks the image away from the centre
