"""UDP links: proven clients (bounded, expiring), datagrams parsed alone within a bad-frame budget, and
links that send only to addresses that proved themselves."""

import random
import socket

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.core.rejection import Rejection
from atlas_onboard.mavlink import codec, framing
from atlas_onboard.mavlink.udp import MAX_BAD_FRAMES, ClientTable, parse_datagram
from tests.mavlink.loopback import FP, MD, D, RawSender, drain, free_port, make_link, poll_until, write_key

pytestmark = pytest.mark.deadlines  # sockets and their deadlines


def _mav():
    return framing.parser(D, None, 1, 197, frozenset())


def _frames(n, sysid=250):
    mav = D.MAVLink(None, srcSystem=sysid, srcComponent=197)
    out = []
    for k in range(n):
        fields = codec.observation_fields(MD, FP)
        fields["seq"] = k
        out.append(bytes(D.MAVLink_atlas_observation_message(**fields).pack(mav)))
    return out


def _bad_crc(frame: bytes) -> bytes:
    return frame[:-2] + bytes([frame[-2] ^ 0xFF, frame[-1]])


# --- the client table (pure) ------------------------------------------------------------------------


def test_clients_are_admitted_bounded_and_expire():
    t = ClientTable(max_clients=3, idle_s=10.0)
    assert t.clients(0.0) == []
    for k in range(3):
        assert t.prove(("10.0.0.1", 1000 + k), float(k))
    assert not t.prove(("10.0.0.9", 9), 3.0)  # full of clients that are not idle
    assert t.refused == 1 and len(t.clients(3.0)) == 3
    # 1000 fell silent at 0 s: forgotten after 10 s, and its place taken
    assert t.clients(10.5) == [("10.0.0.1", 1001), ("10.0.0.1", 1002)]
    assert t.expired == 1
    assert t.prove(("10.0.0.9", 9), 10.5)
    assert t.prove(("10.0.0.1", 1001), 11.0)  # a refresh keeps it
    assert t.clients(12.5) == [("10.0.0.9", 9), ("10.0.0.1", 1001)]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 40), st.floats(0.0, 1.0)), max_size=200))
def test_the_table_never_holds_more_than_its_bound_nor_an_idle_client(events):
    t = ClientTable(max_clients=5, idle_s=2.0)
    now, last = 0.0, {}
    for port, dt in events:
        now += dt
        if t.prove(("h", port), now):
            last[("h", port)] = now
        clients = t.clients(now)
        assert len(clients) <= 5
        assert all(now - last[a] <= 2.0 for a in clients)


# --- parsing a datagram ------------------------------------------------------------------------------


@pytest.mark.usefixtures("framing_mode")
def test_whole_frames_parse_as_pymavlink_parses_them():
    frames = _frames(5)
    got = parse_datagram(D, _mav(), b"".join(frames))
    ref = D.MAVLink(None, 1, 197).parse_buffer(b"".join(frames))
    assert not got.cut
    assert [m.get_msgbuf() for m in got.messages] == [m.get_msgbuf() for m in ref]


@pytest.mark.usefixtures("framing_mode")
def test_a_partial_frame_never_swallows_the_next_datagrams_frames():
    mav = _mav()
    real = b"".join(_frames(3))
    lost = 0
    for _ in range(20):
        first = parse_datagram(D, mav, real[:10])  # a frame's first 10 bytes
        assert [m.get_type() for m in first.messages] == ["BAD_DATA"]
        second = parse_datagram(D, mav, real)
        lost += 3 - sum(m.get_type() == "ATLAS_OBSERVATION" for m in second.messages)
    assert lost == 0


@pytest.mark.usefixtures("framing_mode")
def test_a_datagram_of_bad_frames_costs_at_most_the_budget():
    frames = [_bad_crc(f) for f in _frames(1)] * 40
    got = parse_datagram(D, _mav(), b"".join(frames))
    assert got.cut
    assert len(got.messages) == MAX_BAD_FRAMES and all(m.get_type() == "BAD_DATA" for m in got.messages)


