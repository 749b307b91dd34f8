"""Links over 127.0.0.1: round trips, signing (unsigned, wrongly signed, replayed, forged timestamps,
restarts), key files, fuzzed bytes and unknown ids, reconnects after UDP and TCP peers restart."""

import itertools
import os
import socket
import time

import pytest

from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import codec
from atlas_onboard.mavlink.link import Link
from atlas_onboard.mavlink.signing import read_key, signing_timestamp
from tests.mavlink.loopback import (
    FP,
    MD,
    D,
    RawSender,
    drain,
    free_port,
    kinds,
    make_link,
    poll_until,
    write_key,
)

pytestmark = pytest.mark.deadlines  # sockets and their deadlines


def test_udp_round_trip_between_two_links(closing):
    port = free_port()
    rx, tx = make_link(f"udpin:127.0.0.1:{port}", 1), make_link(f"udpout:127.0.0.1:{port}", 250)
    closing(rx), closing(tx)
    rx.open(), tx.open()
    assert tx.send(codec.encode_observation(tx.dialect, MD, FP))
    msgs = poll_until(rx, lambda m: len(m) >= 1)
    assert kinds(msgs) == ["ATLAS_OBSERVATION"] and msgs[0].get_srcSystem() == 250
    md = codec.decode_observation(msgs[0], msgs[0].get_srcSystem(), FP, check=True)
    assert (md.sensor_id, md.marker_id, md.origin, md.capture_time_us) == (10, 5, 250, MD.capture_time_us)
    # udpin answers the address it last heard from
    assert rx.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    assert kinds(poll_until(tx, lambda m: len(m) >= 1)) == ["HEARTBEAT"]
    assert rx.counters["rx_atlas_observation"] == 1 and tx.counters["tx_atlas_observation"] == 1


def test_send_on_a_closed_link_is_counted_not_raised():
    link = make_link(f"udpout:127.0.0.1:{free_port()}", 250)
    assert link.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3)) is False
    assert link.counters["tx_dropped_link_down"] == 1


def test_random_bytes_truncated_frames_and_unknown_ids_are_counted(closing):
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1)
    closing(rx)
    rx.open()
    s = RawSender(port)
    closing(s)
    rng = __import__("random").Random(1)
    for _ in range(20):
        s.raw(bytes(rng.randrange(256) for _ in range(rng.randrange(1, 200))))
    good = s.observation(seq=7)
    for cut in (1, 5, 12, len(good) - 1):
        s.raw(good[:cut])
    unknown = bytearray(s.heartbeat())
    unknown[7:10] = (47999).to_bytes(3, "little")  # an id no dialect of ours has; the CRC is not even checked
    s.raw(bytes(unknown))
    bad_crc = bytearray(s.observation(seq=8))
    bad_crc[-1] ^= 0xFF
    s.raw(bytes(bad_crc))
    s.raw(s.observation(seq=9))
    msgs = drain(rx, 0.3)
    # Only the intact frame gets through (random bytes never make a valid CRC here).
    assert [(m.get_type(), m.seq) for m in msgs if m.get_type() == "ATLAS_OBSERVATION"] == [("ATLAS_OBSERVATION", 9)]
    assert not any(k.startswith("UNKNOWN") or k == "BAD_DATA" for k in kinds(msgs))
    assert rx.counters["rejected_unknown_id"] >= 1
    assert rx.counters["rejected_bad_data"] >= 2  # the bad CRC and the random bytes at least
    assert rx.counters["read_errors"] == 0 and rx.is_open


# --- signing ----------------------------------------------------------------------------------------


def test_signing_policy_on_a_link_that_requires_it(tmp_path, closing):
    key = os.urandom(32)
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, write_key(tmp_path, key))
    closing(rx)
    rx.open()
    signed, unsigned, wrong = RawSender(port, 250, key), RawSender(port, 251), RawSender(port, 252, os.urandom(32))
    for s in (signed, unsigned, wrong):
        closing(s)
    replay = []
    for k in range(3):
        for s in (signed, unsigned, wrong):
            frame = s.observation(seq=k)
            s.raw(frame)
            if s is signed:
                replay.append(frame)
    for s in (unsigned, wrong):
        s.raw(s.heartbeat())  # the autopilot's or a GCS's unsigned traffic may pass
    for frame in replay:
        signed.raw(frame)
    msgs = drain(rx, 0.3)
    obs = [(m.get_srcSystem(), m.seq) for m in msgs if m.get_type() == "ATLAS_OBSERVATION"]
    assert obs == [(250, 0), (250, 1), (250, 2)]
    assert sorted(m.get_srcSystem() for m in msgs if m.get_type() == "HEARTBEAT") == [251, 252]
    c = rx.counters
    assert c["rejected_unsigned_or_bad_signature"] == 3 + 3 + 3  # unsigned, wrong key, replays
    assert c["rejected_bad_signature"] == 9
    assert c["signature_mismatch"] == 3 + 1  # wrong key: 3 observations and a heartbeat
    assert c["signature_replayed"] == 3


