"""Real photographs: recall at least the AprilTag library's at decimate 1, no false ids, and the pose
of the Ubiquity Robotics test photo against the pose its source expects."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import parse_world
from atlas_onboard.detector.backends import _library_detector
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector

DATA = Path(__file__).resolve().parents[1] / "data"
MANIFEST = json.loads((DATA / "swatbotics_manifest.json").read_text())


def images(kind):
    for item in MANIFEST["images"]:
        folder, name = item["file"].split("/")
        if folder == kind and item.get("expected_ids") is not None:
            path = DATA / ("swatbotics_mapping" if kind == "mapping_feb_2014" else "swatbotics_clipboard") / name
            if path.exists():
                yield path, set(item["expected_ids"])


def detector_for(ids, width, height, K):
    world = parse_world(
        {
            "entities": {
                "world": {"markers": [{"id": i, "size_m": 0.127, "pose": {"pos": [float(i), 0, 0]}} for i in ids]},
                "cam": {"sensors": [{"name": "c", "id": 1, "pose": {}}]},
            }
        }
    )
    cal = Calibration(width, height, K, np.zeros(5))
    # Still photos: no previous frame to track from, so search at full resolution.
    return Detector(world.sensors[1], world, cal, decimate=1.0, track=False, joint=False, max_ambiguity=1.0)


@pytest.mark.parametrize("kind", ["mapping_feb_2014", "clipboard"])
def test_recall_at_least_the_library_and_no_false_ids(kind):
    # The library at decimate 1 with its default settings (refine_edges 1, decode_sharpening 0.25).
    library = _library_detector("tag36h11", 1, 1.0)
    expected_total = ours_found = lib_found = 0
    false_ids = []
    for path, expected in images(kind):
        gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        h, w = gray.shape
        K = (
            np.array([[765.0, 0, 393.72], [0, 764.18, 304.66], [0, 0, 1]])
            if w == 816
            else np.array([[300.0, 0, (w - 1) / 2], [0, 300.0, (h - 1) / 2], [0, 0, 1]])
        )
        det = detector_for(range(30), w, h, K)
        ours = {d.marker_id for d in det.find(gray)}
        lib = {r.tag_id for r in library.detect(gray)}
        expected_total += len(expected)
        ours_found += len(ours & expected)
        lib_found += len(lib & expected)
        false_ids += [(path.name, i) for i in ours - expected]
    assert expected_total > 0
    assert ours_found >= lib_found, f"{kind}: ours {ours_found}/{expected_total}, library {lib_found}/{expected_total}"
    assert false_ids == []


def test_ubiquity_403_pose_matches_its_source():
    cams = yaml.safe_load((DATA / "ubiquity" / "cameras.yaml").read_text())["test_png_and_403"]
    K = np.array(cams["K"], dtype=float).reshape(3, 3)
    world = parse_world(
        {
            "marker_family": "DICT_5X5_1000",
            "entities": {
                "world": {"markers": [{"id": 403, "size_m": 0.145, "pose": {}}]},
                "robot": {"sensors": [{"name": "cam", "id": 1, "pose": {}}]},
            },
        }
    )
    cal = Calibration(1280, 960, K, np.array(cams["D"], dtype=float))
    det = Detector(world.sensors[1], world, cal, decimate=1.0, track=False)
    gray = cv2.imread(str(DATA / "ubiquity" / "403.jpg"), cv2.IMREAD_GRAYSCALE)
    (md,) = det.detect(gray, 0)
    w, x, y, z = md.q_sensor_marker_wxyz
    T_cam_marker = RigidTransform.from_components(md.p_sensor_marker_m, Rotation.from_quat([x, y, z, w]))
    # The source's camera in base_link: static_transform_publisher x y z yaw pitch roll.
    T_base_cam = RigidTransform.from_components(
        [0.035, 0.145, 0.14], Rotation.from_euler("ZYX", [-1.479119, -0.041544, -1.204205])
    )
    T_base_marker = T_base_cam * T_cam_marker
    expected = RigidTransform.from_components(
        [0.7611, 0.2505, 0.4028], Rotation.from_euler("ZYX", [-1.546, -0.014, 1.5751])
    )  # rpy (1.5751, -0.014, -1.546) as the source gives it
    err_m = float(np.linalg.norm(T_base_marker.translation - expected.translation))
    err_deg = float(np.degrees((T_base_marker.rotation.inv() * expected.rotation).magnitude()))
    assert err_m <= 0.01, err_m
    assert err_deg <= 1.0, err_deg
