"""The detector on hard frames, against ground truth: markers cut by the image border, single
markers over the whole of a strongly distorted 640x480 image with noise and blur on a concrete floor
(the 6x6 covariance must be honest there too), and a world file with one marker moved."""

from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
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


def test_markers_at_or_across_the_image_border_are_never_reported_with_a_wrong_pose():
    """Markers slid across each side of the image, from fully in (a corner a pixel or two from the
    border) to half out: whatever is reported is within 3 sigma of the truth on every axis, and those
    cut by the border are counted as dropped."""
    det = one_tag_detector(decimate=1.0, track=False)
    rng = np.random.default_rng(1)
    checked = 0
    for k in range(28):
        side = k % 4
        distance = rng.uniform(0.6, 1.6)
        rot = Rotation.from_euler("zxz", [rng.uniform(-20, 20), 180 + rng.uniform(0, 35), 0], degrees=True)
        # The marker's half width in pixels, roughly; its centre from a half width inside to a quarter outside.
        half_px = 460 * SIZE / 2 / distance
        inset = half_px * rng.uniform(0.6, 1.3)
        along = rng.uniform(0.3, 0.7)
        u, v = [(inset, along * H), (W - 1 - inset, along * H), (along * W, inset), (along * W, H - 1 - inset)][side]
        T = at_pixel(u, v, distance, rot)
        img = render(CAM, [MarkerView("tag36h11", 7, SIZE, T)], noise_sigma=2.0, seed=k, background_style="concrete")
        for md in det.detect(img, k):
            e, C = pose_error(md, T)
            sigmas = np.sqrt(np.diag(C))
            assert np.all(np.abs(e) <= 3 * sigmas), (k, e, sigmas)
            checked += 1
    assert det.counters["dropped_image_border"] >= 5  # the border case really happened
    assert checked >= 5  # and markers well inside were reported


@pytest.fixture(scope="module")
def whole_image_errors():
    """Single markers anywhere in the distorted image, 0.4-3 m, 0-70 degrees, half of them blurred:
    the errors of what the detector reports against its covariances."""
    det = one_tag_detector(decimate=1.0, track=False)
    rng = np.random.default_rng(0)
    out = []
    for k in range(64):
        distance, angle = rng.uniform(0.4, 3.0), rng.uniform(0.0, 70.0)
        rot = Rotation.from_euler("zxz", [rng.uniform(0, 360), 180 + angle, rng.uniform(0, 360)], degrees=True)
        T = at_pixel(rng.uniform(20, W - 20), rng.uniform(20, H - 20), distance, rot)
        blur = tuple(rng.uniform(0, 3, 2)) if rng.random() < 0.5 else (0.0, 0.0)
        img = render(CAM, [MarkerView("tag36h11", 7, SIZE, T)], noise_sigma=3.0, blur_px=blur, seed=k,
                     background_style="concrete", background_seed=k % 5)  # fmt: skip
        for md in det.detect(img, k):
            if md.ambiguity_ratio > 0.5:  # both solutions go downstream, which resolves them
                continue
            out.append(pose_error(md, T))
    return out


def test_single_marker_covariance_is_neither_cautious_nor_overconfident(whole_image_errors):
    """Honest means both. Over the whole distorted image (blur, noise, 0.4-3 m, 0-70 deg) the
    mean NEES is near its dimension (3 for the position, 6 for the pose; a covariance several times too
    large hides real errors in the autopilot's gate as surely as one too small), and at least 99 % of
    the detections lie within 3 sigma on every axis. The position's lower bound is 1.0, not 1.5: the
    scatter of a sharp oblique edge's points holds the pixel grid's pattern, which the line fit averages
    out, so sharp markers stay cautious (the bench's bar, over more detections, is 1.5)."""
    assert len(whole_image_errors) >= 40
    nees3 = np.array([e[:3] @ np.linalg.solve(C[:3, :3], e[:3]) for e, C in whole_image_errors])
    nees6 = np.array([e @ np.linalg.solve(C, e) for e, C in whole_image_errors])
    within = np.mean([np.abs(e) <= 3 * np.sqrt(np.diag(C)) for e, C in whole_image_errors], axis=0)
    assert np.all(within >= 0.99), within
    assert 1.0 <= nees3.mean() <= 4.5, nees3.mean()
    assert 3.0 <= nees6.mean() <= 9.0, nees6.mean()


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


