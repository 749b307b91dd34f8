"""End to end over 127.0.0.1: a real node process, a peer sending observations, a simulated autopilot.

The numbers the autopilot receives are checked against ground truth in its own frames (NED/FRD).
"""

import math
import time

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from tests.e2e.helpers import start_node_with_peer, wait_for
from tests.helpers import observe, pose

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group

MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD = 20, 12


def world_doc(peer_port, ap_port, output="vision_position_estimate", extra_node=None):
    return {
        # No edge ageing: the covariance the autopilot gets is then exactly the observation's, whatever
        # the few milliseconds between capture and evaluation (ageing is tested in the core and sim).
        "fusion": {"age_sigma_m_per_s": 0, "age_sigma_deg_per_s": 0},
        "entities": {
            # A world-fixed camera 4 m up looking down, and a drone with a tag on top.
            "world": {"sensors": [{"name": "ceiling", "id": 10, "pose": {"pos": [0, 0, 4], "rpy_deg": [0, 90, 0]}}]},
            "d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
        },
        "nodes": {
            "d1": {
                "system_id": 1,
                "autopilot": {"url": f"udpout:127.0.0.1:{ap_port}", "output": output},
                "peers": [{"url": f"udpin:127.0.0.1:{peer_port}", **(extra_node or {})}],
                "status_interval_s": 1,
            },
            "world": {"system_id": 250},  # the node of the ceiling camera: the tests' peer
        },
    }


@pytest.fixture
def rig(tmp_path, request):
    output = getattr(request, "param", "vision_position_estimate")
    world, ap, node, peer = start_node_with_peer(tmp_path, lambda port, ap_port: world_doc(port, ap_port, output))
    yield world, ap, node, peer
    peer.close()
    node.stop()
    ap.stop()


TRUTH = {"world": RigidTransform.identity(), "d1": pose([1.0, 2.0, 3.0], [0, 0, 90])}


def feed(world, peer, n=10, truth=TRUTH, period=0.02, t0_us=None):
    t0_us = t0_us or int(time.time() * 1e6)
    for k in range(n):
        peer.send(observe(world, truth, 10, 5, sigma_m=0.02, capture_time_us=t0_us + k * 20000), world.fingerprint())
        time.sleep(period)
    return t0_us


def expected_covariance(world, truth=TRUTH):
    """What the pure core makes of the test's observation, in MAVLink's 21 NED/FRD values."""
    from atlas_onboard.listener import Listener
    from atlas_onboard.mavlink import covariance
    from atlas_onboard.node.setup import make_graph

    graph = make_graph(world)
    listener = Listener(world, graph)
    assert listener.accept(observe(world, truth, 10, 5, sigma_m=0.02, capture_time_us=1), 0) is None
    cov = graph.evaluate(0).poses["d1"].covariance
    return covariance.covariance_upper_triangle(covariance.covariance_ned_frd(cov))


def test_vision_position_estimate_matches_truth_in_ned(rig):
    world, ap, node, peer = rig
    t0 = feed(world, peer)
    assert wait_for(lambda: len(ap.snapshot()) >= 5), node.log()
    for rec in ap.snapshot():
        assert rec.kind == "VISION_POSITION_ESTIMATE"
        # ENU (1, 2, 3) with yaw 90 (nose north) arrives as NED (2, 1, -3) with yaw 0.
        np.testing.assert_allclose(rec.xyz_m, [2.0, 1.0, -3.0], atol=1e-5)
        np.testing.assert_allclose(rec.rpy_rad, [0.0, 0.0, 0.0], atol=1e-5)
        # The covariance is the 6x6 the core propagates for this observation (camera position
        # sigma 2 cm, carried through the mountings to the drone's centre), turned to NED/FRD.
        np.testing.assert_allclose(rec.covariance, expected_covariance(world), rtol=1e-4, atol=1e-12)
        cov = np.array(rec.covariance)
        assert np.all(cov[[0, 6, 11]] >= 0.02**2 * (1 - 1e-5))  # at least the camera's own sigma
        assert np.all(cov[[15, 18, 20]] > 0) and np.all(np.isfinite(cov))
        assert t0 <= rec.usec <= t0 + 9 * 20000  # capture time of the newest observation, not send time
        assert (rec.src_system, rec.src_component) == (1, 197)
        assert rec.reset_counter == ap.snapshot()[0].reset_counter  # no reset within one stream
    assert ap.heartbeats_from[(1, 197)] >= 1