def test_signed_links_talk_and_an_unsigned_autopilot_link_is_unaffected(tmp_path, closing):
    key_file = write_key(tmp_path, os.urandom(32))
    port, ap_port = free_port(), free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, key_file)
    tx = make_link(f"udpout:127.0.0.1:{port}", 250, key_file)
    ap_rx = make_link(f"udpin:127.0.0.1:{ap_port}", 1)  # the autopilot link: no signing at all
    for link in (rx, tx, ap_rx):
        closing(link)
        link.open()
    for _ in range(3):
        tx.send(codec.encode_observation(tx.dialect, MD, FP))
    ap = RawSender(ap_port, 1)
    closing(ap)
    ap.raw(ap.heartbeat())
    ap.raw(ap.frame(D.MAVLink_timesync_message(0, 12345)))
    assert kinds(poll_until(rx, lambda m: len(m) >= 3)) == ["ATLAS_OBSERVATION"] * 3
    assert kinds(poll_until(ap_rx, lambda m: len(m) >= 2)) == ["HEARTBEAT", "TIMESYNC"]
    assert rx.counters["rejected_bad_signature"] == 0 and ap_rx.counters["rejected_bad_signature"] == 0


def test_require_false_accepts_unsigned_observations(tmp_path, closing):
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, write_key(tmp_path, os.urandom(32)), require=False)
    closing(rx)
    rx.open()
    s = RawSender(port, 251)
    closing(s)
    s.raw(s.observation(seq=3))
    assert kinds(poll_until(rx, lambda m: len(m) >= 1)) == ["ATLAS_OBSERVATION"]


def test_a_forged_future_timestamp_cannot_lock_out_a_genuine_peer(tmp_path, closing):
    """pymavlink alone stores a stream's timestamp before checking the signature: one forged frame
    with timestamp 2^48 - 1 would make every genuine frame of that stream a 'replay'."""
    key = os.urandom(32)
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, write_key(tmp_path, key))
    closing(rx)
    rx.open()
    forger = RawSender(port, 250, os.urandom(32), timestamp=2**48 - 2)  # same sysid, compid, link id
    genuine = RawSender(port, 250, key)
    closing(forger), closing(genuine)
    genuine.raw(genuine.observation(seq=1))
    forger.raw(forger.observation(seq=2))
    genuine.raw(genuine.observation(seq=3))
    genuine.raw(genuine.observation(seq=4))
    msgs = drain(rx, 0.3)
    assert [m.seq for m in msgs if m.get_type() == "ATLAS_OBSERVATION"] == [1, 3, 4]
    assert rx.counters["signature_mismatch"] == 1 and rx.counters["signature_replayed"] == 0


def test_signing_timestamps_follow_the_clock_so_a_restarted_peer_accepts_a_long_running_one(tmp_path, closing):
    key_file = write_key(tmp_path, os.urandom(32))
    now = time.time()
    clock = {"tx": now, "rx": now + 120.0}
    port = free_port()
    tx = make_link(f"udpout:127.0.0.1:{port}", 250, key_file, wall=lambda: clock["tx"])
    closing(tx)
    tx.open()  # the sender starts now and runs for two minutes, sending little
    clock["tx"] += 120.0
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, key_file, wall=lambda: clock["rx"])  # a peer that just restarted
    closing(rx)
    rx.open()
    tx.send(codec.encode_observation(tx.dialect, MD, FP))
    assert kinds(poll_until(rx, lambda m: len(m) >= 1)) == ["ATLAS_OBSERVATION"]
    # A sender that only counts messages (pymavlink's own behaviour) is two minutes behind: refused.
    stale = RawSender(port, 251, key_file.read_bytes(), timestamp=signing_timestamp(now) + 5)
    closing(stale)
    stale.raw(stale.observation(seq=1))
    assert drain(rx, 0.3) == []
    assert rx.counters["signature_stream_too_old"] == 1


