"""Relative poses in a real node process: two drones that see each other but no world marker, and
the node publishes the second's pose in the first's frame (ATLAS_FUSED_POSE with frame_index)."""

import time

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from tests.e2e.helpers import start_node_with_peer
from tests.helpers import observe, pose

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group


def world_doc(peer_port, ap_port, relative):
    return {
        "fusion": {"relative_poses": relative},
        "entities": {
            "world": {"markers": [{"id": 0, "size_m": 0.2, "pose": {"pos": [0, 0, 0]}}]},
            "d1": {"markers": [{"id": 1, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
            "lead": {"sensors": [{"name": "rear", "id": 20, "pose": {"pos": [-0.1, 0, 0], "rpy_deg": [0, 0, 180]}}]},
            "follower": {"markers": [{"id": 7, "size_m": 0.15, "pose": {"pos": [0.12, 0, 0], "rpy_deg": [0, 90, 0]}}]},
        },
        "nodes": {
            "d1": {
                "system_id": 1,
                "autopilot": {"url": f"udpout:127.0.0.1:{ap_port}"},
                "peers": [{"url": f"udpin:127.0.0.1:{peer_port}"}],
                "fused_rate_hz": 10,
            },
            "lead": {"system_id": 250},  # the tests' peer runs the lead, whose rear camera sees the follower
        },
    }


TRUTH = {
    "world": RigidTransform.identity(),
    "d1": pose([0.0, 0.0, 1.0], [0, 0, 0]),
    "lead": pose([5.0, 3.0, 1.5], [0, 0, 40]),
    "follower": pose([3.2, 1.6, 1.3], [0, 0, 35]),
}


def fused_messages(tmp_path, relative):
    world, ap, node, peer = start_node_with_peer(tmp_path, lambda port, ap_port: world_doc(port, ap_port, relative))
    got = []
    try:
        t0 = int(time.time() * 1e6)
        for k in range(15):  # the lead's rear camera sees the follower's tag, 20 Hz
            peer.send(observe(world, TRUTH, 20, 7, sigma_m=0.01, capture_time_us=t0 + k * 50_000), world.fingerprint())
            deadline = time.monotonic() + 0.05
            while time.monotonic() < deadline:
                msg = peer.conn.recv_match(type="ATLAS_FUSED_POSE", blocking=True, timeout=0.01)
                if msg is not None:
                    got.append(msg)
    finally:
        peer.close()
        assert node.stop() == 0
        ap.stop()
    return world, got, ap


def test_a_group_without_world_is_published_relative_to_its_first_entity(tmp_path):
    world, got, ap = fused_messages(tmp_path, relative=True)
    names = world.entity_names
    rel = [m for m in got if m.entity_index == names.index("follower")]
    assert rel, [(m.entity_index, m.frame_index) for m in got]
    assert all(m.frame_index == names.index("lead") for m in rel)
    expected = TRUTH["lead"].inv() * TRUTH["follower"]
    m = rel[-1]
    np.testing.assert_allclose([m.x, m.y, m.z], expected.translation, atol=1e-5)
    w, x, y, z = m.q
    assert (Rotation.from_quat([x, y, z, w]).inv() * expected.rotation).magnitude() < 1e-5
    assert m.level == 1 and m.n_observations == 1
    assert ap.snapshot() == []  # d1 itself has no pose: nothing to its autopilot
    # The group's first entity is the frame, not a pose of its own; no one has a world pose.
    assert not any(mm.entity_index == names.index("lead") for mm in got)
    assert not any(mm.frame_index == 0 for mm in got)


def test_without_the_option_nothing_unconnected_is_published(tmp_path):
    _, got, _ = fused_messages(tmp_path, relative=False)
    assert got == []