def test_a_moved_marker_costs_only_itself_and_is_named(caplog):
    world, spots = moved_marker_world(5, 0.10)
    det = Detector(world.sensors[1], world, Calibration(W, H, K, DIST), decimate=1.0, track=False)
    img, T_cam_world = moved_marker_image(spots)
    with caplog.at_level(logging.WARNING, logger="atlas_onboard.detector"):
        found = det.detect(img, 1_000_000)
    # The entity's pose from the three that fit, at marker 1, within millimetres of the truth.
    (md,) = found
    assert md.marker_id == 1
    np.testing.assert_allclose(md.p_sensor_marker_m, T_cam_world.translation, atol=0.005)
    assert dict(det.disagreements) == {5: 1}
    # The offset is where marker 5's own square puts it against where the others do: 10 cm, within the
    # few millimetres of depth error of a 15 cm square seen from 1.6 m.
    offset_cm = float(det.report.explain().split("marker 5 disagrees by ")[1].split(" cm")[0])
    assert 8.0 <= offset_cm <= 12.0
    assert any("marker 5 disagrees" in r.getMessage() for r in caplog.records)
    (status,) = det.take_status()
    assert "marker 5" in status and len(status) <= 50
    # Within the minute: counted again, but no second STATUSTEXT.
    det.detect(moved_marker_image(spots, yaw_deg=5.0)[0], 31_000_000)
    assert det.disagreements[5] == 2 and det.take_status() == []
    det.detect(img, 62_000_000)
    assert len(det.take_status()) == 1


def test_detect_command_says_why_it_printed_nothing(tmp_path):
    import subprocess
    import sys

    import yaml

    cal = tmp_path / "cal.yaml"
    cal.write_text(yaml.safe_dump({
        "image_width": W, "image_height": H, "distortion_model": "plumb_bob",
        "camera_matrix": {"rows": 3, "cols": 3, "data": K.ravel().tolist()},
        "distortion_coefficients": {"rows": 1, "cols": 5, "data": DIST.tolist()},
    }))  # fmt: skip
    spots = {1: (0.0, 0.0), 5: (0.6, 0.0)}
    markers = [{"id": i, "size_m": SIZE, "pose": {"pos": [x + (0.1 if i == 5 else 0.0), y, 0.0]}}
               for i, (x, y) in spots.items()]  # fmt: skip
    sensor = {"name": "cam", "id": 1, "pose": {}, "camera": {"calibration": str(cal)}}
    (tmp_path / "w.yaml").write_text(yaml.safe_dump({"entities": {"world": {"markers": markers},
                                                                  "robot": {"sensors": [sensor]}}}))  # fmt: skip
    img, _ = moved_marker_image(spots)
    cv2.imwrite(str(tmp_path / "two.png"), img)
    cv2.imwrite(str(tmp_path / "none.png"), np.full((H, W), 128, np.uint8))

    def detect(name):
        cmd = [sys.executable, "-m", "atlas_onboard", "detect", "--config", str(tmp_path / "w.yaml"),
               "--sensor", "cam", "--image", str(tmp_path / name)]  # fmt: skip
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60, check=False)

    two = detect("two.png")
    assert two.returncode == 0, two.stderr
    assert "2 tags found (ids 1, 5); none reported: " in two.stdout
    assert "markers 1 and 5 disagree by " in two.stdout
    none = detect("none.png")
    assert none.returncode == 0 and none.stdout.strip() == "frame 0: no tag found"


def test_the_node_sends_a_cameras_warning_as_statustext():
    """The node's small hook: what a camera's detector has to say (a disagreeing marker) goes out as a
    STATUSTEXT with WARNING severity, once."""
    import threading
    import time

    from atlas_onboard.config import NodeConfig
    from atlas_onboard.node.loop import Node
    from tests.node.test_loop import WORLD, FakeTransport

    class Cam:
        name = "c"

        def __init__(self):
            self.pending = ["atlas world: marker 5 disagrees by 10.1 cm"]

        def start(self, deliver):
            pass

        def stop(self):
            pass

        def counters(self):
            return {}

        def map_pose_changed(self, marker_id):
            pass

        def take_status(self):
            out, self.pending = self.pending, []
            return out

    sent = []

    class Transport(FakeTransport):
        def send_status(self, text, severity):
            sent.append((text, severity))

    transport = Transport(time.monotonic_ns)
    node = Node(WORLD, NodeConfig(entity="d1", system_id=7), transport, cameras=[Cam()])
    thread = threading.Thread(target=node.run)
    thread.start()
    try:
        transport.started.wait(5)
        deadline = time.monotonic() + 5
        while not sent and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)
    finally:
        node.stop()
        thread.join(5)
    assert sent == [("atlas world: marker 5 disagrees by 10.1 cm", 4)]