def test_timestamp_persists_across_a_restart_without_a_real_time_clock(tmp_path, closing):
    key_file = write_key(tmp_path, os.urandom(32))
    state = tmp_path / "state"
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, key_file)
    closing(rx)
    rx.open()
    url = f"udpout:127.0.0.1:{port}"
    first = make_link(url, 250, key_file, state_dir=state)
    first.open()
    first.send(codec.encode_observation(first.dialect, MD, FP))
    assert len(poll_until(rx, lambda m: len(m) >= 1)) == 1
    saved_from = first.mav.signing.timestamp
    first.close()
    assert len(list(state.glob("signing-*.json"))) == 1
    # Restart with the clock at 2015-01-02 (no RTC): the persisted timestamp, not the clock, wins.
    boot_clock = 1420070400 + 86400.0
    second = make_link(url, 250, key_file, state_dir=state, wall=lambda: boot_clock)
    closing(second)
    second.open()
    assert second.mav.signing.timestamp >= saved_from + 10 * 100_000
    second.send(codec.encode_observation(second.dialect, MD, FP))
    assert len(poll_until(rx, lambda m: len(m) >= 1)) == 1
    # Without the state file the same restart signs in the past: the receiver calls it a replay.
    third = make_link(url, 250, key_file, wall=lambda: boot_clock)
    closing(third)
    third.open()
    third.send(codec.encode_observation(third.dialect, MD, FP))
    assert drain(rx, 0.3) == []
    assert rx.counters["signature_replayed"] == 1


@pytest.mark.parametrize("mode", [0o644, 0o640, 0o604, 0o660])
def test_key_file_readable_by_others_is_refused(tmp_path, mode):
    path = write_key(tmp_path, b"k" * 32, mode)
    with pytest.raises(AtlasError, match="readable by group or others"):
        read_key(path)
    with pytest.raises(AtlasError, match="readable by group or others"):
        make_link("udpin:127.0.0.1:1", 1, path)


def test_key_file_formats(tmp_path):
    key = bytes(range(32))
    assert read_key(write_key(tmp_path, key, name="raw.key")) == key
    assert read_key(write_key(tmp_path, key.hex().encode() + b"\n", name="hex.key")) == key
    with pytest.raises(AtlasError, match="expected 32 bytes"):
        read_key(write_key(tmp_path, b"short", name="short.key"))
    with pytest.raises(AtlasError, match="cannot read"):
        read_key(tmp_path / "missing.key")


# --- reconnects -------------------------------------------------------------------------------------


def test_tcp_peer_restart_reconnects_with_backoff(closing):
    port = free_port(socket.SOCK_STREAM)

    def listen():
        srv = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        srv.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        srv.bind(("127.0.0.1", port))
        srv.listen(1)
        srv.settimeout(5.0)
        return srv

    hb = RawSender(1, 1)
    closing(hb)
    srv = listen()
    link = make_link(f"tcp:127.0.0.1:{port}", 1)
    closing(link)
    link.open()
    conn, _ = srv.accept()
    conn.sendall(hb.heartbeat())
    assert kinds(poll_until(link, lambda m: len(m) >= 1)) == ["HEARTBEAT"]
    # The peer restarts: its socket closes and for a while nothing listens.
    conn.close()
    srv.close()
    poll_until(link, lambda m: False, timeout_s=0.5)
    assert link.counters["read_errors"] == 1 and link.counters["open_errors"] >= 1 and not link.is_open
    assert link.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3)) is False  # counted while down
    srv = listen()
    closing(srv)
    poll_until(link, lambda m: link.is_open, timeout_s=5.0)
    conn, _ = srv.accept()
    closing(conn)
    assert link.counters["reconnects"] == 1
    conn.sendall(hb.heartbeat())
    assert kinds(poll_until(link, lambda m: len(m) >= 1)) == ["HEARTBEAT"]
    assert link.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    conn.settimeout(5.0)
    assert conn.recv(100)[0] == 0xFD  # our MAVLink 2 frame reached the restarted peer


def test_udp_peer_restart_on_a_new_source_port(closing):
    port = free_port()
    link = make_link(f"udpin:127.0.0.1:{port}", 1)
    closing(link)
    link.open()
    first = RawSender(port, 250)
    first.raw(first.heartbeat())
    assert len(poll_until(link, lambda m: len(m) >= 1)) == 1
    first.close()  # the peer process dies; its successor sends from another port
    second = RawSender(port, 250)
    closing(second)
    second.raw(second.heartbeat())
    assert len(poll_until(link, lambda m: len(m) >= 1)) == 1
    link.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))  # replies go to the new address
    second.sock.settimeout(5.0)
    assert second.sock.recv(300)[0] == 0xFD
    assert link.counters["read_errors"] == 0


