"""A transparent relay between a node and its autopilot that keeps what the bench check needs.

``atlas-onboard preflight`` puts it on the autopilot link: the node's bytes go to the autopilot and
the autopilot's to the node unchanged (signed or not), and a copy of each is parsed for the messages
the checks read: the vision poses the node sends (with their arrival time here, which is within a
millisecond of the autopilot's), the autopilot's ATTITUDE, LOCAL_POSITION_NED, HEARTBEAT, PARAM_VALUE
and GPS_GLOBAL_ORIGIN, and both halves of TIMESYNC. It also asks the autopilot for parameters
(PARAM_REQUEST_READ) and its EKF origin (MAV_CMD_REQUEST_MESSAGE).
"""

from __future__ import annotations

import select
import socket
import struct
import threading
import time

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation  # here, not in the relay's thread: an import there stalls it

from atlas_onboard.mavlink.samples import AttitudeSample, PositionSample, Tap, VisionSample

PREFLIGHT_COMPONENT = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER4  # not the node's (191): the answers are told apart
GPS_GLOBAL_ORIGIN_ID = 49
_INTEGER_TYPES = (mavlink.MAV_PARAM_TYPE_INT32, mavlink.MAV_PARAM_TYPE_UINT32)


def _q_from_euler_wxyz(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    x, y, z, w = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
    return float(w), float(x), float(y), float(z)


class Relay:
    """Listen on 127.0.0.1 (``port``; the node's URL is ``udpout:127.0.0.1:PORT``) and relay to ``autopilot_url``."""

    def __init__(self, autopilot_url: str, system_id: int) -> None:
        self.tap = Tap()
        self._node_sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._node_sock.bind(("127.0.0.1", 0))
        self._node_sock.setblocking(False)
        self.port = self._node_sock.getsockname()[1]
        self._node_addr: tuple[str, int] | None = None
        self._ap = mavutil.mavlink_connection(
            autopilot_url, source_system=system_id, source_component=PREFLIGHT_COMPONENT, dialect="common"
        )
        self._own = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=PREFLIGHT_COMPONENT)
        self._from_node = mavlink.MAVLink(None)
        self._from_ap = mavlink.MAVLink(None)
        for parser in (self._from_node, self._from_ap):
            parser.robust_parsing = True
        self._requests: set[int] = set()  # ts1 of the autopilot's TIMESYNC requests
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="preflight-relay", daemon=True)

    def start(self) -> Relay:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._node_sock.close()
        self._ap.close()

    def request_params(self, names: list[str]) -> None:
        """PARAM_REQUEST_READ for each name (the answers land in ``tap.params``)."""
        target = self.tap.autopilot_system or 1
        for name in names:
            self._send(self._own.param_request_read_encode(target, 1, name.encode(), -1))

    def request_origin(self) -> None:
        target = self.tap.autopilot_system or 1
        cmd = mavlink.MAV_CMD_REQUEST_MESSAGE
        self._send(self._own.command_long_encode(target, 1, cmd, 0, GPS_GLOBAL_ORIGIN_ID, 0, 0, 0, 0, 0, 0))

    def _send(self, msg: mavlink.MAVLink_message) -> None:
        try:
            self._ap.write(msg.pack(self._own))
        except OSError:
            pass

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self._node_sock, self._ap.fd], [], [], 0.05)
            except (OSError, ValueError):
                return
            now = time.time()
            if self._node_sock in ready:
                try:
                    data, self._node_addr = self._node_sock.recvfrom(65535)
                except OSError:
                    data = b""
                if data:
                    self._ap.write(data)
                    self._inspect_node(data, now)
            if self._ap.fd in ready:
                try:
                    data = self._ap.recv(65535)
                except OSError:
                    data = b""
                if data:
                    if self._node_addr is not None:
                        try:
                            self._node_sock.sendto(data, self._node_addr)
                        except OSError:
                            pass
                    self._inspect_autopilot(bytes(data), now)

    def _inspect_node(self, data: bytes, now: float) -> None:
        try:
            msgs = self._from_node.parse_buffer(data) or []
        except mavlink.MAVError:
            return
        t = self.tap
        with t.lock:
            for msg in msgs:
                kind = msg.get_type()
                if kind in ("VISION_POSITION_ESTIMATE", "ODOMETRY"):
                    if msg._signed:
                        t.signed_from_node += 1
                    else:
                        t.unsigned_from_node += 1
                if kind == "VISION_POSITION_ESTIMATE":
                    q = _q_from_euler_wxyz(msg.roll, msg.pitch, msg.yaw)
                    t.vision.append(VisionSample(now, int(msg.usec), (msg.x, msg.y, msg.z), q))
                elif kind == "ODOMETRY":
                    w, x, y, z = (float(v) for v in msg.q)
                    t.vision.append(VisionSample(now, int(msg.time_usec), (msg.x, msg.y, msg.z), (w, x, y, z)))
                elif kind == "TIMESYNC" and msg.tc1 != 0 and int(msg.ts1) in self._requests:
                    t.timesync_answers += 1

    def _inspect_autopilot(self, data: bytes, now: float) -> None:
        try:
            msgs = self._from_ap.parse_buffer(data) or []
        except mavlink.MAVError:
            return
        t = self.tap
        with t.lock:
            for msg in msgs:
                kind = msg.get_type()
                from_fc = msg.get_srcComponent() == 1
                if kind == "HEARTBEAT" and from_fc and msg.autopilot != mavlink.MAV_AUTOPILOT_INVALID:
                    t.autopilot, t.autopilot_system = int(msg.autopilot), msg.get_srcSystem()
                elif kind == "ATTITUDE":
                    t.attitude.append(AttitudeSample(now, msg.roll, msg.pitch, msg.yaw))
                elif kind == "LOCAL_POSITION_NED":
                    t.local_position.append(PositionSample(now, (msg.x, msg.y, msg.z)))
                elif kind == "PARAM_VALUE":
                    name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
                    value = float(msg.param_value)
                    if t.autopilot == mavlink.MAV_AUTOPILOT_PX4 and msg.param_type in _INTEGER_TYPES:
                        value = float(struct.unpack("<i", struct.pack("<f", value))[0])  # PX4 sends the int's bytes
                    t.params[name.rstrip("\0")] = value
                elif kind == "GPS_GLOBAL_ORIGIN":
                    t.origin = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
                elif kind == "TIMESYNC" and msg.tc1 == 0:
                    t.timesync_requests += 1
                    self._requests.add(int(msg.ts1))
