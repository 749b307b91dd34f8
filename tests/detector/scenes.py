"""Rendered scenes with known truth shared by the detector's tests: a strongly distorted 640x480
camera with single tags or four tags of which the world file may misplace one, and an undistorted
1280x720 camera over two tags of one entity."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import parse_world
from atlas_onboard.core.markerdata import upper_to_matrix
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import LENS_RESIDUAL_PX, Camera, MarkerView, render

W, H = 640, 480
K = np.array([[460.0, 0.0, 319.5], [0.0, 460.0, 239.5], [0.0, 0.0, 1.0]])
DIST = np.array([-0.3, 0.08, 0.0, 0.0, 0.0])  # strong barrel distortion
CAM = Camera(W, H, K, DIST)
SIZE = 0.15


def one_tag_detector(**kw) -> Detector:
    world = parse_world(
        {
            "entities": {
                "world": {"markers": [{"id": 7, "size_m": SIZE, "pose": {}}]},
                "cam": {"sensors": [{"name": "c", "id": 1, "pose": {}}]},
            }
        }
    )
    # The renders' lens is exact: their calibration states the simulator's residual, as its files do.
    return Detector(world.sensors[1], world, Calibration(W, H, K, DIST, False, LENS_RESIDUAL_PX), **kw)


def pose_error(md, T_true: RigidTransform) -> tuple[np.ndarray, np.ndarray]:
    """[dp, dtheta] of the truth against the record (atlas-onboard's convention: dp in the camera
    frame, dtheta about the marker's axes) and the record's 6x6 covariance."""
    w, x, y, z = md.q_sensor_marker_wxyz
    R = Rotation.from_quat([x, y, z, w])
    e = np.concatenate([T_true.translation - np.array(md.p_sensor_marker_m), (R.inv() * T_true.rotation).as_rotvec()])
    return e, upper_to_matrix(np.array(md.covariance))


def at_pixel(u: float, v: float, distance_m: float, rot: Rotation) -> RigidTransform:
    """A marker pose whose centre is seen at image pixel (u, v), ``distance_m`` deep."""
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    n = cv2.undistortPoints(np.array([[[u, v]]], float), K, DIST, None, None, criteria=crit).ravel()
    return RigidTransform.from_components([n[0] * distance_m, n[1] * distance_m, distance_m], rot)


def moved_marker_world(moved_id: int | None, offset_m: float):
    """Four 15 cm tags on the floor at the corners of a 60 x 40 cm rectangle; the world file puts
    ``moved_id`` ``offset_m`` off along x."""
    spots = {1: (0.0, 0.0), 2: (0.6, 0.0), 3: (0.6, 0.4), 5: (0.0, 0.4)}
    markers = [{"id": i, "size_m": SIZE, "pose": {"pos": [x + (offset_m if i == moved_id else 0.0), y, 0.0]}}
               for i, (x, y) in spots.items()]  # fmt: skip
    world = parse_world(
        {"entities": {"world": {"markers": markers}, "cam": {"sensors": [{"name": "c", "id": 1, "pose": {}}]}}}
    )
    return world, spots


def moved_marker_image(spots, yaw_deg: float = 4.0):
    T_cam_world = RigidTransform.from_components(
        [-0.3, -0.2, 1.6], Rotation.from_euler("xyz", [200, 6, yaw_deg], degrees=True)
    )
    views = [MarkerView("tag36h11", i, SIZE, T_cam_world * RigidTransform.from_translation([x, y, 0]))
             for i, (x, y) in spots.items()]  # fmt: skip
    return render(CAM, views, noise_sigma=2.0, seed=3, background_style="concrete"), T_cam_world


K_HD = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
CAM_HD = Camera(1280, 720, K_HD, np.zeros(5))


def two_tag_detector(offset_m: float) -> Detector:
    """Two 15 cm tags on the floor 40 cm apart; the world file puts the second ``offset_m`` off."""
    world = parse_world(
        {
            "entities": {
                "world": {
                    "markers": [
                        {"id": 1, "size_m": 0.15, "pose": {"pos": [0.0, 0.0, 0.0]}},
                        {"id": 2, "size_m": 0.15, "pose": {"pos": [0.4 + offset_m, 0.0, 0.0]}},
                    ]
                },
                "cam": {"sensors": [{"name": "c", "id": 1, "pose": {}}]},
            }
        }
    )
    return Detector(world.sensors[1], world, Calibration(1280, 720, K_HD, np.zeros(5)), decimate=1.0, track=False)


def two_tag_image():
    """The camera 1.5 m from the tags, looking at them from 25 degrees off the normal."""
    T_cam_world = RigidTransform.from_components(
        [-0.2, 0.05, 1.5], Rotation.from_euler("xyz", [205, 8, 3], degrees=True)
    )
    views = [MarkerView("tag36h11", i, 0.15, T_cam_world * RigidTransform.from_translation([x, 0, 0]))
             for i, x in ((1, 0.0), (2, 0.4))]  # fmt: skip
    return render(CAM_HD, views, noise_sigma=1.0, seed=3), T_cam_world
