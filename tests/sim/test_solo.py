"""A solo node's simulated autopilot (:mod:`atlas_onboard.sim.solo`): it streams its drone's attitude
as a real autopilot does, and the node uses it for its single tags (here the relay drone's view of its
leader's marker, with the leader's views played)."""

import time

import pytest

from atlas_onboard.sim import peerplay

pytestmark = pytest.mark.realtime  # node processes in real time

SECONDS = 5.0


def test_the_relay_drones_autopilot_streams_its_attitude_and_the_node_checks_its_leaders_tag_with_it():
    node = peerplay.start("relay", SECONDS + 0.5)
    leader = None
    try:
        epoch = node.start_scenario()
        leader = peerplay.honest_leader(node)
        leader.run_between(epoch, epoch + SECONDS + 0.5)
        time.sleep(max(0.0, epoch + SECONDS + 0.3 - time.time()))
    finally:
        if leader is not None:
            leader.join()
        assert node.stop() == 0, node.log[-3000:]
    c = node.final_counters()
    # 25 Hz from the scenario's start: the node heard most of them.
    assert c.get("autopilot_rx_attitude", 0) >= 0.5 * 25 * SECONDS, c
    checked = sum(c.get(f"attitude_{v}", 0) for v in ("primary", "alt", "both", "neither"))
    assert checked >= 10, sorted((k, v) for k, v in c.items() if "attitude" in k or "ambig" in k)