@pytest.mark.usefixtures("framing_mode")
def test_bad_frames_below_the_budget_leave_the_good_ones():
    good = _frames(4)
    data = _bad_crc(good[0]) + b"\x01\x02\x03" + good[1] + _bad_crc(good[2]) + good[3]
    got = parse_datagram(D, _mav(), data)
    assert not got.cut
    kinds = [m.get_type() for m in got.messages]
    assert kinds.count("ATLAS_OBSERVATION") == 2 and kinds.count("BAD_DATA") == 3


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=1400))
def test_any_bytes_parse_without_raising_within_the_budget(data):
    got = parse_datagram(D, _mav(), data)
    assert sum(m.get_type() == "BAD_DATA" for m in got.messages) <= MAX_BAD_FRAMES + 1


# --- links over loopback -----------------------------------------------------------------------------


def _listen():
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    s.settimeout(0.3)
    return s


def _received(sock) -> int:
    n = 0
    try:
        while True:
            sock.recv(65535)
            n += 1
    except (TimeoutError, BlockingIOError):
        return n


def test_udpin_sends_only_to_addresses_that_proved_themselves(closing):
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1)
    closing(rx)
    rx.open()
    strangers = [_listen() for _ in range(20)]
    for s in strangers:
        closing(s)
        s.sendto(b"\x00", ("127.0.0.1", port))  # one byte: no frame, no proof
    peer = RawSender(port, 250)
    closing(peer)
    drain(rx, 0.2)
    assert rx.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3)) is True
    assert rx.counters["udp_tx_no_client"] == 1
    peer.sock.settimeout(0.3)
    peer.raw(peer.heartbeat())  # a valid frame: the peer proves its address
    poll_until(rx, lambda m: len(m) >= 1)
    rx.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    assert _received(peer.sock) == 1
    assert sum(_received(s) for s in strangers) == 0
    assert rx.counters["udp_clients_admitted"] == 1


def test_on_a_signed_link_only_a_signed_frame_proves_an_address(tmp_path, closing):
    key = write_key(tmp_path, bytes(range(32)))
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, key)
    closing(rx)
    rx.open()
    unsigned, signed = RawSender(port, 250), RawSender(port, 251, key.read_bytes())
    for s in (unsigned, signed):
        closing(s)
        s.sock.settimeout(0.3)
    unsigned.raw(unsigned.heartbeat())  # an unsigned HEARTBEAT passes (not protected) but proves nothing
    assert len(poll_until(rx, lambda m: len(m) >= 1)) == 1
    rx.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    assert _received(unsigned.sock) == 0
    signed.raw(signed.heartbeat())
    poll_until(rx, lambda m: len(m) >= 1)
    rx.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    assert _received(signed.sock) == 1 and _received(unsigned.sock) == 0


def test_udpbcast_is_never_captured_by_a_sender(closing):
    dest = _listen()
    closing(dest)
    tx = make_link(f"udpbcast:127.0.0.1:{dest.getsockname()[1]}", 1)
    closing(tx)
    tx.open()
    tx.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    assert _received(dest) == 1
    # someone sends to the link's own port: pymavlink would send everything to them from now on
    intruder = _listen()
    closing(intruder)
    src_port = tx._conn.port.getsockname()[1]
    intruder.sendto(RawSender(0, 77).heartbeat(), ("127.0.0.1", src_port))
    poll_until(tx, lambda m: len(m) >= 1, 1.0)
    for _ in range(3):
        tx.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    assert _received(dest) == 3 and _received(intruder) == 0


def test_a_flood_of_bad_frames_is_cut_per_datagram(closing):
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1)
    closing(rx)
    rx.open()
    s = RawSender(port)
    closing(s)
    junk = _bad_crc(s.heartbeat()) * 100
    rng = random.Random(0)
    for _ in range(10):
        s.raw(junk[: rng.randrange(1000, len(junk))])
    s.raw(s.heartbeat())
    got = poll_until(rx, lambda m: any(x.get_type() == "HEARTBEAT" for x in m))
    assert [m.get_type() for m in got] == ["HEARTBEAT"]
    assert rx.counters["datagrams_cut"] == 10
    assert rx.counters[Rejection.BAD_DATA.counter] == 10 * MAX_BAD_FRAMES
