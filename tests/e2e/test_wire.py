"""Attacks on the wire end to end (real node processes, loopback): a signed frame stamped near 2^48 and a
state file poisoned with one; one-byte datagrams from many addresses to a ``udpin`` port; a partial frame
before each real datagram; an impostor autopilot behind the autopilot link; datagrams of bad frames."""

import hashlib
import json
import os
import socket
import time

import pytest

from atlas_onboard.config import load_world
from atlas_onboard.mavlink import dialect
from atlas_onboard.mavlink.signing import SIGNING_TICKS_PER_S, signing_timestamp
from atlas_onboard.mavlink.udp import MAX_BAD_FRAMES
from atlas_onboard.sim.autopilot import SimAutopilot
from atlas_onboard.sim.solo import Radio
from tests.e2e.helpers import NodeProcess, free_udp_port, wait_for, write_world
from tests.e2e.test_autopilot import world_doc
from tests.e2e.test_signing import TRUTH_A, key_file
from tests.helpers import observe

pytestmark = pytest.mark.deadlines  # one node, little CPU: beside the real-time group

D = dialect.load()
TICKS_2_48 = (1 << 48) - 1


def _start(tmp_path, extra_node=None, ap=None, state=False, origin=None):
    ap = ap or SimAutopilot(system_id=1).start()
    port = free_udp_port()
    doc = world_doc(port, ap.port, extra_node=extra_node)
    if state:
        doc["nodes"]["d1"]["state_dir"] = str(tmp_path / "state")
    if origin is not None:
        doc["nodes"]["d1"]["autopilot"]["origin"] = origin
    path = write_world(tmp_path, doc)
    return load_world(path), ap, path, port


def _listener() -> socket.socket:
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.setblocking(False)
    return s


def _drain(sock: socket.socket) -> list[bytes]:
    got = []
    while True:
        try:
            got.append(sock.recv(65535))
        except BlockingIOError:
            return got


def _observations(world, radio, n, system_id=250, key=None, before=None, period=0.02):
    fp = world.fingerprint()
    for k in range(n):
        md = observe(world, TRUTH_A, 10, 5, capture_time_us=int(time.time() * 1e6))
        if before is not None:
            radio.send(before)
        radio.send(radio.observation(md, fp, system_id, key, seq=k + 1))
        time.sleep(period)


def test_a_frame_stamped_near_2_48_and_a_poisoned_state_file_stop_no_signed_traffic(tmp_path):
    key = os.urandom(32)
    signing = {"key_file": str(key_file(tmp_path, key)), "require": True}
    world, ap, path, port = _start(tmp_path, {"signing": signing}, state=True)
    url = f"udpin:127.0.0.1:{port}"
    digest = hashlib.sha256(f"{url}|1|197".encode()).hexdigest()[:12]
    (tmp_path / "state").mkdir()
    state_file = tmp_path / "state" / f"signing-{digest}.json"
    state_file.write_text(json.dumps({"timestamp": TICKS_2_48 - 5}))  # saved by an older version
    node = NodeProcess(path, "d1")
    radio = Radio(port)
    radio.sock.setblocking(False)
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
        evil = D.MAVLink(None, srcSystem=250, srcComponent=197)  # a key holder, as the world's node
        evil.signing.secret_key, evil.signing.sign_outgoing = key, True
        evil.signing.timestamp = TICKS_2_48 - 10
        radio.send(bytes(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3).pack(evil)))
        time.sleep(0.3)
        _observations(world, radio, 5, key=key)  # the real node 250 with a right clock
        assert wait_for(lambda: len(ap.snapshot()) >= 1, 5.0), node.log()
        time.sleep(1.5)  # heartbeats of the node to its proven client
        frames = [m for data in _drain(radio.sock) for m in (D.MAVLink(None).parse_buffer(data) or ())]
    finally:
        radio.close()
        assert node.stop() == 0
        ap.stop()
    c = node.final_counters()
    assert c["accepted"] == 5 and c["peer0_signature_ahead"] == 1
    assert c["peer0_signing_state_repaired"] == 1
    # What the node signs is near the clock, so a peer with a right clock takes it.
    now = signing_timestamp(time.time())
    signed = [bytes(f.get_msgbuf()) for f in frames if f.get_msgbuf()[2] & 1]
    stamps = [int.from_bytes(buf[-12:-6], "little") for buf in signed]
    assert stamps and all(now - 60 * SIGNING_TICKS_PER_S < t < now + 30 * SIGNING_TICKS_PER_S for t in stamps)
    assert json.loads(state_file.read_text())["timestamp"] < now + 30 * SIGNING_TICKS_PER_S


