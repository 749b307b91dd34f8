"""The node's MAVLink transport in a real process: duplicates fused once, a flooding peer limited
without starving the others, TIMESYNC answered, the EKF origin sent until the autopilot has one,
peers seen and lost, clock skew noticed."""

import time

import pytest

from atlas_onboard.config import load_world
from atlas_onboard.mavlink import dialect
from atlas_onboard.sim.autopilot import SimAutopilot
from tests.e2e.helpers import NodeProcess, Peer, free_udp_port, wait_for, write_world
from tests.e2e.test_autopilot import TRUTH, world_doc
from tests.helpers import observe, pose

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group

TRUTH_D2 = {**TRUTH, "d2": pose([0.0, 2.0, 3.0], [0, 0, 0])}  # 1 m from d1, looking along +x at its tag


def start(tmp_path, extra_node=None, autopilot_extra=None, autopilot_type=12):
    ap = SimAutopilot(system_id=1, autopilot_type=autopilot_type).start()
    port = free_udp_port()
    doc = world_doc(port, ap.port, extra_node=extra_node)
    doc["nodes"]["d1"]["autopilot"].update(autopilot_extra or {})
    # A second peer (system 251) runs d2, whose camera sees d1's tag too.
    doc["entities"]["d2"] = {"sensors": [{"name": "cam", "id": 11, "pose": {"pos": [0.1, 0, 0], "rpy_deg": [0, 0, 0]}}]}
    doc["nodes"]["d2"] = {"system_id": 251}
    path = write_world(tmp_path, doc)
    world = load_world(path)
    node = NodeProcess(path, "d1")
    assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
    return ap, port, world, node


def test_duplicates_rate_limit_peer_status_and_skew(tmp_path):
    ap, port, world, node = start(tmp_path, extra_node={"rate_limit_hz": 50})
    a, b = Peer(port, 250), Peer(port, 251)
    fp = world.fingerprint()
    try:
        now_us = int(time.time() * 1e6)
        frame = a.send(observe(world, TRUTH, 10, 5, capture_time_us=now_us), fp)
        a.raw(frame)  # a mesh echo: the very same observation again
        a.raw(frame)
        time.sleep(0.2)
        # Peer a floods 500 observations at once; peer b sends 5 spread over the same time.
        t_flood = time.monotonic()
        for k in range(500):  # stamped as they are sent (an old stamp is refused: bad_stamp)
            a.send(observe(world, TRUTH, 10, 5, capture_time_us=int(time.time() * 1e6) + k), fp)
        flood_s = time.monotonic() - t_flood
        for _ in range(5):
            b.send(observe(world, TRUTH_D2, 11, 5, capture_time_us=int(time.time() * 1e6)), fp)
            time.sleep(0.05)
        # An observation stamped 0.5 s in the past: the clocks disagree (warned, still used); one
        # 3 s in the past is refused.
        b.send(observe(world, TRUTH_D2, 11, 5, capture_time_us=int(time.time() * 1e6) - 500_000), fp)
        b.send(observe(world, TRUTH_D2, 11, 5, capture_time_us=int(time.time() * 1e6) - 3_000_000), fp)
        time.sleep(0.3)
        assert wait_for(lambda: any(b"peer 250 seen" in t for t in ap.statustexts), 5)
        time.sleep(3.5)  # both peers fall silent for longer than 3 s
        assert wait_for(lambda: any(b"peer 250 lost" in t for t in ap.statustexts), 5)
    finally:
        a.close()
        b.close()
        assert node.stop() == 0
        ap.stop()
    c = node.final_counters()
    assert c["rejected_duplicate"] == 2
    # a's bucket holds 50 (one second's worth) and refills at 50/s while the flood lasts (plus the
    # time the node takes to read it): of 501 observations about 50 + 50 * flood time pass.
    passed_max = 50 + 50 * (flood_s + 1.0)
    assert 501 - passed_max <= c["rejected_rate_limited"] <= 501 - 50, (c["rejected_rate_limited"], flood_s)
    assert c["accepted"] == 501 + 6 - c["rejected_rate_limited"], sorted(
        c.items()
    )  # every distinct one, less the limited
    assert c["clock_skew_warnings"] >= 1 and c["rejected_bad_stamp"] == 1
    assert "sync the clocks" in node.log()


def test_timesync_answers_only_the_autopilot_and_names_it(tmp_path):
    """Behind a router a GCS's TIMESYNC request reaches the node on the autopilot link too: only the
    autopilot's is answered, and the answer names the autopilot (system 1, component 1)."""
    ap, _, _, node = start(tmp_path)
    d = dialect.load()
    try:
        assert wait_for(lambda: node.proc.poll() is None and "autopilot found" in node.log(), 10), node.log()
        ap.send(d.MAVLink_timesync_message(tc1=0, ts1=111), source=(255, 190))  # a GCS, through a router
        ap.send(d.MAVLink_timesync_message(tc1=0, ts1=222))  # the autopilot itself
        assert wait_for(lambda: any(r[1] == 222 for r in ap.timesync_replies), 5), node.log()
        time.sleep(0.3)
    finally:
        node.stop()
        ap.stop()
    answered = {r[1]: r for r in ap.timesync_replies}
    assert 111 not in answered, "the GCS's request was answered"
    assert answered[222][2:] == (1, 1), answered[222]
    assert node.final_counters()["timesync_not_from_autopilot"] == 1


def test_timesync_is_answered_and_origin_sent_until_known(tmp_path):
    origin = {"lat_deg": 49.6116, "lon_deg": 6.1319, "alt_m": 300.0}
    ap, _, _, node = start(tmp_path, autopilot_extra={"origin": origin}, autopilot_type=3)  # ArduPilot, no origin
    try:
        assert wait_for(lambda: ap.other.get("SET_GPS_GLOBAL_ORIGIN", 0) >= 1, 5), node.log()
        msg = ap.last["SET_GPS_GLOBAL_ORIGIN"]
        assert (msg.latitude, msg.longitude, msg.altitude) == (496116000, 61319000, 300000)
        d = dialect.load()
        ts1 = time.monotonic_ns()
        ap.send(d.MAVLink_timesync_message(tc1=0, ts1=ts1))
        assert wait_for(lambda: "TIMESYNC" in ap.last and ap.last["TIMESYNC"].ts1 == ts1, 5)
        assert ap.last["TIMESYNC"].tc1 > 0  # the node's time, answered
        time.sleep(2.0)  # the autopilot has an origin now (and said so): nothing more
        assert ap.other["SET_GPS_GLOBAL_ORIGIN"] == 1, "the origin kept coming after GPS_GLOBAL_ORIGIN"
    finally:
        node.stop()
        ap.stop()
