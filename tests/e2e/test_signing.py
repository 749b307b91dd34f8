"""MAVLink 2 signing end to end: a node whose peer link requires signatures, a signed and an unsigned
peer, a replay; the autopilot link stays unsigned. Plus observations carried in TUNNEL."""

import os
import subprocess
import sys
import time

import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform

from atlas_onboard.config import load_world
from atlas_onboard.sim.autopilot import SimAutopilot
from tests.e2e.helpers import NodeProcess, Peer, free_udp_port, wait_for, write_world
from tests.e2e.test_autopilot import world_doc
from tests.helpers import observe, pose

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group

TRUTH_A = {"world": RigidTransform.identity(), "d1": pose([1.0, 2.0, 3.0], [0, 0, 90])}
TRUTH_B = {"world": RigidTransform.identity(), "d1": pose([-2.0, 0.0, 1.0], [0, 0, 0])}


def key_file(tmp_path, key, mode=0o600):
    path = tmp_path / "swarm.key"
    path.write_bytes(key)
    os.chmod(path, mode)
    return path


def test_unsigned_wrongly_signed_and_replayed_observations_change_nothing(tmp_path):
    key = os.urandom(32)
    ap = SimAutopilot(system_id=1).start()
    port = free_udp_port()
    doc = world_doc(port, ap.port, extra_node={"signing": {"key_file": str(key_file(tmp_path, key)), "require": True}})
    doc["nodes"]["d1"]["state_dir"] = str(tmp_path / "state")
    path = write_world(tmp_path, doc)
    world = load_world(path)
    node = NodeProcess(path, "d1")
    signed, unsigned, wrong = Peer(port, 250, key=key), Peer(port, 251), Peer(port, 252, key=os.urandom(32))
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()  # unsigned autopilot link
        fp = world.fingerprint()
        now_us = int(time.time() * 1e6)
        # Unsigned and wrongly signed observations claim the drone is at B: they must change nothing.
        for k in range(5):
            unsigned.send(observe(world, TRUTH_B, 10, 5, capture_time_us=now_us + k), fp)
            wrong.send(observe(world, TRUTH_B, 10, 5, capture_time_us=now_us + k), fp)
        time.sleep(0.4)
        assert ap.snapshot() == []
        frames = [signed.send(observe(world, TRUTH_A, 10, 5, capture_time_us=now_us + 10 + k), fp) for k in range(5)]
        assert wait_for(lambda: len(ap.snapshot()) >= 1), node.log()
        time.sleep(0.3)  # let A's edge expire, then replay a signed frame claiming A's old pose
        n = len(ap.snapshot())
        for f in frames:
            signed.raw(f)
        time.sleep(0.4)
        assert len(ap.snapshot()) == n, "a replayed signed frame was used"
        for rec in ap.snapshot():
            np.testing.assert_allclose(rec.xyz_m, [2.0, 1.0, -3.0], atol=1e-5)  # A in NED, never B
    finally:
        for p in (signed, unsigned, wrong):
            p.close()
        assert node.stop() == 0
        ap.stop()
    c = node.final_counters()
    assert c["peer0_rejected_unsigned_or_bad_signature"] >= 10  # 5 unsigned + 5 wrongly signed
    assert c["peer0_rejected_bad_signature"] >= 15  # those 10, and the 5 replays
    assert c["accepted"] == 5
    # Decoded: the five signed ones; no unsigned, wrongly signed or replayed frame got that far.
    assert c["peer0_rx_atlas_observation"] == 5
    assert list((tmp_path / "state").glob("signing-*.json")), "signing timestamp not persisted"


def test_key_file_readable_by_others_is_refused(tmp_path):
    path = write_world(
        tmp_path,
        world_doc(
            free_udp_port(),
            free_udp_port(),
            extra_node={"signing": {"key_file": str(key_file(tmp_path, b"k" * 32, 0o644))}},
        ),
    )
    proc = subprocess.run(
        [sys.executable, "-m", "atlas_onboard", "run", "--config", str(path), "--entity", "d1"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "readable by group or others" in lines[0] and "Traceback" not in proc.stderr


def test_observations_in_tunnel_messages(tmp_path):
    ap = SimAutopilot(system_id=1).start()
    port = free_udp_port()
    path = write_world(tmp_path, world_doc(port, ap.port, extra_node={"tunnel": True}))
    world = load_world(path)
    node = NodeProcess(path, "d1")
    peer = Peer(port, 250)
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
        from atlas_onboard.mavlink import codec

        now_us = int(time.time() * 1e6)
        for k in range(5):
            payload = codec.tunnel_payload(
                observe(world, TRUTH_A, 10, 5, capture_time_us=now_us + k), world.fingerprint()
            )
            msg = peer.d.MAVLink_tunnel_message(
                0, 0, codec.TUNNEL_PAYLOAD_OBSERVATION, len(payload), list(payload) + [0] * (128 - len(payload))
            )
            peer.raw(msg.pack(peer.conn.mav))
            time.sleep(0.02)
        assert wait_for(lambda: len(ap.snapshot()) >= 1), node.log()
        np.testing.assert_allclose(ap.snapshot()[-1].xyz_m, [2.0, 1.0, -3.0], atol=1e-5)
    finally:
        peer.close()
        node.stop()
        ap.stop()