def test_one_byte_from_many_addresses_makes_no_client(tmp_path):
    _, ap, path, port = _start(tmp_path)
    node = NodeProcess(path, "d1")
    strangers = [_listener() for _ in range(100)]
    radio = Radio(port)
    radio.sock.setblocking(False)
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
        for s in strangers:
            s.sendto(b"\x00", ("127.0.0.1", port))
        radio.send(radio.frame(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3), 250))  # the real peer proves itself
        time.sleep(2.5)  # two heartbeats and telemetry of the node
        to_strangers = sum(len(_drain(s)) for s in strangers)
        to_peer = len(_drain(radio.sock))
    finally:
        for s in strangers:
            s.close()
        radio.close()
        assert node.stop() == 0
        ap.stop()
    assert to_strangers == 0
    assert to_peer >= 2
    assert node.final_counters()["peer0_udp_clients_admitted"] == 1


def test_a_partial_frame_before_each_real_datagram_loses_no_observation(tmp_path):
    world, ap, path, port = _start(tmp_path)
    node = NodeProcess(path, "d1")
    radio = Radio(port)
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
        partial = radio.observation(observe(world, TRUTH_A, 10, 5), world.fingerprint(), 250)[:10]
        _observations(world, radio, 40, before=partial)
        time.sleep(0.5)
    finally:
        radio.close()
        assert node.stop() == 0
        ap.stop()
    c = node.final_counters()
    assert c["peer0_rx_atlas_observation"] == 40 and c["accepted"] == 40


def test_an_impostor_behind_the_autopilot_link_never_becomes_the_autopilot(tmp_path):
    ap = SimAutopilot(system_id=1, autopilot_type=12).start()  # PX4: no origin unless asked
    _, ap, path, _ = _start(tmp_path, ap=ap, origin={"lat_deg": 47.4, "lon_deg": 8.5, "alt_m": 489.4})
    node = NodeProcess(path, "d1")
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
        for _ in range(15):  # another vehicle's ArduPilot behind a shared router, 10 Hz for 1.5 s
            ap.send(D.MAVLink_heartbeat_message(2, 3, 0, 0, 4, 3), source=(2, 1))
            ap.send(D.MAVLink_timesync_message(0, 123_456), source=(2, 1))
            time.sleep(0.1)
        time.sleep(1.5)
    finally:
        assert node.stop() == 0
        ap.stop()
    assert ap.other.get("SET_GPS_GLOBAL_ORIGIN", 0) == 0 and ap.local_z_shift_m == 0.0
    assert all((t_sys, t_comp) == (1, 1) for _, _, t_sys, t_comp in ap.timesync_replies)
    assert node.final_counters()["heartbeat_not_from_autopilot"] >= 15


def test_datagrams_of_bad_frames_cost_the_budget_and_lose_no_observation(tmp_path):
    world, ap, path, port = _start(tmp_path)
    node = NodeProcess(path, "d1")
    radio = Radio(port)
    try:
        assert wait_for(lambda: ap.heartbeats_from.get((1, 197), 0) > 0), node.log()
        hb = radio.frame(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3), 77)
        bad = (hb[:-2] + bytes([hb[-2] ^ 0xFF, hb[-1]])) * (1400 // len(hb))
        for _ in range(30):
            for _ in range(20):
                radio.send(bad)
            _observations(world, radio, 1, period=0.0)
            time.sleep(0.03)
        time.sleep(0.5)
    finally:
        radio.close()
        assert node.stop() == 0
        ap.stop()
    c = node.final_counters()
    flood = 30 * 20
    assert c["peer0_rejected_bad_data"] <= MAX_BAD_FRAMES * flood  # not the 116 frames of each
    assert c["peer0_datagrams_cut"] + c.get("peer0_kernel_drops", 0) >= flood
    assert c["accepted"] == 30
