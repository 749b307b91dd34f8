"""The corner refit of all markers of a frame in one pass (refine.refine_markers_undistorted) gives each
marker what its refit alone gives: markers of different sizes (different samples a side and search
widths), a lens with distortion, one too small to fit among them."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.detector import pose, refine
from atlas_onboard.detector.render import Camera, MarkerView, render

K = np.array([[457.0, 0.0, 319.5], [0.0, 457.0, 239.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.2, 0.05, 0.0, 0.0, 0.0])


def _image_corners(view: MarkerView) -> np.ndarray:
    """Where the marker's corners fall in the distorted image (pixel centres)."""
    P = view.T_camera_marker.apply(pose.object_corners(view.size_m))
    return cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, DIST)[0].reshape(4, 2)


def test_a_frames_markers_refitted_together_get_what_each_gets_alone() -> None:
    cam = Camera(640, 480, K, DIST)
    views = []
    for k, (x, y, z, size) in enumerate(
        [(-0.5, -0.3, 1.5, 0.16), (0.3, -0.25, 2.5, 0.16), (0.0, 0.2, 1.0, 0.12), (0.55, 0.3, 4.0, 0.1)]
    ):
        R = Rotation.from_euler("xyz", [180 + 15 * k, -10 * k, 40 * k], degrees=True)
        views.append(MarkerView("tag36h11", k + 1, size, RigidTransform.from_components([x, y, z], R)))
    img = render(cam, views, seed=3, noise_sigma=2.0)
    rng = np.random.default_rng(0)
    found = [_image_corners(v) + rng.normal(0, 0.2, (4, 2)) for v in views]
    corners = [pose.undistort(c, K, DIST, False) for c in found]
    corners.append(np.array([[300.0, 200.0], [304.0, 200.0], [304.0, 204.0], [300.0, 204.0]]))  # too small
    together = refine.refine_markers_undistorted(img, corners, K, DIST, False, 0.1)
    alone = [refine.refine_corners_undistorted(img, c, K, DIST, False, 0.1) for c in corners]
    assert together[-1] is None and alone[-1] is None
    assert sum(r is not None for r in together) >= 3  # the frame's markers were fitted
    for a, b in zip(alone, together, strict=True):
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            np.testing.assert_array_equal(a.corners, b.corners)
            assert a.sigma_px == b.sigma_px
            np.testing.assert_array_equal(a.covariance, b.covariance)