@pytest.mark.parametrize("rig", ["odometry"], indirect=True)
def test_odometry_matches_truth_in_local_frd(rig):
    world, ap, node, peer = rig
    truth = {"world": RigidTransform.identity(), "d1": pose([-0.5, 1.5, 2.0], [5, -3, 30])}
    t0 = feed(world, peer, truth=truth)
    assert wait_for(lambda: len(ap.snapshot()) >= 5), node.log()
    for r in ap.snapshot():
        # pose_covariance: the 6x6 the core propagates, in LOCAL_FRD / BODY_FRD, as for the other message.
        np.testing.assert_allclose(r.covariance, expected_covariance(world, truth), rtol=1e-4, atol=1e-12)
        assert t0 <= r.usec <= t0 + 9 * 20000  # capture time of the newest observation
    rec = ap.snapshot()[-1]
    assert rec.kind == "ODOMETRY"
    assert (rec.frame_id, rec.child_frame_id, rec.estimator_type) == (MAV_FRAME_LOCAL_FRD, MAV_FRAME_BODY_FRD, 2)
    np.testing.assert_allclose(rec.xyz_m, [1.5, -0.5, -2.0], atol=1e-5)
    w, x, y, z = rec.q_wxyz
    R_ned_frd = Rotation.from_quat([x, y, z, w])
    # Expected: NED/FRD attitude of an ENU/FLU body with roll 5, pitch -3, yaw 30 -> roll 5, pitch 3, yaw 60.
    np.testing.assert_allclose(R_ned_frd.as_euler("ZYX", degrees=True), [60.0, 3.0, 5.0], atol=1e-3)
    assert 1 <= rec.quality <= 100


def test_output_stops_when_the_peer_goes_silent_and_resumes(rig):
    """Told in order, whatever the machine's load (how soon the edges expire is the publisher's, tested
    in tests/core/test_publisher.py): the pose is found, then lost once the peer is silent, nothing is sent
    after it is said lost, and it is sent again, with a new reset_counter, when the peer resumes."""
    world, ap, node, peer = rig
    feed(world, peer, n=10)
    assert wait_for(lambda: len(ap.snapshot()) >= 5), node.log()
    lost = b"atlas d1: pose lost"
    assert wait_for(lambda: any(t.startswith(lost) for t in ap.statustexts)), (ap.statustexts, node.log())
    sent_before_loss = ap.statustext_poses[next(i for i, t in enumerate(ap.statustexts) if t.startswith(lost))]
    assert len(ap.snapshot()) == sent_before_loss, "the node kept sending a pose it no longer has"
    first = ap.snapshot()[0].reset_counter
    feed(world, peer, n=5)
    assert wait_for(lambda: len(ap.snapshot()) > sent_before_loss), "output did not resume"
    assert ap.snapshot()[-1].reset_counter == (first + 1) % 256  # lost then found: the autopilot is told to reset
    said = [t[10:20] for t in ap.statustexts if t.startswith(b"atlas d1: pose")]
    assert said[:2] == [b"pose found", b"pose lost"], said


def test_bad_input_changes_nothing_and_is_counted(rig):
    world, ap, node, peer = rig
    fp = world.fingerprint()
    feed(world, peer, n=5)
    assert wait_for(lambda: len(ap.snapshot()) >= 3), node.log()
    good = observe(world, TRUTH, 10, 5, sigma_m=0.02, capture_time_us=int(time.time() * 1e6))
    rng = np.random.default_rng(0)
    peer.raw(rng.integers(0, 256, 300, dtype=np.uint8).tobytes())  # random bytes
    frame = peer.send(good, fp)  # a valid frame, then truncated copies of it
    for cut in (3, 10, len(frame) - 1):
        peer.raw(frame[:cut])
    for field in ("x", "y", "z", "sigma"):
        for value in (math.nan, math.inf, -math.inf, 1e30):
            peer.send(good, fp, **{field: value})
    peer.send(good, fp, q=[0.0, 0.0, 0.0, 0.0])
    peer.send(good, fp, q=[math.nan, 0.0, 0.0, 1.0])
    peer.send(good, fp, q=[math.inf, 0.0, 0.0, 1.0])
    peer.send(good, fp, reprojection_error=-1.0)
    peer.send(good, fp, ambiguity=2.0)
    # The other planar solution partly infinite, or NaN beside finite values: ignored, the record
    # stands on its (good) chosen solution.
    peer.send(good, fp, x_alt=math.inf, y_alt=0.0, z_alt=1.0, q_alt=[1.0, 0.0, 0.0, 0.0])
    peer.send(good, fp, x_alt=math.nan, y_alt=0.0, z_alt=1.0, q_alt=[1.0, 0.0, 0.0, 0.0])
    peer.send(good, fp, time_usec=0)  # 1970
    peer.send(good, fp, time_usec=good.capture_time_us + 10**13)  # four months ahead
    peer.send(good, fp, sigma=-0.1)
    peer.send(good, fp, sensor_id=999)
    peer.send(good, fp, marker_id=999)
    peer.send(good, fp ^ 0xFFFF)  # another world file
    peer.send(good, fp, format_version=9)
    time.sleep(0.5)
    for rec in ap.snapshot():  # the estimate never moved
        np.testing.assert_allclose(rec.xyz_m, [2.0, 1.0, -3.0], atol=1e-5)
    assert node.proc.poll() is None, "the node died"
    code = node.stop()
    assert code == 0
    c = node.final_counters()
    assert c["rejected_non_finite"] >= 10  # nan and inf in x, y, z, sigma; inf in q
    assert c["rejected_bad_quality"] == 2 and c["rejected_bad_stamp"] == 2
    assert c["alt_ignored"] == 2
    assert c["rejected_out_of_range"] >= 3  # 1e30 in x, y, z
    assert c["rejected_zero_quaternion"] == 1
    assert c["rejected_bad_sigma"] == 2  # -0.1 and 1e30
    assert c["rejected_unknown_sensor"] == 1 and c["rejected_unknown_marker"] == 1
    assert c["rejected_wrong_fingerprint"] == 1 and c["rejected_bad_version"] == 1
    assert c["peer0_rejected_bad_data"] >= 1


