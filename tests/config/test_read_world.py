"""The world file's reader: normalisation of conventions, poses, paths and the fingerprint."""

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, Weighting, load_world, parse_world
from atlas_onboard.core.geometry import rpy_deg
from tests.config.common import BASE, REPO


def test_base_loads_with_defaults_and_world():
    w = parse_world(yaml.safe_load(BASE))
    assert w.entity_names == (WORLD, "drone1", "drone2")
    assert w.fusion.ema_alpha == 0.5 and w.fusion.weighting is Weighting.SIGMA_MIN
    assert sorted(w.sensors) == [1, 2] and sorted(w.markers) == [0, 10]
    assert w.markers[10].family == "tag36h11"


def test_world_entity_always_exists():
    w = parse_world({"entities": {"a": {}}})
    assert w.entity_names == (WORLD, "a")


def test_ned_frd_file_is_normalised_to_enu_flu():
    doc = {
        "conventions": {"world": "NED", "body": "FRD"},
        "entities": {
            "world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [1, 2, 3], "rpy_deg": [0, 0, 90]}}]},
            "d": {"markers": [{"id": 1, "size_m": 0.1, "pose": {"pos": [0.1, 0.2, 0.3]}}]},
        },
    }
    w = parse_world(doc)
    m0 = w.markers[0].T_entity_marker
    np.testing.assert_allclose(m0.translation, [2, 1, -3], atol=1e-12)  # NED (1, 2, 3) -> ENU (2, 1, -3)
    # The marker's x axis points NED-east (yaw 90 from north) = ENU x.
    np.testing.assert_allclose(m0.rotation.apply([1, 0, 0]), [1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(w.markers[1].T_entity_marker.translation, [0.1, -0.2, -0.3], atol=1e-12)


def test_same_world_in_ned_and_enu_has_same_fingerprint():
    enu = {"entities": {"world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [2, 1, -3]}}]}}}
    ned = {
        "conventions": {"world": "NED"},
        "entities": {
            "world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [1, 2, 3], "rpy_deg": [180, 0, 90]}}]}
        },
    }
    a, b = parse_world(enu), parse_world(ned)
    np.testing.assert_allclose(
        a.markers[0].T_entity_marker.as_matrix(), b.markers[0].T_entity_marker.as_matrix(), atol=1e-12
    )
    assert a.fingerprint() == b.fingerprint()
    moved = {"entities": {"world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [2, 1, -3.01]}}]}}}
    assert parse_world(moved).fingerprint() != a.fingerprint()


def test_sensor_mount_pose_becomes_optical_frame():
    w = parse_world(
        {"entities": {"d": {"sensors": [{"name": "down", "id": 1, "pose": {"pos": [0, 0, 0], "rpy_deg": [0, 90, 0]}}]}}}
    )
    np.testing.assert_allclose(w.sensors[1].T_entity_sensor.rotation.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)


def test_quaternion_and_rpy_agree():
    a = parse_world({"entities": {"d": {"markers": [{"id": 1, "size_m": 0.1, "pose": {"rpy_deg": [10, 20, 30]}}]}}})
    q = Rotation.from_euler("ZYX", [30, 20, 10], degrees=True).as_quat()
    b = parse_world(
        {
            "entities": {
                "d": {
                    "markers": [{"id": 1, "size_m": 0.1, "pose": {"rot": {"w": q[3], "x": q[0], "y": q[1], "z": q[2]}}}]
                }
            }
        }
    )
    np.testing.assert_allclose(rpy_deg(a.markers[1].T_entity_marker.rotation), [10, 20, 30], atol=1e-9)
    np.testing.assert_allclose(
        a.markers[1].T_entity_marker.as_matrix(), b.markers[1].T_entity_marker.as_matrix(), atol=1e-12
    )


def test_calibration_path_is_relative_to_the_file(tmp_path):
    f = tmp_path / "w.yaml"
    sensor = "{name: c, id: 1, pose: {}, camera: {calibration: cal/c.yaml, fps: 30}}"
    f.write_text(f"entities:\n  d:\n    sensors:\n      - {sensor}\n")
    assert load_world(f).sensors[1].camera.calibration == tmp_path / "cal" / "c.yaml"


# One case per kind of bad input: (description, edit of BASE, expected field path, expected words).


def test_paper_replicas_match_the_paper():
    t1 = load_world(REPO / "config" / "paper-test1.yaml")
    world_markers = t1.entity(WORLD).markers
    assert len(world_markers) == 13 and all(m.size_m == 0.18 and m.family == "tag36h11" for m in world_markers)
    assert all(abs(m.T_entity_marker.translation[2]) < 1e-12 for m in world_markers)  # on the floor
    cam = t1.entity("ardrone").sensors[0]
    np.testing.assert_allclose(cam.T_entity_sensor.rotation.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)  # looks down
    t2 = load_world(REPO / "config" / "paper-test2.yaml")
    assert [m.size_m for m in t2.entity("tag").markers] == [0.12]
    assert sum(1 for e in t2.entities if e.name.startswith("drone")) == 2


def test_mounted_cameras_are_the_same_whether_written_in_flu_or_frd():
    # The same physical cameras: a drone's forward camera rolled 30 deg, a down camera, and a world
    # camera on the ceiling looking down. FLU pitch +90 (nose down) is FRD pitch -90; y and z flip.
    flu = {
        "entities": {
            "world": {"sensors": [{"name": "ceil", "id": 9, "pose": {"pos": [1, 2, 3], "rpy_deg": [0, 90, 0]}}]},
            "d": {
                "sensors": [
                    {"name": "fwd", "id": 1, "pose": {"pos": [0.1, 0.02, -0.03], "rpy_deg": [30, 0, 0]}},
                    {"name": "down", "id": 2, "pose": {"pos": [0.05, 0.0, -0.03], "rpy_deg": [0, 90, 0]}},
                ]
            },
        }
    }
    frd = {
        "conventions": {"world": "NED", "body": "FRD"},
        "entities": {
            "world": {"sensors": [{"name": "ceil", "id": 9, "pose": {"pos": [2, 1, -3], "rpy_deg": [0, -90, 90]}}]},
            "d": {
                "sensors": [
                    {"name": "fwd", "id": 1, "pose": {"pos": [0.1, -0.02, 0.03], "rpy_deg": [30, 0, 0]}},
                    {"name": "down", "id": 2, "pose": {"pos": [0.05, 0.0, 0.03], "rpy_deg": [0, -90, 0]}},
                ]
            },
        },
    }
    a, b = parse_world(flu), parse_world(frd)
    for sid in (1, 2, 9):
        np.testing.assert_allclose(
            a.sensors[sid].T_entity_sensor.as_matrix(), b.sensors[sid].T_entity_sensor.as_matrix(), atol=1e-12
        )
    # The forward camera rolled 30 deg right-side down: it looks along +x and the image's right
    # (optical x) points to the drone's right (FLU -y), lowered by 30 deg.
    R = b.sensors[1].T_entity_sensor.rotation
    np.testing.assert_allclose(R.apply([0, 0, 1]), [1, 0, 0], atol=1e-12)
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    np.testing.assert_allclose(R.apply([1, 0, 0]), [0, -c, -s], atol=1e-12)
    # The down camera: optical axis down, image top (optical -y) towards the nose.
    R = b.sensors[2].T_entity_sensor.rotation
    np.testing.assert_allclose(R.apply([0, 0, 1]), [0, 0, -1], atol=1e-12)
    np.testing.assert_allclose(R.apply([0, -1, 0]), [1, 0, 0], atol=1e-12)
