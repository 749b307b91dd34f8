"""The node's transport in this process over 127.0.0.1: an observation arriving on two links is
delivered once, TUNNEL and plain alike; refusals are counted; TIMESYNC is answered on the wall clock;
the EKF origin is sent until the autopilot reports one; a pose that is not finite is never sent."""

import math
import random
import socket
import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.config import AutopilotConfig, AutopilotOutput, GlobalOrigin, LinkConfig, NodeConfig
from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import Rejection
from atlas_onboard.core.records import AutopilotPose
from atlas_onboard.mavlink import codec, framing
from atlas_onboard.mavlink.transport import MavlinkTransport
from atlas_onboard.node.schedule import ParkingBuffer
from tests.e2e.helpers import wait_for
from tests.helpers import world_from
from tests.mavlink.loopback import MD, D, RawSender, free_port

pytestmark = [
    pytest.mark.usefixtures("framing_mode"),  # every test with the fast path and without
    pytest.mark.deadlines,  # sockets and their deadlines
]

WALL_S = 1_700_000_000.25  # the transport's wall clock, frozen


class FakeAutopilot:
    """A UDP socket the transport's ``udpout`` autopilot link talks to; it records what arrives."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.mav = D.MAVLink(None, srcSystem=1, srcComponent=1)
        self.parser = D.MAVLink(None)
        self.received: list = []
        self.node_addr = None

    def pump(self, seconds: float = 0.2) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            try:
                data, addr = self.sock.recvfrom(4096)
            except TimeoutError:
                continue
            self.node_addr = addr
            self.received.extend(self.parser.parse_buffer(data) or [])

    def send(self, msg) -> None:
        self.sock.sendto(msg.pack(self.mav), self.node_addr)

    def of(self, kind: str) -> list:
        return [m for m in self.received if m.get_type() == kind]


@pytest.fixture
def rig():
    world = world_from(
        {
            "entities": {
                "world": {"sensors": [{"name": "cam", "id": 10, "pose": {"pos": [0, 0, 4], "rpy_deg": [0, 90, 0]}}]},
                "d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
            }
        }
    )
    ap = FakeAutopilot()
    p0, p1 = free_port(), free_port()
    config = NodeConfig(
        entity="d1",
        system_id=1,
        autopilot=AutopilotConfig(LinkConfig(f"udpout:127.0.0.1:{ap.port}"), origin=GlobalOrigin(47.1, 8.5, 400.0)),
        peers=(LinkConfig(f"udpin:127.0.0.1:{p0}"), LinkConfig(f"udpin:127.0.0.1:{p1}", tunnel=True)),
        heartbeat_hz=2.0,
        owners=(("world", 250), ("d1", 1)),  # the senders below are the world's node
    )
    transport = MavlinkTransport(world, config, wall_clock=lambda: WALL_S)
    delivered: list = []
    lock = threading.Lock()

    def deliver(items):  # as the node takes what can move its pose: decoded and checked at once
        with lock:
            delivered.extend(md for md in (item.take() for item in items) if md is not None)
            transport.batches.append(len(items))

    transport.batches = []  # how many observations each hand-over carried
    transport.start(deliver)
    senders = [RawSender(p0, 250), RawSender(p1, 250)]
    yield world, transport, ap, senders, delivered
    transport.close()
    ap.sock.close()
    for s in senders:
        s.close()


def settle(transport, delivered, quiet_s=0.2):
    """Wait until neither deliveries nor counters change for ``quiet_s``."""
    last = None
    stable_since = time.monotonic()
    while time.monotonic() - stable_since < quiet_s:
        now = (len(delivered), sorted(transport.counters().items()))
        if now != last:
            last, stable_since = now, time.monotonic()
        time.sleep(0.02)


# A ceiling camera (sensor 10) on the world, and two drones with a tag each (5 and 6).
CEILING_D1_D2 = {
    "entities": {
        "world": {"sensors": [{"name": "cam", "id": 10, "pose": {"pos": [0, 0, 4], "rpy_deg": [0, 90, 0]}}]},
        "d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
        "d2": {"markers": [{"id": 6, "size_m": 0.2, "pose": {"pos": [0, 0, 0.05]}}]},
    }
}


def test_one_observation_over_two_links_is_delivered_once(rig):
    world, transport, _, (s0, s1), delivered = rig
    fp = world.fingerprint()
    t_us = int(WALL_S * 1e6)
    frame = s0.observation(seq=1, fingerprint=fp, time_usec=t_us)
    s0.raw(frame)  # plain, on link 0
    s0.raw(frame)  # a mesh echo
    payload_fields = codec.tunnel_fields(replace(MD, capture_time_us=t_us, seq=1), fp)
    s1.raw(s1.frame(D.MAVLink_tunnel_message(**payload_fields)))  # the same observation in TUNNEL, link 1
    s1.raw(s1.observation(seq=2, fingerprint=fp, time_usec=t_us))  # another one
    settle(transport, delivered)
    assert sorted((m.origin, m.seq) for m in delivered) == [(250, 1), (250, 2)]
    assert transport.counters()["rejected_duplicate"] == 2
    assert delivered[0].capture_time_us == t_us and delivered[0].sensor_id == 10


def test_refusals_are_counted_and_nothing_raises(rig):
    world, transport, _, (s0, s1), delivered = rig
    fp = world.fingerprint()
    t_us = int(WALL_S * 1e6)
    rng = random.Random(7)
    for _ in range(30):
        s0.raw(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 300))))
    good = s0.observation(seq=100, fingerprint=fp, time_usec=t_us)
    for cut in (2, 9, 40, len(good) - 1):
        s0.raw(good[:cut])
    unknown = bytearray(s0.heartbeat())
    unknown[7:10] = (45000).to_bytes(3, "little")
    s0.raw(bytes(unknown))
    s0.raw(s0.observation(seq=101, fingerprint=fp ^ 0xFF, time_usec=t_us))  # another world file
    s0.raw(s0.observation(seq=102, fingerprint=fp, time_usec=t_us, format_version=7))
    s1.raw(s1.frame(D.MAVLink_tunnel_message(0, 0, 40000, 10, [1] * 128)))  # someone else's TUNNEL
    s1.raw(s1.frame(D.MAVLink_tunnel_message(0, 0, 43100, 50, [1] * 128)))  # ours, but cut short
    s0.raw(s0.observation(seq=103, fingerprint=fp, time_usec=t_us, x=math.nan))
    s0.raw(s0.observation(seq=104, fingerprint=fp, time_usec=t_us, q=[0.0, 0.0, 0.0, 0.0]))
    s0.raw(s0.observation(seq=105, fingerprint=fp, time_usec=t_us, sigma=-1.0))
    s0.raw(s0.observation(seq=106, fingerprint=fp, time_usec=t_us, sigma=math.inf))
    s0.raw(s0.observation(seq=108, fingerprint=fp, time_usec=t_us, reprojection_error=-1.0))
    s0.raw(s0.observation(seq=109, fingerprint=fp, time_usec=t_us, reprojection_error=math.inf))
    s0.raw(s0.observation(seq=110, fingerprint=fp, time_usec=t_us, ambiguity=1.5))
    s0.raw(s0.observation(seq=111, fingerprint=fp, time_usec=t_us, ambiguity=-math.inf))
    s0.raw(s0.observation(seq=112, fingerprint=fp, time_usec=t_us, q=[math.inf, 0.0, 0.0, 1.0]))
    # Capture stamps: 0.5 s old passes (with a warning); 2 s old, a year ahead, and 0 are refused.
    s0.raw(s0.observation(seq=113, fingerprint=fp, time_usec=t_us - 500_000))
    for seq, stamp in ((114, t_us - 2_000_000), (115, t_us + 365 * 86400 * 10**6), (116, 0)):
        s0.raw(s0.observation(seq=seq, fingerprint=fp, time_usec=stamp))
    s0.raw(s0.observation(seq=107, fingerprint=fp, time_usec=t_us))  # finally a good one
    settle(transport, delivered, 0.3)
    c = transport.counters()
    assert c["rejected_bad_stamp"] == 3 and c["clock_skew_warnings"] >= 1
    assert c["rejected_wrong_fingerprint"] == 1 and c["rejected_bad_version"] == 1
    assert c["rejected_tunnel_unknown_type"] == 1 and c["rejected_tunnel_bad_length"] == 1
    assert c["peer0_rejected_unknown_id"] >= 1 and c["peer0_rejected_bad_data"] >= 1
    # Wire-valid records go on to the listener, whose checks (and counters) they fail there.
    reasons = {m.seq: m.rejection() for m in delivered}
    assert reasons == {
        103: Rejection.NON_FINITE,
        104: Rejection.ZERO_QUATERNION,
        105: Rejection.BAD_SIGMA,
        106: Rejection.NON_FINITE,
        108: Rejection.BAD_QUALITY,
        109: Rejection.BAD_QUALITY,
        110: Rejection.BAD_QUALITY,
        111: Rejection.BAD_QUALITY,
        112: Rejection.NON_FINITE,
        113: None,
        107: None,
    }
    assert all(lk.is_open for lk in transport.peers)


def test_timesync_answered_on_the_wall_clock_and_origin_until_known(rig):
    _, transport, ap, _, _ = rig
    transport.tick(0)
    ap.pump(0.2)
    ap.send(D.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3))  # ArduPilot (MAV_AUTOPILOT_ARDUPILOTMEGA)
    assert wait_for(lambda: transport.autopilot_link.autopilot_type == 3)
    # Asked for every 0.5 s; set after two requests went unanswered, together with a third request.
    for now_ns in (400_000_000, 1_000_000_000, 1_500_000_000):  # heartbeats at 2 Hz
        transport.tick(now_ns)
    ap.pump(0.3)
    assert len(ap.of("HEARTBEAT")) == 3  # at 0, 1 and 1.5 s (0.4 s is within the 0.5 s period)
    hb = ap.of("HEARTBEAT")[0]
    assert (hb.type, hb.autopilot, hb.get_srcSystem(), hb.get_srcComponent()) == (18, 8, 1, 197)
    requests = [m for m in ap.of("COMMAND_LONG") if m.command == 512]
    assert [(m.param1, m.target_system, m.target_component) for m in requests] == [(49.0, 1, 1)] * 3
    origins = ap.of("SET_GPS_GLOBAL_ORIGIN")
    assert [(o.latitude, o.longitude, o.altitude, o.target_system) for o in origins] == [
        (471000000, 85000000, 400000, 1)
    ]
    ap.send(D.MAVLink_timesync_message(0, 987_654_321))
    ap.send(D.MAVLink_gps_global_origin_message(471000000, 85000000, 400000, 0))
    ap.pump(0.3)
    (reply,) = ap.of("TIMESYNC")
    assert (reply.tc1, reply.ts1) == (1_700_000_000_250_000_000, 987_654_321)  # the wall clock of usec, in ns
    assert (reply.target_system, reply.target_component) == (1, 1)
    assert transport.autopilot_link.origin_known
    for now_ns in range(2_000_000_000, 10_000_000_000, 500_000_000):
        transport.tick(now_ns)
    ap.pump(0.2)
    assert len(ap.of("SET_GPS_GLOBAL_ORIGIN")) == 1  # no more once the autopilot has one
    assert len([m for m in ap.of("COMMAND_LONG") if m.command == 512]) == 3


def _origin_run(sim, origin, seconds=3.0):
    """A transport with ``origin`` against the simulated autopilot ``sim``, ticked every 0.1 s of
    its clock for ``seconds`` (20 ms apart in real time, for the answers to arrive)."""
    world = world_from({"entities": {"d1": {"markers": [{"id": 5, "size_m": 0.2, "pose": {"pos": [0, 0, 0]}}]}}})
    config = NodeConfig(
        entity="d1",
        system_id=1,
        autopilot=AutopilotConfig(LinkConfig(f"udpout:127.0.0.1:{sim.port}"), origin=origin),
    )
    transport = MavlinkTransport(world, config)
    transport.start(lambda items: None)
    try:
        transport.tick(0)  # a heartbeat: the simulated autopilot learns where the node is
        assert wait_for(lambda: sim._peer is not None)
        sim.send(sim._mav.heartbeat_encode(2, sim.autopilot_type, 0, 0, 3))
        assert wait_for(lambda: transport.autopilot_link.autopilot_type == sim.autopilot_type)
        for k in range(1, int(seconds * 10)):
            transport.tick(k * 100_000_000)
            time.sleep(0.02)
        time.sleep(0.1)
    finally:
        transport.close()
    return transport


@pytest.mark.parametrize("framing_mode", ["fast"], indirect=True)  # what is sent, not how framed
def test_origin_after_a_restart_against_ardupilot_that_has_one_is_asked_for_never_set(framing_mode):
    from atlas_onboard.sim.autopilot import SimAutopilot

    sim = SimAutopilot(system_id=1, autopilot_type=3, origin=(47.1, 8.5, 400.0)).start()
    try:
        transport = _origin_run(sim, GlobalOrigin(49.6, 6.1, 300.0))  # the node's is another: ignored
    finally:
        sim.stop()
    assert transport.autopilot_link.origin_known
    assert sim.other.get("SET_GPS_GLOBAL_ORIGIN", 0) == 0
    assert sim.origin_requests == 1 and sim.origin == (47.1, 8.5, 400.0)


@pytest.mark.parametrize("framing_mode", ["fast"], indirect=True)  # what is sent, not how framed
def test_origin_set_once_on_ardupilot_without_one(framing_mode):
    from atlas_onboard.sim.autopilot import SimAutopilot

    sim = SimAutopilot(system_id=1, autopilot_type=3).start()
    try:
        transport = _origin_run(sim, GlobalOrigin(49.6116, 6.1319, 300.0))
    finally:
        sim.stop()
    assert transport.autopilot_link.origin_known and sim.other.get("SET_GPS_GLOBAL_ORIGIN", 0) == 1
    assert sim.origin == pytest.approx((49.6116, 6.1319, 300.0), abs=1e-6)


@pytest.mark.parametrize("framing_mode", ["fast"], indirect=True)  # what is sent, not how framed
@pytest.mark.parametrize("send_to_px4", [False, True])
def test_origin_never_moves_px4s_local_frame(send_to_px4, framing_mode):
    """PX4 v1.16 (``setAltOrigin``, modelled by the simulated autopilot): an origin altitude set after
    height initialisation shifts local z by it. The node sends none to PX4 unless asked, and then
    one that leaves the local height where it is."""
    from atlas_onboard.sim.autopilot import SimAutopilot

    sim = SimAutopilot(system_id=1, autopilot_type=12).start()  # height initialised on vision: origin alt 0
    try:
        _origin_run(sim, GlobalOrigin(47.397742, 8.545594, 489.4, send_to_px4=send_to_px4), seconds=2.5)
    finally:
        sim.stop()
    assert sim.local_z_shift_m == 0.0
    if send_to_px4:
        assert sim.other.get("SET_GPS_GLOBAL_ORIGIN", 0) == 1
        assert sim.origin[:2] == pytest.approx((47.397742, 8.545594), abs=1e-6)
    else:
        assert sim.other.get("SET_GPS_GLOBAL_ORIGIN", 0) == 0 and sim.origin_requests == 0


def test_statustext_at_most_one_per_reason(rig):
    _, transport, ap, _, _ = rig
    for _ in range(5):  # e.g. a forged peer appearing again and again
        transport.send_status("atlas: peer 9 seen", 6, "peer_seen_9")
    transport.send_status("atlas d1: pose lost", 4)  # another reason goes out
    ap.pump(0.3)
    assert [m.text for m in ap.of("STATUSTEXT")] == ["atlas: peer 9 seen", "atlas d1: pose lost"]
    assert transport.counters()["statustext_suppressed"] == 4


def test_autopilot_gets_ned_and_never_a_non_finite_pose(rig):
    _, transport, ap, _, _ = rig
    transport.tick(0)
    ap.pump(0.1)
    q = Rotation.from_euler("z", 90, degrees=True).as_quat()
    good = EntityPose("d1", np.array([1.0, 2.0, 3.0]), q, 1, 1, 2, 0.02, 1_700_000_000_000_000)
    bad = EntityPose("d1", np.array([math.nan, 2.0, 3.0]), q, 1, 1, 2, 0.02, 1_700_000_000_000_001)
    worse = EntityPose("d1", np.array([1.0, 2.0, 3.0]), q, 1, 1, 2, math.inf, 1_700_000_000_000_002)
    transport.send_autopilot(AutopilotPose(bad, 0))
    transport.send_autopilot(AutopilotPose(worse, 0))
    transport.send_autopilot(AutopilotPose(good, 3))
    ap.pump(0.3)
    (vpe,) = ap.of("VISION_POSITION_ESTIMATE")
    assert (vpe.x, vpe.y, vpe.z) == pytest.approx((2.0, 1.0, -3.0)) and abs(vpe.yaw) < 1e-6
    assert vpe.usec == 1_700_000_000_000_000 and vpe.reset_counter == 3
    assert [vpe.covariance[i] for i in (0, 6, 11)] == pytest.approx([0.0004] * 3)
    assert transport.counters()["autopilot_pose_refused"] == 2


def test_odometry_output(rig):
    _, transport, ap, _, _ = rig
    ap_config = AutopilotConfig(transport.config.autopilot.link, output=AutopilotOutput.ODOMETRY)
    transport.autopilot_link.settings = ap_config
    transport.tick(0)
    ap.pump(0.1)
    q = Rotation.from_euler("z", 90, degrees=True).as_quat()
    transport.send_autopilot(AutopilotPose(EntityPose("d1", np.array([1.0, 2.0, 3.0]), q, 1, 1, 2, 0.01, 5), 1))
    ap.pump(0.3)
    (odo,) = ap.of("ODOMETRY")
    assert (odo.frame_id, odo.child_frame_id, odo.estimator_type, odo.quality) == (20, 12, 2, 100)
    assert (odo.x, odo.y, odo.z) == pytest.approx((2.0, 1.0, -3.0))
    assert odo.q == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-6)


def test_clock_skew_is_counted(rig):
    world, transport, _, (s0, _), delivered = rig
    fp = world.fingerprint()
    s0.raw(s0.observation(seq=1, fingerprint=fp, time_usec=int(WALL_S * 1e6) - 400_000))  # 400 ms: warned
    s0.raw(s0.observation(seq=2, fingerprint=fp, time_usec=int(WALL_S * 1e6) - 50_000))  # 50 ms: fine
    s0.raw(s0.observation(seq=3, fingerprint=fp, time_usec=int(WALL_S * 1e6) - 2_000_000))  # 2 s: refused
    settle(transport, delivered)
    assert [md.seq for md in delivered] == [1, 2]
    c = transport.counters()
    # The 2 s one is refused on its stamp before anything else (never kept, never decoded): not a skew warning.
    assert c["clock_skew_warnings"] == 1 and c["rejected_bad_stamp"] == 1


def test_the_observations_of_one_datagram_are_handed_on_together(rig):
    """An image's observations packed in one datagram (as nodes send them) reach the node in one
    hand-over, in order; separate datagrams in separate ones."""
    world, transport, _, (s0, _), delivered = rig
    fp = world.fingerprint()
    t_us = int(WALL_S * 1e6)
    image = [s0.observation(seq=10 + k, fingerprint=fp, time_usec=t_us, frame_remaining=2 - k) for k in range(3)]
    s0.raw(b"".join(image))
    settle(transport, delivered)
    s0.raw(s0.observation(seq=20, fingerprint=fp, time_usec=t_us))
    settle(transport, delivered)
    assert [m.seq for m in delivered] == [10, 11, 12, 20] and [m.frame_remaining for m in delivered[:3]] == [2, 1, 0]
    assert transport.batches == [3, 1]


class Parking:
    """What a node does with delivered observations: those of marker 6 parked (the newest of each
    edge, undecoded), the others taken (decoded and checked) at once."""

    def __init__(self):
        self.delivered = []
        self.parking = ParkingBuffer(64, newest_wins=True)

    def __call__(self, items):
        self.parking.put([item for item in items if item.marker_id == 6])
        taken = ((item.take(), item.arrival_ns) for item in items if item.marker_id != 6)
        self.delivered.extend((md, arrival_ns) for md, arrival_ns in taken if md is not None)

    def take(self):
        taken = ((item.take(), item.arrival_ns) for item in self.parking.take())
        return [(md, arrival_ns) for md, arrival_ns in taken if md is not None]


@pytest.mark.parametrize("framing_mode", ["fast"], indirect=True)  # deferred decoding is the fast path's
def test_parked_observations_are_the_newest_of_each_edge_and_checked_when_taken(monkeypatch, framing_mode):
    """Observations the node parks (here of marker 6) are delivered undecoded: the newest of its
    edge is kept, the others dropped (counted), and it is decoded and checked (duplicates, stamps)
    only when taken; another world file's never stands in for ours (refused before decoding); the
    rest is taken at once. Those dropped are never decoded, nor is a peer's fused pose (it only says
    the peer is alive)."""
    decoded = []
    real = framing.Deferred.decoded
    monkeypatch.setattr(framing.Deferred, "decoded", lambda self: decoded.append(self.get_type()) or real(self))
    world = world_from(CEILING_D1_D2)
    port = free_port()
    config = NodeConfig(
        entity="d1",
        system_id=1,
        peers=(LinkConfig(f"udpin:127.0.0.1:{port}"),),
        owners=(("world", 250), ("d1", 1), ("d2", 77)),
    )
    wall = [WALL_S]
    transport = MavlinkTransport(world, config, wall_clock=lambda: wall[0])
    node = Parking()
    delivered = node.delivered
    transport.start(node)
    sender = RawSender(port, 250)
    try:
        fp, t_us = world.fingerprint(), int(WALL_S * 1e6)
        assert node.parking.since_ns() is None
        for seq, dt in ((1, 0), (2, 1000), (3, -1000)):  # the newest (seq 2) arrives in the middle
            sender.raw(sender.observation(seq=seq, fingerprint=fp, time_usec=t_us + dt, marker_id=6))
        sender.raw(sender.observation(seq=4, fingerprint=fp ^ 1, time_usec=t_us + 2000, marker_id=6))
        sender.raw(sender.observation(seq=5, fingerprint=fp, time_usec=t_us, marker_id=5))  # delivered
        settle(transport, delivered)
        assert [(md.marker_id, md.seq) for md, _ in delivered] == [(5, 5)]
        c = transport.counters()
        assert node.parking.superseded == 2 and c["rejected_wrong_fingerprint"] == 1
        assert decoded == ["ATLAS_OBSERVATION"]  # seq 5 (the other world file's was refused undecoded)
        pose = EntityPose("d2", np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 0.0, 1.0]), 1, 2, 3, 0.01, t_us)
        peer = RawSender(port, 77)
        fused = peer.frame(codec.encode_fused(D, pose, 2, 0, fp))
        made = []  # fused pose messages made from here on (a decode makes one)
        cls = D.MAVLink_atlas_fused_pose_message
        monkeypatch.setattr(cls, "__init__", lambda self, *a, init=cls.__init__: made.append(1) or init(self, *a))
        peer.raw(fused)
        assert wait_for(lambda: 77 in transport.peers_seen)
        assert decoded == ["ATLAS_OBSERVATION"] and not made
        assert transport.counters()["peer0_rx_atlas_fused_pose"] == 1
        peer.close()
        since = node.parking.since_ns()
        assert since is not None and since <= time.monotonic_ns()
        wall[0] += 0.3  # taken later than it arrived: its clock is checked as of its arrival
        taken = node.take()
        assert transport.counters().get("clock_skew_warnings", 0) == 0
        assert [(md.marker_id, md.seq, md.capture_time_us) for md, _ in taken] == [(6, 2, t_us + 1000)]
        assert decoded == ["ATLAS_OBSERVATION"] * 2  # the one taken
        assert taken[0][1] >= since and node.parking.since_ns() is None and node.take() == []
        # Checked as any other when taken: the same observation again is a duplicate; a stale one is refused.
        wall[0] = WALL_S
        sender.raw(sender.observation(seq=2, fingerprint=fp, time_usec=t_us + 1000, marker_id=6))
        settle(transport, delivered)
        assert node.take() == [] and transport.counters()["rejected_duplicate"] == 1
        sender.raw(sender.observation(seq=6, fingerprint=fp, time_usec=t_us - 5_000_000, marker_id=6))
        settle(transport, delivered)
        assert node.take() == [] and transport.counters()["rejected_bad_stamp"] == 1
    finally:
        transport.close()
        sender.close()


def test_a_forged_observation_never_supersedes_the_kept_one():
    """The DANGER of keeping the newest of an edge: a forged one with a later stamp would evict the
    real one. From a system id that does not run the sensor, or stamped far ahead, it is refused
    before it is kept (and never decoded)."""
    world = world_from(CEILING_D1_D2)
    port = free_port()
    config = NodeConfig(entity="d1", system_id=1, peers=(LinkConfig(f"udpin:127.0.0.1:{port}"),),
                        owners=(("world", 250), ("d1", 1), ("d2", 2)))  # fmt: skip
    transport = MavlinkTransport(world, config, wall_clock=lambda: WALL_S)
    node = Parking()
    transport.start(node)
    real, forger = RawSender(port, 250), RawSender(port, 2)
    try:
        fp, t_us = world.fingerprint(), int(WALL_S * 1e6)
        real.raw(real.observation(seq=1, fingerprint=fp, time_usec=t_us, marker_id=6))
        forger.raw(forger.observation(seq=2, fingerprint=fp, time_usec=t_us + 500_000, marker_id=6))  # not its sensor
        real.raw(real.observation(seq=3, fingerprint=fp, time_usec=t_us + 3_600_000_000, marker_id=6))  # 1 h ahead
        settle(transport, node.delivered)
        taken = node.take()
        assert [(md.seq, md.origin, md.capture_time_us) for md, _ in taken] == [(1, 250, t_us)]
        c = transport.counters()
        assert c["rejected_not_owner"] == 1 and c["rejected_bad_stamp"] == 1 and node.parking.superseded == 0
        assert c["refused_from_2"] == 1 and c["refused_from_250"] == 1
    finally:
        transport.close()
        real.close()
        forger.close()


def test_what_px4_and_ardupilot_stream_is_not_counted_as_unknown_ids(rig):
    """PX4 builds with development.xml and streams CURRENT_MODE, AVAILABLE_MODES (development.xml),
    TIME_ESTIMATE_TO_TARGET, EVENT and CURRENT_EVENT_SEQUENCE (common.xml, newer than pymavlink
    2.4.50's copy): decoded. An
    ArduPilot message (AHRS, id 163, ardupilotmega.xml) is counted as another dialect's; only an id
    no public dialect defines is an unknown id."""
    _, transport, ap, _, _ = rig
    transport.tick(0)
    ap.pump(0.2)
    ap.send(D.MAVLink_current_mode_message(0, 0, 0))
    ap.send(D.MAVLink_available_modes_message(1, 1, 0, 0, 0, b"POSCTL"))
    ap.send(D.MAVLink_time_estimate_to_target_message(-1, -1, -1, -1, -1))
    ap.send(D.MAVLink_current_event_sequence_message(7, 0))
    ap.send(D.MAVLink_event_message(0, 0, 1234, 5000, 7, 0x66, [0] * 40))
    # Those added to pymavlink's common.xml carry upstream's CRC extras (MAVLink's C headers).
    assert [m.crc_extra for m in (D.MAVLink_time_estimate_to_target_message, D.MAVLink_event_message,
                                  D.MAVLink_current_event_sequence_message)] == [232, 160, 106]  # fmt: skip
    for msg_id in (163, 45000):
        frame = bytearray(D.MAVLink_heartbeat_message(2, 3, 0, 0, 3, 3).pack(ap.mav))
        frame[7:10] = msg_id.to_bytes(3, "little")
        ap.sock.sendto(bytes(frame), ap.node_addr)
    assert wait_for(lambda: transport.counters().get("autopilot_rejected_unknown_id", 0) == 1), sorted(
        transport.counters().items()
    )
    c = transport.counters()
    assert (c["autopilot_rx_current_mode"], c["autopilot_rx_available_modes"]) == (1, 1)
    assert c["autopilot_rx_time_estimate_to_target"] == 1 and c["autopilot_rx_other_dialect"] == 1
    assert (c["autopilot_rx_event"], c["autopilot_rx_current_event_sequence"]) == (1, 1)


def test_on_a_signed_link_only_signed_frames_say_a_peer_is_alive(tmp_path):
    from atlas_onboard.config import SigningConfig
    from tests.mavlink.loopback import write_key

    key = write_key(tmp_path, bytes(range(32)))
    world = world_from(CEILING_D1_D2)
    port = free_port()
    config = NodeConfig(
        entity="d1",
        system_id=1,
        peers=(LinkConfig(f"udpin:127.0.0.1:{port}", signing=SigningConfig(key)),),
        owners=(("world", 250), ("d1", 1), ("d2", 2)),
    )
    transport = MavlinkTransport(world, config)
    transport.start(lambda items: None)
    unsigned, signed = RawSender(port, 2), RawSender(port, 250, key.read_bytes())
    try:
        for _ in range(3):
            unsigned.raw(unsigned.heartbeat())  # passes the link (not protected), but is anyone's
        assert wait_for(lambda: transport.counters().get("peer0_rx_heartbeat", 0) == 3)
        assert 2 not in transport.peers_seen
        signed.raw(signed.heartbeat())
        assert wait_for(lambda: 250 in transport.peers_seen)
    finally:
        transport.close()
        unsigned.close()
        signed.close()


def test_only_peers_and_ground_stations_become_clients_of_a_udpin_link():
    world = world_from(CEILING_D1_D2)
    port = free_port()
    config = NodeConfig(
        entity="d1", system_id=1, peers=(LinkConfig(f"udpin:127.0.0.1:{port}"),), owners=(("d1", 1), ("d2", 2))
    )
    transport = MavlinkTransport(world, config)
    transport.start(lambda items: None)
    stranger, gcs, peer = RawSender(port, 77), RawSender(port, 255), RawSender(port, 2)
    try:
        stranger.raw(stranger.heartbeat())  # a valid frame, but from no node of the world file
        gcs.raw(gcs.frame(D.MAVLink_heartbeat_message(6, 8, 0, 0, 4, 3)))  # MAV_TYPE_GCS
        peer.raw(peer.heartbeat())
        assert wait_for(lambda: transport.counters().get("peer0_rx_heartbeat", 0) == 3)
        transport.send_status("atlas: test", 6)
        got = {}
        for name, s in (("stranger", stranger), ("gcs", gcs), ("peer", peer)):
            s.sock.settimeout(0.3)
            try:
                got[name] = len(s.sock.recv(4096)) > 0
            except TimeoutError:
                got[name] = False
        assert got == {"stranger": False, "gcs": True, "peer": True}
    finally:
        transport.close()
        for s in (stranger, gcs, peer):
            s.close()
