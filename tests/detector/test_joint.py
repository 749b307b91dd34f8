"""Markers of one entity seen together are solved jointly; if they do not fit together as the world
file places them, nothing of that entity is reported from the image (rendered views, truth known)."""

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import parse_world
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import Camera, MarkerView, render

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
CAM = Camera(1280, 720, K, np.zeros(5))


def detector(offset_m: float) -> Detector:
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
    return Detector(world.sensors[1], world, Calibration(1280, 720, K, np.zeros(5)), decimate=1.0, track=False)


def image():
    """The camera 1.5 m from the tags, looking at them from 25 degrees off the normal."""
    T_cam_world = RigidTransform.from_components(
        [-0.2, 0.05, 1.5], Rotation.from_euler("xyz", [205, 8, 3], degrees=True)
    )
    views = [MarkerView("tag36h11", i, 0.15, T_cam_world * RigidTransform.from_translation([x, 0, 0]))
             for i, x in ((1, 0.0), (2, 0.4))]  # fmt: skip
    return render(CAM, views, noise_sigma=1.0, seed=3), T_cam_world


@pytest.mark.parametrize("offset_m", [0.0, 0.05])
def test_joint_pose_or_nothing_when_the_markers_do_not_fit_together(offset_m):
    det = detector(offset_m)
    img, T_cam_world = image()
    found = det.detect(img, 1)
    if offset_m == 0.0:
        # One observation of the entity, at the first marker, within a few mm and a fraction of a degree.
        (md,) = found
        assert md.marker_id == 1 and det.counters["joint"] == 1
        np.testing.assert_allclose(md.p_sensor_marker_m, T_cam_world.translation, atol=0.005)
        w, x, y, z = md.q_sensor_marker_wxyz
        assert np.degrees((Rotation.from_quat([x, y, z, w]).inv() * T_cam_world.rotation).magnitude()) < 0.5
    else:
        # A marker 5 cm from where the world file says: no pose of the world from this image.
        assert found == [] and det.counters["joint_misfit"] == 1
