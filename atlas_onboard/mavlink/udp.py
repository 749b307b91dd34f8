"""Who a UDP link talks to. pymavlink's ``mavudp`` makes every source address that sends it a datagram a
client forever (``udpin``: one byte from a spoofed address turns the node into a reflector towards it,
and each client costs every send), and lets the first sender capture a ``udpbcast`` link. The link
therefore reads and writes the connection's socket itself, through :class:`UdpEndpoint`:

- ``udpin``: a source address becomes a client only once a frame from it has passed the link's checks
  (:meth:`UdpEndpoint.prove`, called by the link), at most MAX_CLIENTS of them, each forgotten after
  CLIENT_IDLE_S without such a frame; nothing is sent to an address that has not proven itself;
- ``udpbcast``: always to its broadcast address, whoever sends to it;
- ``udpout``: always to its destination.

And how a datagram is read (:func:`parse_datagram`): its frames alone, from a fresh parser state,
within a budget of bad frames.
"""

from __future__ import annotations

import os
import socket
from collections import OrderedDict
from dataclasses import dataclass
from types import ModuleType
from typing import Any

from atlas_onboard.counters import Counters
from atlas_onboard.mavlink.dialect import known_elsewhere
from atlas_onboard.mavlink.framing import reset

_MAGIC_V2, _MAGIC_V1 = 0xFD, 0xFE
_IFLAG_SIGNED = 0x01
_V2_OVERHEAD, _V1_OVERHEAD, _SIGNATURE_LEN = 12, 8, 13  # header and checksum bytes; the signature

MAX_CLIENTS = 16
"""Proven clients of one ``udpin`` link: a swarm's nodes and a ground station or two on the link (the
world file's nodes are what may prove themselves); a new address beyond it waits (counted) until one
falls silent. Bounds the work of every send whatever the network sends."""
CLIENT_IDLE_S = 10.0
"""A client that sent no frame that passed the checks for this long is forgotten (peers send a
HEARTBEAT every second): a node that moved to another address stops receiving at its old one."""
UDP_MAX_DATAGRAM = 65535

Address = tuple[str, int]

RCVBUF_BYTES = 512 * 1024
"""The receive buffer asked for on a UDP link (Linux caps it at net.core.rmem_max; the node logs what
it got). Sized for what is worth keeping: a swarm's traffic for one edge timeout. 16 drones, each
sending a datagram per camera frame at 30 Hz plus fused poses and heartbeats, make about 600
datagrams a second; 250 ms of it at the kernel's ~2 KiB accounting per small datagram is ~300 KiB.
A larger buffer would only hold datagrams older than the edge timeout when a flood fills it; a
smaller one drops the real peers' first under a burst. What does not fit is dropped by the kernel
(``kernel_drops``); the node refuses a forged datagram for its origin before decoding it, so a
flood costs it a header read per datagram, never its own camera's path."""


def udp_socket_drops(sock: Any) -> int | None:
    """Datagrams the kernel dropped for this UDP socket because its receive buffer was full (Linux's
    /proc/net/udp, matched by the socket's inode), or None where that is not available."""
    try:
        inode = str(os.fstat(sock.fileno()).st_ino)
        for table in ("/proc/net/udp", "/proc/net/udp6"):
            with open(table, encoding="ascii") as f:
                for line in f:
                    cols = line.split()
                    if len(cols) > 12 and cols[9] == inode:
                        return int(cols[-1])
    except (OSError, ValueError, AttributeError):
        return None
    return None


MAX_BAD_FRAMES = 4
"""Consecutive frames of one datagram that fail (bytes without a magic, a frame longer than what is
left of the datagram, a bad checksum or signature, an id no dialect defines) after which the rest of
the datagram is dropped (counted): a real sender writes whole, valid frames, so a datagram of garbage
costs at most this many frame checks, whatever its size."""


@dataclass(frozen=True, slots=True)
class DatagramParse:
    """What one datagram held: its messages (BAD_DATA included, for the link to count) and whether its
    rest was dropped after MAX_BAD_FRAMES bad frames in a row."""

    messages: list[Any]
    cut: bool


def _next_magic(data: bytes, start: int) -> int:
    hits = [k for k in (data.find(b"\xfd", start), data.find(b"\xfe", start)) if k >= 0]
    return min(hits) if hits else len(data)


def _is_bad(msg: Any) -> bool:
    kind = msg.get_type()
    if kind == "BAD_DATA":
        return True
    return type(msg).__name__ == "MAVLink_unknown" and msg.get_msgId() not in known_elsewhere()


def _crc_wrong(module: ModuleType, frame: bytes) -> bool:
    """Whether a MAVLink 2 frame of a known id has a wrong checksum (False for anything else: the
    parser decides those)."""
    if frame[0] != _MAGIC_V2:
        return False
    msgtype = module.mavlink_map.get(frame[7] | frame[8] << 8 | frame[9] << 16)
    if msgtype is None:
        return False
    trailer = 2 + (_SIGNATURE_LEN if frame[2] & _IFLAG_SIGNED else 0)
    crc = module.x25crc(frame[1:-trailer])
    crc.accumulate(bytes([msgtype.crc_extra]))
    return bool(crc.crc != frame[-trailer] | frame[1 - trailer] << 8)


