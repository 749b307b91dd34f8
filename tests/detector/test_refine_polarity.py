"""ArUco corners refined on the marker's outer edge only (dark border inside, bright quiet zone outside):
an edge of a white data cell next to the border has the other polarity and must not be taken for it."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.detector.backends import ArucoBackend
from atlas_onboard.detector.render import Camera, MarkerView, render

K = np.array([[380.0, 0.0, 319.5], [0.0, 380.0, 239.5], [0.0, 0.0, 1.0]])


def test_aruco_corners_are_unbiased_on_rendered_markers() -> None:
    cam = Camera(640, 480, K, np.zeros(5))
    rng = np.random.default_rng(0)
    backend = ArucoBackend("DICT_5X5_100")
    h = 0.09
    X = np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
    errors = []
    for k in range(24):
        tilt = Rotation.from_euler("xyz", [*rng.uniform(-50, 50, 2), rng.uniform(-180, 180)], degrees=True)
        T = RigidTransform.from_components(
            [rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.3), rng.uniform(1.2, 2.8)],
            tilt * Rotation.from_euler("x", 180, degrees=True),  # facing the camera
        )
        img = render(cam, [MarkerView("DICT_5X5_100", 30 + k % 2, 0.18, T)], seed=k, noise_sigma=2.0, supersample=3)
        found = backend.detect(img)
        assert len(found) == 1
        P = T.apply(X)
        errors.append(found[0].corners_px - (P[:, :2] / P[:, 2:] * K[0, 0] + K[:2, 2]))
    e = np.array(errors)
    assert np.sqrt(np.mean(e**2)) < 0.2
    assert np.abs(e).max() < 1.0