def test_udpout_to_a_peer_that_is_down_then_up(closing):
    port = free_port()
    link = make_link(f"udpout:127.0.0.1:{port}", 1)
    closing(link)
    link.open()
    for _ in range(3):  # nobody listens: ICMP port unreachable must not break the link
        link.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
        link.poll(0.02)
    assert link.is_open and link.counters["read_errors"] == 0
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    closing(peer)
    peer.bind(("127.0.0.1", port))
    peer.settimeout(5.0)
    assert link.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    frame = peer.recv(300)
    (msg,) = [m for m in D.MAVLink(None).parse_buffer(frame)]
    assert msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == 1 and msg.get_srcComponent() == 197


def test_thread_mode_survives_a_failing_handler(closing):
    port = free_port()
    link = make_link(f"udpin:127.0.0.1:{port}", 1)
    seen = []

    def handler(lk: Link, msg, arrival_ns: int) -> None:
        seen.append((msg.get_type(), arrival_ns > 0))
        if len(seen) == 1:
            raise RuntimeError("a bug in the handler")

    link.start(handler)
    closing(link)
    s = RawSender(port, 250)
    closing(s)
    deadline = time.monotonic() + 5
    while len(seen) < 2 and time.monotonic() < deadline:
        s.raw(s.heartbeat())
        time.sleep(0.05)
    assert seen[:2] == [("HEARTBEAT", True), ("HEARTBEAT", True)]
    assert link.counters["handler_errors"] == 1


def test_serial_device_that_vanishes_and_returns(tmp_path, closing):
    """A USB serial adapter unplugged and plugged back (a pty behind a stable symlink)."""
    device = tmp_path / "ttyAUTOPILOT"
    hb = RawSender(1, 1)
    closing(hb)

    def plug():
        master, slave = os.openpty()
        if device.is_symlink():
            device.unlink()
        device.symlink_to(os.ttyname(slave))
        return master, slave

    master, slave = plug()
    link = make_link(f"{device},921600", 1)
    closing(link)
    link.open()
    os.write(master, hb.heartbeat())
    assert kinds(poll_until(link, lambda m: len(m) >= 1)) == ["HEARTBEAT"]
    os.close(master)  # unplugged
    os.close(slave)
    poll_until(link, lambda m: link.counters["read_errors"] >= 1 and link.counters["open_errors"] >= 1, 5.0)
    assert link.counters["read_errors"] == 1 and not link.is_open
    master, slave = plug()  # plugged back (another pts, the same symlink)
    try:
        poll_until(link, lambda m: link.is_open, 5.0)
        assert link.counters["reconnects"] == 1
        os.write(master, hb.heartbeat())
        assert kinds(poll_until(link, lambda m: len(m) >= 1)) == ["HEARTBEAT"]
        assert link.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
        time.sleep(0.05)
        assert os.read(master, 100)[0] == 0xFD
    finally:
        link.close()
        os.close(master)
        os.close(slave)


def test_udpbcast_sends_then_talks_to_whoever_answers(closing):
    port = free_port()
    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    closing(peer)
    peer.bind(("127.0.0.1", port))
    peer.settimeout(5.0)
    link = make_link(f"udpbcast:127.0.0.1:{port}", 1)
    closing(link)
    link.open()
    assert link.send(D.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
    frame, addr = peer.recvfrom(300)
    assert [m.get_type() for m in D.MAVLink(None).parse_buffer(frame)] == ["HEARTBEAT"]
    answer = RawSender(port, 250)
    closing(answer)
    peer.sendto(answer.heartbeat(), addr)
    msgs = poll_until(link, lambda m: len(m) >= 1)
    assert [(m.get_type(), m.get_srcSystem()) for m in msgs] == [("HEARTBEAT", 250)]


@pytest.mark.parametrize(
    ("url", "device", "kwargs"),
    [
        ("/dev/ttyAMA0,921600", "/dev/ttyAMA0", {"baud": 921600}),
        ("/dev/serial/by-id/usb-ArduPilot_fmuv3-if00,115200", "/dev/serial/by-id/usb-ArduPilot_fmuv3-if00",
         {"baud": 115200}),
        ("/dev/ttyACM0", "/dev/ttyACM0", {"baud": 57600}),
        ("tcp:127.0.0.1:5760", "tcp:127.0.0.1:5760", {"retries": 0}),
        ("udpin:0.0.0.0:14550", "udpin:0.0.0.0:14550", {}),
        ("udpout:10.0.0.2:14550", "udpout:10.0.0.2:14550", {}),
        ("udpbcast:192.168.50.255:14600", "udpbcast:192.168.50.255:14600", {}),
    ],
)  # fmt: skip
def test_connection_strings_reach_pymavlink_as_written(monkeypatch, url, device, kwargs):
    calls = []

    class Fake:
        mav = None

    def fake_connection(dev, **kw):
        calls.append((dev, kw))
        return Fake()

    monkeypatch.setattr("atlas_onboard.mavlink.link.mavutil.mavlink_connection", fake_connection)
    link = make_link(url, 7)
    link.open()
    ((dev, kw),) = calls
    assert dev == device
    assert kw == {"source_system": 7, "source_component": 197, **kwargs}
    assert link.mav.srcSystem == 7 and link.mav.srcComponent == 197  # our dialect on this connection


@pytest.mark.skipif(not os.path.exists("/proc/net/udp"), reason="the kernel's UDP drop counts are Linux's /proc")
def test_datagrams_the_kernel_dropped_are_counted(closing):
    """A link that reads too slowly loses datagrams in the kernel: they are counted, not silent."""
    port = free_port()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1)
    closing(rx)
    rx.open()
    buf = codec.encode_observation(D, MD, FP).pack(D.MAVLink(None, srcSystem=250, srcComponent=197))
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for _ in range(5000):  # far more than a default receive buffer holds, none read meanwhile
            s.sendto(buf, ("127.0.0.1", port))
    rx.poll(0.05)
    dropped = rx.counters["kernel_drops"]
    received = rx.counters["rx_atlas_observation"]
    while rx.poll(0.05):
        received = rx.counters["rx_atlas_observation"]
    assert dropped > 0 and received + dropped == 5000, (received, dropped)