def test_reset_counter_signals_a_restart(tmp_path):
    """A restarted node (same state_dir) starts one past the counter the autopilot last saw, so the
    autopilot resets to vision instead of fusing a jump across the restart as a measurement."""
    from atlas_onboard.config import load_world
    from atlas_onboard.sim.autopilot import SimAutopilot
    from tests.e2e.helpers import NodeProcess, Peer, free_udp_port, write_world

    ap = SimAutopilot(system_id=1).start()
    port = free_udp_port()
    doc = world_doc(port, ap.port)
    doc["nodes"]["d1"]["state_dir"] = str(tmp_path / "state")
    path = write_world(tmp_path, doc)
    world = load_world(path)
    counters = []
    try:
        for _ in range(2):
            n_before = len(ap.snapshot())
            node = NodeProcess(path, "d1")
            peer = Peer(port, system_id=250)
            try:
                assert wait_for(lambda n=node: n.proc.poll() is None and "running" in n.log(), 10), node.log()
                feed(world, peer, n=5)
                assert wait_for(lambda k=n_before: len(ap.snapshot()) >= k + 3), node.log()
            finally:
                peer.close()
                assert node.stop() == 0
            counters.append({r.reset_counter for r in ap.snapshot()[n_before:]})
    finally:
        ap.stop()
    (first,), (second,) = counters  # one counter per process: no reset within a stream
    assert second == (first + 1) % 256


def test_a_stopping_node_says_pose_lost(rig):
    """SIGTERM while the pose is fresh (observations still arriving): "pose lost" goes out."""
    import threading

    world, ap, node, peer = rig
    stop = threading.Event()

    def keep_feeding():
        while not stop.is_set():
            feed(world, peer, n=1, period=0.02)

    feeder = threading.Thread(target=keep_feeding, daemon=True)
    feeder.start()
    try:
        assert wait_for(lambda: any(b"pose found" in t for t in ap.statustexts), 10), node.log()
        assert node.stop() == 0
        assert wait_for(lambda: any(b"pose lost" in t for t in ap.statustexts), 2), ap.statustexts
    finally:
        stop.set()
        feeder.join(2)
    assert "pose lost (node stopping)" in node.log()


def test_ground_station_sees_pose_state_and_named_values(tmp_path):
    """HEARTBEAT system_status STANDBY before the first pose, ACTIVE with it, CRITICAL once lost;
    NAMED_VALUE_FLOAT on the peer (GCS) link with the pose's sigma, detections/s, latency, peers."""
    import threading

    from atlas_onboard.listener import Listener
    from atlas_onboard.node.setup import make_graph
    from tests.e2e.helpers import start_node_with_peer

    def doc_for(port, ap_port):
        doc = world_doc(port, ap_port)
        doc["nodes"]["d1"]["heartbeat_hz"] = 5
        return doc

    world, ap, node, peer = start_node_with_peer(tmp_path, doc_for)
    states = lambda: [s for key, s in ap.heartbeat_states if key == (1, 197)]  # noqa: E731
    stop = threading.Event()
    feeder = threading.Thread(target=lambda: [feed(world, peer, n=1) for _ in iter(stop.is_set, True)], daemon=True)
    values: dict[str, float] = {}
    try:
        assert wait_for(lambda: 3 in states(), 5), states()
        feeder.start()
        assert wait_for(lambda: 4 in states(), 5), (states(), node.log())
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not (
            math.isfinite(values.get("atl_sigma", math.nan)) and values.get("atl_peers")
        ):
            msg = peer.conn.recv_match(type="NAMED_VALUE_FLOAT", blocking=True, timeout=0.2)
            if msg is not None:
                values[msg.name] = msg.value
        stop.set()
        feeder.join(2)
        assert wait_for(lambda: states()[-1] == 5, 5), states()
    finally:
        stop.set()
        peer.close()
        node.stop()
        ap.stop()
    s = states()
    assert s[0] == 3 and s.index(3) < s.index(4) < len(s) - 1 - s[::-1].index(5)  # standby, active, critical
    graph = make_graph(world)
    assert Listener(world, graph).accept(observe(world, TRUTH, 10, 5, sigma_m=0.02, capture_time_us=1), 0) is None
    assert values["atl_sigma"] == pytest.approx(graph.evaluate(0).poses["d1"].sigma_m, rel=1e-5)
    assert values["atl_det_hz"] == 0.0  # no camera of its own: the observations are the peer's
    assert values["atl_peers"] == 1.0
    assert set(values) == {"atl_sigma", "atl_det_hz", "atl_lat_ms", "atl_peers"}
