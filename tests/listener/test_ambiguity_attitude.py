"""MegaTag2-style: the autopilot's roll and pitch pick a single tag's IPPE solution. Rendered
images of a small tag far away and nearly face-on (where IPPE flips), detected by the real detector,
resolved by the listener with a noisy gravity reference and no pose estimate at all."""

import math

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import parse_world
from atlas_onboard.core.attitude import up_in_body
from atlas_onboard.core.markerdata import AltState
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.render import Camera, MarkerView, render
from atlas_onboard.listener import EdgeUpdate, Listener
from atlas_onboard.node.setup import make_graph

K = np.array([[900.0, 0.0, 639.5], [0.0, 900.0, 359.5], [0.0, 0.0, 1.0]])
CAM = Camera(1280, 720, K, np.zeros(5))
SIZE_M = 0.15
FLIP_DEG = 10.0
AUTOPILOT_NOISE_DEG = 1.0


def scene():
    world = parse_world(
        {
            "entities": {
                "world": {"markers": [{"id": 7, "size_m": SIZE_M, "pose": {}}]},
                "cam": {"sensors": [{"name": "c", "id": 1, "pose": {"rpy_deg": [0, 80, 0]}}]},
            }
        }
    )
    det = Detector(world.sensors[1], world, Calibration(1280, 720, K, np.zeros(5)), decimate=1.0, track=False)
    return world, det


def angle_deg(a: Rotation, b: Rotation) -> float:
    return float(np.degrees((a.inv() * b).magnitude()))


def test_flipped_single_tags_are_corrected_by_the_autopilots_tilt_never_published():
    world, det = scene()
    listener = Listener(world, make_graph(world, "cam"))
    R_es = world.sensors[1].T_entity_sensor.rotation
    R_wm = world.markers[7].T_entity_marker.rotation
    rng = np.random.default_rng(5)
    corrected = decided = flips = 0
    for k in range(40):
        tilt = rng.uniform(4.0, 12.0)
        R_sm = Rotation.from_euler("zxz", [rng.uniform(0, 360), 180 + tilt, rng.uniform(0, 360)], degrees=True)
        T_sm = RigidTransform.from_components([rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3), 7.0], R_sm)
        img = render(CAM, [MarkerView("tag36h11", 7, SIZE_M, T_sm)], noise_sigma=4.0, seed=k)
        R_wb_true = R_wm * R_sm.inv() * R_es.inv()  # the body's true attitude
        # The autopilot's view: the truth tilted by its own error, under a heading of its own.
        err = Rotation.from_rotvec(np.r_[rng.normal(0, AUTOPILOT_NOISE_DEG, 2), 0.0] * math.pi / 180)
        up = up_in_body(Rotation.from_euler("z", 123, degrees=True) * err * R_wb_true)
        listener.set_attitude("cam", lambda t_us, up=up: up)
        for md in det.detect(img, capture_time_us=1_000 + k):
            if md.alt_state() is not AltState.VALID:
                continue
            w, x, y, z = md.q_sensor_marker_wxyz
            flipped = angle_deg(Rotation.from_quat([x, y, z, w]), R_sm) > FLIP_DEG
            flips += flipped
            before = listener.counters.snapshot()
            result = listener.accept_many([(md, k * 1_000_000)])[0]
            notes = {n for n, v in listener.counters.items() if v > before.get(n, 0)}
            if not notes & {"attitude_primary", "attitude_alt"}:
                continue  # gravity could not tell them apart: as without attitude
            decided += 1
            edge = listener.edge_from(md)
            assert result is None and isinstance(edge, EdgeUpdate)
            R_edge_true = R_es * R_sm * R_wm.inv()  # T_cam_world
            assert angle_deg(Rotation.from_quat(edge.q_a_b_xyzw), R_edge_true) < FLIP_DEG, f"frame {k}: wrong pick"
            corrected += flipped and "attitude_alt" in notes
    summary = f"{flips} flipped detections, {corrected} corrected, {decided} of 40 decided by gravity"
    assert flips >= 5 and corrected >= 0.6 * flips and decided >= 25, summary


def test_without_attitude_nothing_changes():
    world, det = scene()
    a, b = Listener(world, make_graph(world, "cam")), Listener(world, make_graph(world, "cam"))
    b.set_attitude("cam", lambda t_us: None)  # an attitude stream that does not cover the capture
    R_sm = Rotation.from_euler("zxz", [30, 188, 10], degrees=True)
    img = render(CAM, [MarkerView("tag36h11", 7, SIZE_M, RigidTransform.from_components([0.1, 0, 5.0], R_sm))], seed=1)
    mds = det.detect(img, capture_time_us=5)
    assert mds
    for md in mds:
        ea, eb = a.edge_from(md), b.edge_from(md)
        assert type(ea) is type(eb)
        if isinstance(ea, EdgeUpdate):
            np.testing.assert_array_equal(ea.q_a_b_xyzw, eb.q_a_b_xyzw)
    b.accept_many([(md, 0) for md in mds])
    assert b.counters["attitude_unavailable"] == len([m for m in mds if m.alt_state() is AltState.VALID])
