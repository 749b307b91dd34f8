"""The autopilot link dies and comes back (a TCP autopilot that restarts): output resumes by itself."""

import time

import numpy as np
import pytest

from atlas_onboard.config import load_world
from atlas_onboard.sim.autopilot import SimAutopilot
from tests.e2e.helpers import NodeProcess, Peer, free_udp_port, wait_for, write_world
from tests.e2e.test_autopilot import TRUTH, world_doc
from tests.helpers import observe

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group


def test_autopilot_tcp_link_restart(tmp_path):
    ap = SimAutopilot(system_id=1, tcp=True).start()
    port = ap.port
    peer_port = free_udp_port()
    doc = world_doc(peer_port, port)
    doc["nodes"]["d1"]["autopilot"]["url"] = f"tcp:127.0.0.1:{port}"
    path = write_world(tmp_path, doc)
    world = load_world(path)
    node = NodeProcess(path, "d1")
    peer = Peer(peer_port, 250)
    stop = False

    def feed_for(seconds):
        end = time.time() + seconds
        while time.time() < end and not stop:
            peer.send(observe(world, TRUTH, 10, 5, capture_time_us=int(time.time() * 1e6)), world.fingerprint())
            time.sleep(0.03)

    try:
        assert wait_for(lambda: ap.connections == 1 and len(ap.heartbeats_from) > 0), node.log()
        feed_for(0.5)
        assert len(ap.snapshot()) > 5
        ap.stop()  # the autopilot reboots: its end of the link is gone
        feed_for(1.0)
        ap2 = SimAutopilot(system_id=1, port=port, tcp=True).start()
        end = time.time() + 15
        while time.time() < end and len(ap2.snapshot()) < 5:
            feed_for(0.2)
        assert len(ap2.snapshot()) >= 5, node.log()[-2000:]
        np.testing.assert_allclose(ap2.snapshot()[-1].xyz_m, [2.0, 1.0, -3.0], atol=1e-5)
        assert node.proc.poll() is None
    finally:
        stop = True
        peer.close()
        assert node.stop() == 0
        ap.stop()
    c = node.final_counters()
    assert c.get("autopilot_reconnects", 0) >= 1
