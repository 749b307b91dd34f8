"""A single sharp tag's reported covariance against rendered truth anywhere in a 640x480 image with strong
barrel distortion (issue 19: honest, not only safe): the position's NEES about its three degrees of freedom,
no position error beyond three of its sigmas. A covariance padded with fixed pixel floors gives a NEES far
below three (a pose trusted less than it deserves)."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import parse_world
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.markerdata import upper_to_matrix
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import LENS_RESIDUAL_PX, Camera, MarkerView, render

K = np.array([[460.0, 0.0, 319.5], [0.0, 460.0, 239.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.3, 0.08, 0.0, 0.0, 0.0])
SIZE_M = 0.15


def position_errors(n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each detection's position error (truth minus reported, m) and its reported 3x3 covariance."""
    world = parse_world({"entities": {"world": {"markers": [{"id": 7, "size_m": SIZE_M, "pose": {}}]},
                                      "cam": {"sensors": [{"name": "c", "id": 1, "pose": {}}]}}})  # fmt: skip
    # A simulated camera's calibration states its lens residual, as the simulator's files do.
    cal = Calibration(640, 480, K, DIST, False, LENS_RESIDUAL_PX)
    det = Detector(world.sensors[1], world, cal, decimate=1.0, track=False)
    rng = np.random.default_rng(11)
    out = []
    for k in range(n):
        distance, tilt = rng.uniform(0.5, 2.5), rng.uniform(0.0, 60.0)
        rot = Rotation.from_euler("zxz", [rng.uniform(0, 360), 180 + tilt, rng.uniform(0, 360)], degrees=True)
        uv = rng.uniform([40, 40], [600, 440]).reshape(1, 1, 2)
        x, y = cv2.undistortPoints(uv, K, DIST).ravel()
        T = RigidTransform.from_components([x * distance, y * distance, distance], rot)
        img = render(Camera(640, 480, K, DIST), [MarkerView("tag36h11", 7, SIZE_M, T)], noise_sigma=3.0, seed=k,
                     background_style="concrete", background_seed=k % 5)  # fmt: skip
        for md in det.detect(img, k):
            if md.ambiguity_ratio <= AMBIGUITY_THRESHOLD:
                C = upper_to_matrix(np.array(md.covariance))[:3, :3]
                out.append((T.translation - np.array(md.p_sensor_marker_m), C))
    return out


def test_a_sharp_single_tags_position_covariance_is_honest_across_the_image():
    errs = position_errors(70)
    assert len(errs) >= 50
    nees = np.array([e @ np.linalg.solve(C, e) for e, C in errs])
    z = np.array([np.abs(e) / np.sqrt(np.diag(C)) for e, C in errs])
    print(f"{len(errs)} detections: position NEES mean {nees.mean():.2f}, median {np.median(nees):.2f}")
    assert z.max() <= 3.5, z.max()  # no position error beyond its sigmas (a little margin over 3 for 200 axes)
    assert 1.5 <= nees.mean() <= 4.5  # about its three degrees of freedom: neither overconfident nor padded
