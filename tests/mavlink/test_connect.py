"""A connection string becomes a pymavlink connection that speaks our dialect, MAVLink 2 only."""

import socket

import pytest
from pymavlink import mavutil

from atlas_onboard.mavlink import dialect
from atlas_onboard.mavlink.connect import connect, is_serial, size_receive_buffer
from atlas_onboard.mavlink.udp import RCVBUF_BYTES


@pytest.mark.parametrize(
    ("url", "serial"),
    [
        ("/dev/ttyAMA0,921600", True),
        ("/dev/serial/by-id/usb-Holybro_Pixhawk6C-if00", True),
        ("COM3", True),
        ("udpin:0.0.0.0:14550", False),
        ("udpout:127.0.0.1:14550", False),
        ("tcp:127.0.0.1:5760", False),
    ],
)
def test_device_paths_and_com_ports_are_serial(url, serial):
    assert is_serial(url) is serial


def test_a_udp_connection_speaks_our_dialect_in_mavlink_2_only():
    d = dialect.load()
    conn = connect("udpout:127.0.0.1:9", d, 7, 197, frozenset())
    try:
        assert isinstance(conn, mavutil.mavudp)
        assert conn.WIRE_PROTOCOL_VERSION == "2.0" and conn.first_byte is False
        assert isinstance(conn.mav, d.MAVLink)  # the dialect's parser (fast path or pymavlink's own)
        assert (conn.mav.srcSystem, conn.mav.srcComponent) == (7, 197)
    finally:
        conn.close()


def test_the_receive_buffer_is_asked_for():
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        before = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        size_receive_buffer(sock, "peer0", "udpin:0.0.0.0:0", say=True)
        after = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
    assert after > before  # the kernel caps it at net.core.rmem_max, but grants more than 4 KiB
    assert RCVBUF_BYTES > 4096
