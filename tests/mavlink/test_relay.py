"""The bench check's relay: the node's bytes reach the autopilot unchanged and the autopilot's reach
the node, while the messages the checks read are kept (PX4's integer parameters decoded bytewise)."""

from __future__ import annotations

import socket
import struct
import time

from pymavlink.dialects.v20 import common as mavlink

from atlas_onboard.mavlink.relay import Relay


def _wait(pred, timeout=5.0):
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.01)
    return False


def test_relay_is_transparent_and_keeps_what_the_checks_need() -> None:
    ap_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    ap_sock.bind(("127.0.0.1", 0))
    ap_sock.settimeout(2.0)
    relay = Relay(f"udpout:127.0.0.1:{ap_sock.getsockname()[1]}", 7).start()
    node_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    node_sock.bind(("127.0.0.1", 0))
    node_sock.settimeout(2.0)
    node = mavlink.MAVLink(None, srcSystem=7, srcComponent=197)
    ap = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    try:
        t_us = round(time.time() * 1e6) - 30_000
        sent = node.vision_position_estimate_encode(t_us, 0.5, -0.25, -1.0, 0.1, -0.2, 1.5).pack(node)
        node_sock.sendto(sent, ("127.0.0.1", relay.port))
        got, ap_addr = ap_sock.recvfrom(65535)
        assert got == sent  # unchanged
        heartbeat = ap.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, 0, 0, 3).pack(ap)
        ap_sock.sendto(heartbeat, ap_addr)
        assert node_sock.recvfrom(65535)[0] == heartbeat
        assert _wait(lambda: relay.tap.autopilot == mavlink.MAV_AUTOPILOT_PX4)
        bytewise = struct.unpack("<f", struct.pack("<i", 11))[0]  # PX4 sends an INT32's bytes in the float
        ap_sock.sendto(
            ap.param_value_encode(b"EKF2_EV_CTRL", bytewise, mavlink.MAV_PARAM_TYPE_INT32, 1, 0).pack(ap)
            + ap.param_value_encode(b"EKF2_EV_DELAY", 42.5, mavlink.MAV_PARAM_TYPE_REAL32, 1, 0).pack(ap),
            ap_addr,
        )
        assert _wait(lambda: len(relay.tap.params) == 2)
        assert relay.tap.params == {"EKF2_EV_CTRL": 11.0, "EKF2_EV_DELAY": 42.5}
        relay.request_params(["EKF2_EV_DELAY"])
        asked = ap.parse_buffer(ap_sock.recvfrom(65535)[0])
        assert asked[0].get_type() == "PARAM_REQUEST_READ" and asked[0].param_id == "EKF2_EV_DELAY"
        assert asked[0].target_system == 1
    finally:
        relay.stop()
        ap_sock.close()
        node_sock.close()
    v = relay.tap.vision[0]
    assert v.usec == t_us and v.xyz_ned_m == (0.5, -0.25, -1.0)
    assert 0.0 < v.arrival_s - t_us * 1e-6 < 1.0
