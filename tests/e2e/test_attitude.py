"""End to end: a node process whose autopilot does not stream ATTITUDE asks for it
(MAV_CMD_SET_MESSAGE_INTERVAL), and then uses the autopilot's roll and pitch to pick the right solution
of a single tag seen with IPPE's flip chosen, with no pose estimate to resolve it otherwise."""

import time
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import load_world
from atlas_onboard.sim.autopilot import SimAutopilot
from tests.e2e.helpers import NodeProcess, Peer, free_udp_port, wait_for, write_world
from tests.helpers import observe, pose

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group

TRUTH = {"world": RigidTransform.identity(), "d1": pose([1.0, 2.0, 3.0], [6, -9, 90])}
FLIP = RigidTransform.from_rotation(Rotation.from_euler("x", 20, degrees=True))  # about the marker's x axis


def world_doc(peer_port: int, ap_port: int) -> dict:
    return {
        "entities": {
            # A world-fixed camera 4.2 m up looking down at a drone with a tag on top.
            "world": {"sensors": [{"name": "ceiling", "id": 10, "pose": {"pos": [1, 2, 4.2], "rpy_deg": [0, 90, 0]}}]},
            "d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
        },
        "nodes": {
            "d1": {
                "system_id": 1,
                "autopilot": {"url": f"udpout:127.0.0.1:{ap_port}"},
                "peers": [{"url": f"udpin:127.0.0.1:{peer_port}"}],
                "status_interval_s": 1,
            },
            "world": {"system_id": 250},
        },
    }


def test_node_asks_for_attitude_and_uses_it_to_undo_a_flip(tmp_path):
    # An autopilot that streams nothing until asked (attitude_hz 0), then the truth with noise and bias.
    ap = SimAutopilot(system_id=1, attitude=lambda _t: TRUTH["d1"].rotation, attitude_hz=0.0).start()
    port = free_udp_port()
    path = write_world(tmp_path, world_doc(port, ap.port))
    world = load_world(path)
    node = NodeProcess(path, "d1")
    peer = Peer(port, system_id=250)
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0, 60), node.log()  # the node is up
        assert wait_for(lambda: ap.attitude_interval_requests > 0, 10), node.log()
        assert wait_for(lambda: ap.attitude_sent > 10, 5)
        time.sleep(0.1)
        for _ in range(100):  # about 2 s of a 50 Hz camera at most
            now_us = int(time.time() * 1e6)
            true = observe(world, TRUTH, 10, 5, sigma_m=0.02, capture_time_us=now_us)
            flipped = observe(world, TRUTH, 10, 5, sigma_m=0.02, capture_time_us=now_us, T_noise=FLIP)
            peer.send(_with_alt(flipped, true), world.fingerprint())
            time.sleep(0.02)
            if len(ap.snapshot()) >= 10:
                break
        got = ap.snapshot()
        assert len(got) >= 5, node.log()[-3000:]
        # Every pose the autopilot got is the truth (NED: north 2, east 1, down -3), not the flip's.
        for r in got:
            np.testing.assert_allclose(r.xyz_m, [2.0, 1.0, -3.0], atol=0.01)
    finally:
        peer.close()
        node.stop()
        ap.stop()
    counters = node.final_counters()
    assert counters.get("attitude_alt", 0) >= 5 and counters.get("attitude_requested", 0) >= 1, counters


def _with_alt(flipped, true):
    """The flipped observation carrying the true one as IPPE's other solution, as ambiguous as IPPE says."""
    return replace(
        flipped,
        ambiguity_ratio=0.9,
        p_sensor_marker_alt_m=true.p_sensor_marker_m,
        q_sensor_marker_alt_wxyz=true.q_sensor_marker_wxyz,
    )
