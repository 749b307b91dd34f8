"""How a connection string becomes a pymavlink connection that speaks our dialect: serial (a device path
and baud rate), TCP (one attempt: the link does the backoff) or UDP, with the framing fast path's parser
(:mod:`~atlas_onboard.mavlink.framing`) and MAVLink 2 only; and a UDP socket's receive buffer sized.
The link (:mod:`~atlas_onboard.mavlink.link`) opens, reopens and reads it."""

from __future__ import annotations

import logging
import socket
from types import ModuleType
from typing import Any

from pymavlink import mavutil

from atlas_onboard.mavlink import framing
from atlas_onboard.mavlink.udp import RCVBUF_BYTES

_logger = logging.getLogger(__name__)


def is_serial(url: str) -> bool:
    """Any absolute device path (``/dev/ttyAMA0,921600``, ``/dev/serial/by-id/...``) or ``COMn`` is serial."""
    return url.startswith(("/", "COM"))


def connect(url: str, dialect: ModuleType, system_id: int, component_id: int, deferred_ids: frozenset[int]) -> Any:
    """A pymavlink connection to ``url`` with ``dialect``'s parser (the messages of ``deferred_ids`` handed
    on undecoded where the fast path can); raises what pymavlink raises (a missing device, a refused TCP
    connect)."""
    kwargs: dict[str, Any] = {"source_system": system_id, "source_component": component_id}
    if is_serial(url):
        device, _, baud = url.partition(",")
        conn = mavutil.mavlink_connection(device, baud=int(baud or 57600), **kwargs)
    elif url.startswith("tcp:"):
        conn = mavutil.mavlink_connection(url, retries=0, **kwargs)  # one attempt: we do the backoff
        framing.raise_on_close(conn)
    else:
        conn = mavutil.mavlink_connection(url, **kwargs)
    # Our dialect (common.xml plus the atlas messages) on this connection only.
    conn.mav = framing.parser(dialect, conn, system_id, component_id, deferred_ids)
    # Our dialect speaks MAVLink 2 only; without this, mavutil's protocol auto-switch would replace
    # conn.mav with its global dialect on the first MAVLink 2 byte.
    conn.WIRE_PROTOCOL_VERSION = "2.0"
    conn.first_byte = False
    return conn


def size_receive_buffer(sock: socket.socket, name: str, url: str, say: bool) -> None:
    """Ask for RCVBUF_BYTES; log what the kernel gave when ``say`` (Linux reports twice the usable size).
    ``name``, ``url``: the link's, for the log."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
        got = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    except OSError as exc:
        _logger.warning("%s: cannot size the receive buffer of %s: %s", name, url, exc.strerror)
        return
    if say:
        _logger.info("%s: %s receive buffer %d bytes (asked %d)", name, url, got, RCVBUF_BYTES)