@pytest.mark.parametrize("signed", [False, True])
def test_many_messages_travel_in_few_datagrams(tmp_path, closing, signed):
    """send_many packs an image's observations into one datagram, and a long batch into datagrams of
    at most MAX_DATAGRAM_BYTES; the receiving link reads every message, in order, signed or not, with
    consecutive sequence numbers."""
    from dataclasses import replace

    from atlas_onboard.mavlink.link import MAX_DATAGRAM_BYTES

    key_file = write_key(tmp_path, os.urandom(32)) if signed else None
    port = free_port()
    spy = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # a raw socket first: count the datagrams
    spy.bind(("127.0.0.1", port))
    spy.settimeout(0.5)
    closing(spy)
    tx = make_link(f"udpout:127.0.0.1:{port}", 250, key_file)
    closing(tx)
    tx.open()
    image = [codec.encode_observation(tx.dialect, replace(MD, marker_id=m, seq=m), FP) for m in range(4)]
    assert tx.send_many(image)
    first = spy.recv(65535)
    one = len(image[0].get_msgbuf())  # every packed observation has the same length
    assert len(first) == 4 * one  # the image in one datagram
    if not signed:
        assert [m.marker_id for m in D.MAVLink(None).parse_buffer(first)] == [0, 1, 2, 3]
    many = [codec.encode_observation(tx.dialect, replace(MD, marker_id=m % 200, seq=m), FP) for m in range(60)]
    assert tx.send_many(many)
    sizes = []
    with pytest.raises(TimeoutError):
        while True:
            sizes.append(len(spy.recv(65535)))
    # As few datagrams as fit: each full but the last, none over the bound.
    assert sum(sizes) == 60 * one and max(sizes) <= MAX_DATAGRAM_BYTES
    assert all(size + one > MAX_DATAGRAM_BYTES for size in sizes[:-1])
    assert tx.counters["tx_atlas_observation"] == 64
    # The same through a receiving link (signature checks included).
    spy.close()
    rx = make_link(f"udpin:127.0.0.1:{port}", 1, key_file)
    closing(rx)
    rx.open()
    assert tx.send_many(many)
    msgs = poll_until(rx, lambda m: len(m) >= 60)
    assert [m.seq for m in msgs] == list(range(60)) and rx.counters["rejected_bad_signature"] == 0
    header_seqs = [m.get_seq() for m in msgs]
    assert all((b - a) % 256 == 1 for a, b in itertools.pairwise(header_seqs))


@pytest.mark.skipif(os.getuid() != 0, reason="needs root to hand the file to another owner and group")
def test_a_root_owned_key_readable_by_the_services_group_only_is_accepted(tmp_path):
    key = bytes(range(32))
    path = write_key(tmp_path, key, 0o640)
    os.chown(path, 0, 65534)  # root:the service's group, mode 640
    assert read_key(path) == key
    os.chown(path, 65534, 65534)  # the service's own file, group-readable: refused
    with pytest.raises(AtlasError, match="readable by group or others"):
        read_key(path)
    os.chown(path, 0, 65534)
    path.chmod(0o644)  # and others never
    with pytest.raises(AtlasError, match="readable by group or others"):
        read_key(path)