def parse_datagram(module: ModuleType, mav: Any, data: bytes) -> DatagramParse:
    """The frames of one UDP datagram, each parsed on its own by ``mav`` (the fast path's or
    pymavlink's parser), from a fresh parser state: a datagram holds whole frames, so a frame cut by
    its end is bad data, never the start of the next datagram's first frame. Each frame's extent is
    read from its header (magic, length, signed flag) before any checksum; after MAX_BAD_FRAMES bad
    frames in a row the rest is dropped (``cut``). A stream (serial, TCP) keeps pymavlink's parser."""
    reset(mav)
    bad_data = module.MAVLink_bad_data
    out: list[Any] = []
    bad = 0
    i, n = 0, len(data)
    while i < n:
        if bad >= MAX_BAD_FRAMES:
            return DatagramParse(out, True)
        magic = data[i]
        if magic not in (_MAGIC_V2, _MAGIC_V1):
            j = _next_magic(data, i + 1)
            out.append(bad_data(bytearray(data[i:j]), "Bad prefix"))
            bad, i = bad + 1, j
            continue
        if n - i < 3:
            end = n + 1
        elif magic == _MAGIC_V2:
            end = i + data[i + 1] + _V2_OVERHEAD + (_SIGNATURE_LEN if data[i + 2] & _IFLAG_SIGNED else 0)
        else:
            end = i + data[i + 1] + _V1_OVERHEAD
        if end > n:
            out.append(bad_data(bytearray(data[i:]), "Frame cut by the end of the datagram"))
            break
        frame = data[i:end]
        i = end
        if bad and _crc_wrong(module, frame):  # garbage seen: the checksum first, without a parser
            out.append(bad_data(bytearray(frame), "invalid MAVLink CRC"))
            bad += 1
            continue
        msgs = mav.parse_buffer(frame) or []
        reset(mav)
        bad = bad + 1 if not msgs or all(_is_bad(m) for m in msgs) else 0
        out.extend(msgs)
    return DatagramParse(out, False)


class ClientTable:
    """The proven clients of a ``udpin`` link (pure: the time is passed in, monotonic seconds)."""

    def __init__(self, max_clients: int = MAX_CLIENTS, idle_s: float = CLIENT_IDLE_S) -> None:
        self.max_clients = max_clients
        self.idle_s = idle_s
        self._last_s: OrderedDict[Address, float] = OrderedDict()  # least recently proven first
        self.admitted = 0
        self.refused = 0
        self.expired = 0

    def prove(self, address: Address, now_s: float) -> bool:
        """``address`` sent a frame that passed the checks: admit or refresh it; False (counted) when
        the table is full of clients that are not idle."""
        self.expire(now_s)
        if address in self._last_s:
            self._last_s[address] = now_s
            self._last_s.move_to_end(address)
            return True
        if len(self._last_s) >= self.max_clients:
            self.refused += 1
            return False
        self._last_s[address] = now_s
        self.admitted += 1
        return True

    def expire(self, now_s: float) -> None:
        """Forget the clients idle for longer than ``idle_s``."""
        while self._last_s:
            address, last = next(iter(self._last_s.items()))
            if now_s - last <= self.idle_s:
                return
            del self._last_s[address]
            self.expired += 1

    def clients(self, now_s: float) -> list[Address]:
        """The clients to send to now."""
        self.expire(now_s)
        return list(self._last_s)


class UdpEndpoint:
    """Reads and writes a pymavlink ``mavudp`` connection's socket (its own ``recv`` and ``write`` are not
    used; see the module). ``prove`` and ``write`` are called under the link's send lock."""

    def __init__(self, conn: Any, counters: Counters) -> None:
        self.sock: socket.socket = conn.port
        self.server = bool(conn.udp_server)
        self.counters = counters
        self.table = ClientTable()
        self._destination: Address | None = None
        if not self.server:
            host, port = conn.destination_addr
            self._destination = (socket.gethostbyname(host), int(port))  # resolved once, as pymavlink does

    def recv(self) -> tuple[bytes, Address]:
        """One datagram and its source (b"" when none is waiting)."""
        try:
            data, address = self.sock.recvfrom(UDP_MAX_DATAGRAM)
        except (BlockingIOError, InterruptedError):
            return b"", ("", 0)
        except ConnectionRefusedError:  # an earlier send's ICMP port unreachable: not a read error
            return b"", ("", 0)
        return data, address

    def prove(self, address: Address, now_s: float) -> None:
        """A frame from ``address`` passed the link's checks (``udpin``: admit it as a client)."""
        if not self.server:
            return
        before = self.table.admitted, self.table.refused, self.table.expired
        self.table.prove(address, now_s)
        for name, was, now in zip(
            ("udp_clients_admitted", "udp_clients_refused", "udp_clients_expired"),
            before,
            (self.table.admitted, self.table.refused, self.table.expired),
            strict=True,
        ):
            if now > was:
                self.counters.inc(name, now - was)

    def write(self, data: bytes, now_s: float) -> None:
        """Send one datagram: to every proven client (``udpin``; none yet: counted, not sent), or to the
        destination (``udpout``, ``udpbcast``). Raises OSError as ``sendto`` does."""
        if self._destination is not None:
            self.sock.sendto(data, self._destination)
            return
        expired = self.table.expired
        clients = self.table.clients(now_s)
        if self.table.expired > expired:
            self.counters.inc("udp_clients_expired", self.table.expired - expired)
        if not clients:
            self.counters.inc("udp_tx_no_client")
            return
        for address in clients:
            try:
                self.sock.sendto(data, address)
            except (ConnectionRefusedError, BlockingIOError):  # one client gone or slow: the others still get it
                self.counters.inc("udp_tx_errors")
