"""One MAVLink connection: opened from a pymavlink connection string with the atlas dialect, reopened
with backoff when it fails, optionally signed; read either by its own thread (:meth:`Link.start`) or
by the caller (:meth:`Link.poll`).

A link knows nothing of the graph: it returns (or hands to a callback) every message that decoded
and passed the signing policy, and counts what it drops (bad CRC, bad or missing signature where it
is required, replays, unknown ids, read errors). Framing is :mod:`~atlas_onboard.mavlink.framing`'s
(with its off switch), signing :mod:`~atlas_onboard.mavlink.signing`'s.
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import threading
import time
from collections import Counter as Tally
from collections.abc import Callable, Collection, Iterator, Sequence
from pathlib import Path
from typing import Any

from pymavlink import mavutil

from atlas_onboard.config import LinkConfig
from atlas_onboard.core.rejection import Rejection
from atlas_onboard.counters import Counters
from atlas_onboard.mavlink import dialect, framing
from atlas_onboard.mavlink.connect import connect, size_receive_buffer
from atlas_onboard.mavlink.signing import LinkSigning
from atlas_onboard.mavlink.udp import UdpEndpoint, parse_datagram, udp_socket_drops

_logger = logging.getLogger(__name__)

BACKOFF_S = (0.2, 0.5, 1.0, 2.0, 5.0)
DATAGRAMS_PER_POLL = 16
DROPS_CHECK_S = 1.0  # how often a UDP link reads the kernel's drop count of its socket
MAX_HOLD_S = 0.02  # a reader held by the node waits no longer than this
MAX_DATAGRAM_BYTES = 1400  # several messages in one UDP datagram, below a network's MTU
Handler = Callable[["Link", Any, int], None]
OriginCheck = Callable[[Any], bool]


class Link:
    """A MAVLink connection with reconnects, counters and optional signing.

    Args:
        config: the connection string, signing and rate settings.
        name: used in counter prefixes and log lines (``autopilot``, ``peer0``).
        system_id, component_id: what this node sends as (the autopilot's system id, 197).
        state_dir: where the signing timestamp persists (None: not persisted).
        link_id: the MAVLink signing link id of this connection.
        wall_clock: UNIX time in seconds (signing timestamps); injectable for tests.
        deferred: names of messages handed on as :class:`framing.Deferred` (checked, decoded only when
            a field is read) where the fast path can (unsigned MAVLink 2); others are decoded as they come.
        origin_ok: which messages may prove a UDP source address a client (see :mod:`.udp`): such a
            message that passed the checks (signed, on a link that requires it) makes its sender's
            address one the link sends to. Default: any message.
    """

    def __init__(
        self,
        config: LinkConfig,
        name: str,
        system_id: int,
        component_id: int,
        state_dir: Path | None = None,
        link_id: int = 0,
        *,
        wall_clock: Callable[[], float] = time.time,
        deferred: Collection[str] = (),
        origin_ok: OriginCheck | None = None,
    ) -> None:
        self.config = config
        self.name = name
        self.system_id = system_id
        self.component_id = component_id
        self.counters = Counters()
        self.dialect = dialect.load()
        names = set(deferred)
        self._deferred_ids = frozenset(t.id for t in self.dialect.mavlink_map.values() if t.msgname in names)
        self._wall = wall_clock
        digest = hashlib.sha256(f"{config.url}|{system_id}|{component_id}".encode()).hexdigest()[:12]
        self.signing = (
            LinkSigning(
                config.signing,
                self.dialect,
                link_id,
                self.counters,
                state_dir / f"signing-{digest}.json" if state_dir is not None else None,
                wall_clock,
            )
            if config.signing is not None
            else None
        )
        self._origin_ok = origin_ok
        self._conn: Any = None
        self._udp: UdpEndpoint | None = None
        self._send_lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._handler: Handler | None = None
        self._read_done: Callable[[Link], None] | None = None
        self._may_read: threading.Event | None = None
        self._kernel_drops = 0
        self._next_drops_check_s = 0.0
        self._backoff = 0
        self._next_open_s = 0.0  # monotonic time of the next reopen attempt
        self._opened_before = False
        self.connected = threading.Event()

    # --- connection ---------------------------------------------------------------------------------

    def open(self) -> None:
        """Open the connection now (raises what pymavlink raises: a missing device, a refused TCP connect)."""
        url = self.config.url
        conn = connect(url, self.dialect, self.system_id, self.component_id, self._deferred_ids)
        if self.signing is not None:
            self.signing.setup(conn)
        udp = None
        if isinstance(conn, mavutil.mavudp):
            size_receive_buffer(conn.port, self.name, url, say=not self._opened_before)
            udp = UdpEndpoint(conn, self.counters)
        with self._send_lock:
            self._conn, self._udp = conn, udp
        self._kernel_drops = 0  # a new socket counts from zero
        self.connected.set()
        if self._opened_before:
            self.counters.inc("reconnects")
            _logger.info("%s: link %s open again", self.name, url)
        self._opened_before = True

    def save_timestamp(self) -> None:
        """Persist the signing timestamp (see :meth:`LinkSigning.save`)."""
        conn = self._conn
        if self.signing is not None and conn is not None:
            self.signing.save(conn, self.name)

    @property
    def is_open(self) -> bool:
        return self._conn is not None

    # --- receiving ----------------------------------------------------------------------------------

    def poll(self, timeout_s: float = 0.05) -> list[Any]:
        """Wait up to ``timeout_s`` for data and return the messages that passed (possibly none).

        Never raises for anything the link or the bytes do: a failed read closes the connection and
        the next calls reopen it with backoff (0.2 s growing to 5 s). Dropped input is counted.
        """
        return [msg for msgs in self._reads(timeout_s) for msg in msgs]

    def _reads(self, timeout_s: float) -> Iterator[list[Any]]:
        """The messages that passed, one read (one datagram) at a time, decoded only when asked for:
        a reader that stops between two reads leaves the rest in the socket, undecoded."""
        conn = self._conn
        if conn is None:
            self._try_reopen(timeout_s)
            return
        try:
            # Raw bytes and pymavlink's parser, not mavutil's recv_match: that one also keeps
            # per-message bookkeeping for interactive tools, which costs more than the decode.
            ready = conn.select(timeout_s)
        except Exception as exc:
            self._failed(exc)
            return
        # A UDP socket holds one datagram per message: take what is queued (up to a bound) per
        # wake-up rather than one select per datagram. Streams return many messages per read.
        udp = self._udp
        for _ in range(DATAGRAMS_PER_POLL if ready and udp is not None else int(ready)):
            try:
                if udp is not None:
                    data, source = udp.recv()
                    msgs = self._datagram(conn, data) if data else None
                else:
                    data = conn.recv(4096)
                    msgs = conn.mav.parse_buffer(data) if data else None
            except Exception as exc:  # the device vanished or the peer went away: reopen with backoff
                self._failed(exc)
                return
            if not data:
                break
            passed = [m for m in msgs or () if self._accept(m)]
            if udp is not None and any(self._proves(m) for m in passed):
                with self._send_lock:
                    udp.prove(source, time.monotonic())
            yield passed
        self._housekeeping(conn)

    def _datagram(self, conn: Any, data: bytes) -> list[Any]:
        """One UDP datagram's frames, parsed from a fresh parser state within a budget of bad frames."""
        parsed = parse_datagram(self.dialect, conn.mav, data)
        if parsed.cut:
            self.counters.inc("datagrams_cut")
        return parsed.messages

    def _proves(self, msg: Any) -> bool:
        """Whether ``msg`` (which passed the link's checks) makes its sender's address a client: from
        a sender ``origin_ok`` allows, and signed where the link requires signatures."""
        if self._origin_ok is not None and not self._origin_ok(msg):
            return False
        signing = self.signing
        return signing is None or not signing.config.require or framing.is_signed(msg)

    def _failed(self, exc: Exception) -> None:
        self.counters.inc("read_errors")
        _logger.warning("%s: link %s failed (%s); reopening", self.name, self.config.url, exc)
        self._drop()

    def _try_reopen(self, timeout_s: float) -> None:
        wait = self._next_open_s - time.monotonic()
        if wait > 0:
            self._stop.wait(min(wait, timeout_s))
            if time.monotonic() < self._next_open_s:
                return
        try:
            self.open()
        except Exception as exc:  # serial device gone, port in use, peer down: retry with backoff
            self.counters.inc("open_errors")
            _logger.debug("%s: cannot open %s: %s", self.name, self.config.url, exc)
            self._next_open_s = time.monotonic() + BACKOFF_S[min(self._backoff, len(BACKOFF_S) - 1)]
            self._backoff += 1
            return
        self._backoff = 0

    def _housekeeping(self, conn: Any) -> None:
        now = time.monotonic()
        if isinstance(conn, mavutil.mavudp) and now >= self._next_drops_check_s:
            # What never reached us: the kernel drops datagrams when we read too slowly (counted).
            self._next_drops_check_s = now + DROPS_CHECK_S
            drops = udp_socket_drops(conn.port)
            if drops is not None and drops > self._kernel_drops:
                self.counters.inc("kernel_drops", drops - self._kernel_drops)
                self._kernel_drops = drops
        if self.signing is None:
            return
        with self._send_lock:  # send() advances it too: never write back a value it has passed
            self.signing.advance(conn)
        if self.signing.save_due():
            self.save_timestamp()

    def _accept(self, msg: Any) -> bool:
        """Count and drop what must not go further; True for a message to hand on."""
        kind = msg.get_type()
        if kind == "BAD_DATA":
            reason = str(msg.reason)
            self.counters.inc(Rejection.BAD_SIGNATURE if "signature" in reason else Rejection.BAD_DATA)
            return False
        if type(msg).__name__ == "MAVLink_unknown" or kind.startswith("UNKNOWN"):
            # pymavlink returns unknown ids before any CRC or signature check: never trust them. An id
            # another public dialect defines (ArduPilot's AHRS, ...) is only not ours to read.
            msg_id = kind.rpartition("_")[2]  # pymavlink names it UNKNOWN_<id>
            other = msg_id.isdigit() and int(msg_id) in dialect.known_elsewhere()
            self.counters.inc("rx_other_dialect" if other else Rejection.UNKNOWN_ID)
            return False
        self.counters.inc(f"rx_{kind.lower()}")
        return True

    def _drop(self) -> None:
        self.connected.clear()
        with self._send_lock:
            conn, self._conn, self._udp = self._conn, None, None
        self._next_open_s = time.monotonic() + BACKOFF_S[0]
        if conn is not None:
            with contextlib.suppress(Exception):
                conn.close()

    # --- thread mode --------------------------------------------------------------------------------

    def start(
        self,
        handler: Handler,
        may_read: threading.Event | None = None,
        read_done: Callable[[Link], None] | None = None,
    ) -> None:
        """Read in a thread of its own: ``handler(link, msg, arrival_monotonic_ns)`` for each message,
        then ``read_done(link)`` after the messages of each read (a datagram, or a chunk of a stream).

        With ``may_read``, the thread reads only while it is set (waiting at most ``MAX_HOLD_S``):
        the node clears it while it evaluates and publishes its own pose, so that decoding the rest
        of a burst does not take the interpreter from it (the datagrams wait in the socket's buffer).
        """
        self._handler = handler
        self._read_done = read_done
        self._may_read = may_read
        self._try_reopen(0.0)
        self._thread = threading.Thread(target=self._run, name=f"link-{self.name}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self._wait_turn()
            for msgs in self._reads(0.05):
                arrival_ns = time.monotonic_ns()
                for msg in msgs:
                    if self._handler is None:
                        continue
                    try:
                        self._handler(self, msg, arrival_ns)
                    except Exception:  # a bug in a handler must not kill the link's thread
                        self.counters.inc("handler_errors")
                        _logger.exception("%s: handler failed on %s", self.name, msg.get_type())
                if self._read_done is not None:
                    try:
                        self._read_done(self)
                    except Exception:  # likewise
                        self.counters.inc("handler_errors")
                        _logger.exception("%s: handler failed after a read", self.name)
                self._wait_turn()  # between two datagrams: the node may be publishing

    def _wait_turn(self) -> None:
        if self._may_read is not None and not self._may_read.is_set():
            self._may_read.wait(MAX_HOLD_S)

    def close(self) -> None:
        """Stop the thread (if any), save the signing timestamp and close the connection."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.save_timestamp()
        self._drop()

    # --- sending ------------------------------------------------------------------------------------

    def send(self, msg: Any) -> bool:
        """Send one message (thread-safe); False (counted) when the link is down or the write fails."""
        return self.send_many((msg,))

    def send_many(self, msgs: Sequence[Any]) -> bool:
        """Send several messages back to back (thread-safe), each as pymavlink's ``send`` would
        (sequence numbers, signing, counters), in as few writes as fit: on UDP, datagrams of up to
        ``MAX_DATAGRAM_BYTES`` (below a network's MTU: a lost fragment would lose them all). A peer
        reads them all from one datagram; each costs the sender, the mesh and the receiver a
        datagram less. False (counted) when the link is down or a write fails."""
        conn = self._conn
        if conn is None:
            self.counters.inc("tx_dropped_link_down", len(msgs))
            return False
        cpu_ns = time.thread_time_ns()
        try:
            with self._send_lock:
                if self.signing is not None:
                    self.signing.advance(conn)
                mav = conn.mav
                chunks, chunk = [], b""
                for msg in msgs:
                    buf = msg.pack(mav)
                    mav.seq = (mav.seq + 1) % 256
                    mav.total_packets_sent += 1
                    mav.total_bytes_sent += len(buf)
                    if chunk and len(chunk) + len(buf) > MAX_DATAGRAM_BYTES:
                        chunks.append(chunk)
                        chunk = b""
                    chunk += buf
                chunks.append(chunk)
                udp = self._udp
                for chunk in chunks:
                    if udp is not None:
                        udp.write(chunk, time.monotonic())
                    else:
                        conn.write(chunk)
        except Exception as exc:  # a write error is a dead link: the reader reopens it when its read fails
            self.counters.inc("tx_errors")
            _logger.debug("%s: send failed: %s", self.name, exc)
            return False
        for kind, n in Tally(msg.get_type().lower() for msg in msgs).items():
            self.counters.inc(f"tx_{kind}", n)
        self.counters.inc("tx_calls")  # and their CPU time: what every send costs this thread
        self.counters.inc("tx_cpu_ns", time.thread_time_ns() - cpu_ns)
        return True

    @property
    def mav(self) -> Any:
        """The dialect's MAVLink object of the current connection (for building messages), or None."""
        conn = self._conn
        return conn.mav if conn is not None else None
