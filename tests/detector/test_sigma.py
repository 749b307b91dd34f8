"""The sigma model against truth: in each bin of distance (0.5-5 m) and viewing angle (0-60 deg), the
median of (actual error of the camera's position relative to the marker / sigma) lies in [0.5, 2]."""

import functools

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.detector import pose
from atlas_onboard.detector.backends import MarkerFinder
from atlas_onboard.detector.render import Camera, MarkerView, render

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
CAM = Camera(1280, 720, K, np.zeros(5))
FINDER = MarkerFinder({7: "tag36h11"})


def ratios(distance, angle, n=10, seed=0):
    rng = np.random.default_rng(seed)
    out = []
    for k in range(n):
        rot = Rotation.from_euler("zxz", [rng.uniform(0, 360), 180 + angle, rng.uniform(0, 360)], degrees=True)
        off = rng.uniform(-0.25, 0.25, 2) * distance
        T = RigidTransform.from_components([off[0], off[1] * 0.5, distance], rot)
        img = render(
            CAM, [MarkerView("tag36h11", 7, 0.15, T)], noise_sigma=2.0, seed=int(distance * 1000 + angle * 10 + k)
        )
        found = FINDER.find(img, 1.0)
        if not found:
            continue
        mp = pose.solve(found[0].corners_px, 0.15, K, pose.SIGMA_PX_APRILTAG)
        cam_true = -T.rotation.inv().apply(T.translation)
        cam_est = -Rotation.from_quat(mp.q_xyzw).inv().apply(mp.p_m)
        out.append(np.linalg.norm(cam_est - cam_true) / mp.sigma_m)
    return np.array(out)


DISTANCES = (0.5, 1.0, 2.0, 3.0, 5.0)
ANGLES = (0, 20, 40, 60)


@functools.cache
def grid_cell(distance, angle):
    """The ratios of one cell of the distance x viewing-angle grid (6 views), shared by the distance
    and the angle tests: each bin of either pools the 4 or 5 cells of its row or column."""
    return ratios(distance, angle, n=6, seed=int(distance * 7 + angle))


@pytest.mark.parametrize("distance", DISTANCES)
def test_sigma_is_calibrated_over_distance(distance):
    r = np.concatenate([grid_cell(distance, a) for a in ANGLES])
    assert len(r) >= 20
    assert 0.5 <= np.median(r) <= 2.0, f"{distance} m: median error/sigma {np.median(r):.2f}"


@pytest.mark.parametrize("angle", ANGLES)
def test_sigma_is_calibrated_over_viewing_angle(angle):
    r = np.concatenate([grid_cell(d, angle) for d in DISTANCES])
    assert len(r) >= 20
    assert 0.5 <= np.median(r) <= 2.0, f"{angle} deg: median error/sigma {np.median(r):.2f}"
