"""A simulated autopilot: the MAVLink endpoint a node's autopilot link talks to in simulations and tests.

It behaves like the parts of PX4/ArduPilot that matter to an external-vision source: it sends
HEARTBEAT at 1 Hz from its system id (component 1), answers TIMESYNC requests, and records every
VISION_POSITION_ESTIMATE and ODOMETRY it receives with the arrival time, the sender and the fields.
It speaks plain ``common.xml`` MAVLink 2 through pymavlink's parser: it is the stand-in for another
program, so it deliberately shares no code with the node's transport.

The EKF origin as each autopilot handles it (``autopilot_type``): it answers MAV_CMD_REQUEST_MESSAGE
for GPS_GLOBAL_ORIGIN (id 49) when it has an origin. ArduPilot takes SET_GPS_GLOBAL_ORIGIN only
while it has none and ignores it silently afterwards (4.8). PX4 takes every one, and moves its
local frame as ekf2's ``setAltOrigin`` (v1.16) does: with an origin altitude already set (0 once
height is initialised on vision), a new altitude A shifts local z (NED) by A minus the old one;
with none set, the local height is kept (``local_z_shift_m`` accumulates the shift).

Attitude (``attitude``: the body's true attitude at a wall time, world ENU / body FLU): ATTITUDE is sent
at ``attitude_hz`` (ArduPilot streams it at its SRn_EXTRA1 rate, typically 10-50 Hz; 0: only once asked
with MAV_CMD_SET_MESSAGE_INTERVAL), in NED/FRD, stamped ``time_boot_ms`` at the measurement and sent
``attitude_delay_s`` later, with a per-run bias and per-sample noise on roll and pitch (an EKF's attitude
in flight) and a heading offset (a compass's): the node must use neither the noise's absence nor the yaw.
With ``rates`` (the body's true angular rates, FLU, at a wall time) ATTITUDE carries the gyros'
rollspeed, pitchspeed and yawspeed of the same instant (:class:`~atlas_onboard.sim.gyro.Gyro`: white
noise and a wandering bias); without, zeros, as an autopilot that does not fill them. ``clock_ppm``: the
autopilot's clock runs that many parts per million fast (negative: slow) against the wall clock. With ``velocity``
(true, world ENU) LOCAL_POSITION_NED carries its EKF's velocity (:mod:`~atlas_onboard.sim.ekf_velocity`).
"""

from __future__ import annotations

import contextlib
import gc
import logging
import math
import socket
import struct
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink
from scipy.spatial.transform import Rotation

from atlas_onboard.core import frames
from atlas_onboard.sim.ekf_velocity import EkfVelocity, EkfVelocityNoise
from atlas_onboard.sim.gyro import Gyro, GyroNoise
from atlas_onboard.sim.lander import Lander

_logger = logging.getLogger(__name__)

# Linux's SO_TIMESTAMPNS (also the ancillary message type, SCM_TIMESTAMPNS); Python does not name it.
_SO_TIMESTAMPNS = 35 if sys.platform.startswith("linux") else None


@contextlib.contextmanager
def recording() -> Iterator[None]:
    """No cyclic garbage collection in this process while autopilots record a run.

    The records (:class:`Received`, a few objects each) hold no cycles: reference counting frees any
    that are dropped. The cyclic collector would still scan them all at each full collection, which
    comes whenever they have grown by a quarter: at the same instants of every run, and longer as the
    run goes. On a busy machine that takes a core from the nodes under test, and every node's
    autopilot gap grows at once."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


@dataclass(frozen=True, slots=True)
class Received:
    """One external-vision message as the autopilot saw it (NED/FRD, as sent)."""

    arrival_s: float  # wall-clock arrival: the kernel's receive timestamp for UDP, time.time() for TCP
    kind: str  # "VISION_POSITION_ESTIMATE" or "ODOMETRY"
    usec: int
    xyz_m: tuple[float, float, float]
    rpy_rad: tuple[float, float, float] | None  # VISION_POSITION_ESTIMATE
    q_wxyz: tuple[float, float, float, float] | None  # ODOMETRY
    covariance: tuple[float, ...]
    reset_counter: int
    src_system: int
    src_component: int
    frame_id: int = 0
    child_frame_id: int = 0
    estimator_type: int = 0
    quality: int = 0

    @classmethod
    def of(cls, msg: mavlink.MAVLink_message, arrival_s: float) -> Received:
        """The record of a VISION_POSITION_ESTIMATE or an ODOMETRY message."""
        kind = msg.get_type()
        common = {
            "arrival_s": arrival_s, "kind": kind, "xyz_m": (msg.x, msg.y, msg.z), "reset_counter": msg.reset_counter,
            "src_system": msg.get_srcSystem(), "src_component": msg.get_srcComponent(),
        }  # fmt: skip
        if kind == "ODOMETRY":
            return cls(
                usec=msg.time_usec, rpy_rad=None, q_wxyz=tuple(msg.q), covariance=tuple(msg.pose_covariance),
                frame_id=msg.frame_id, child_frame_id=msg.child_frame_id, estimator_type=msg.estimator_type,
                quality=msg.quality, **common,
            )  # fmt: skip
        rpy = (msg.roll, msg.pitch, msg.yaw)
        return cls(usec=msg.usec, rpy_rad=rpy, q_wxyz=None, covariance=tuple(msg.covariance), **common)


@dataclass
class SimAutopilot:
    """A UDP MAVLink endpoint on 127.0.0.1 (the node connects with ``udpout:127.0.0.1:PORT``)."""

    system_id: int
    port: int = 0  # 0: choose a free port; read it back from .port after start()
    tcp: bool = False  # a TCP server (like SITL's tcp:5760) instead of a UDP endpoint
    autopilot_type: int = mavlink.MAV_AUTOPILOT_PX4
    received: list[Received] = field(default_factory=list)
    heartbeats_from: dict[tuple[int, int], int] = field(default_factory=dict)
    heartbeat_states: list[tuple[tuple[int, int], int]] = field(default_factory=list)  # (sender, system_status)
    timesync_answered: int = 0
    timesync_replies: list[tuple[int, int, int, int]] = field(default_factory=list)  # tc1, ts1, target sys, comp
    other: dict[str, int] = field(default_factory=dict)
    statustexts: list[bytes] = field(default_factory=list)
    statustext_poses: list[int] = field(default_factory=list)  # vision poses received before each STATUSTEXT
    last: dict[str, object] = field(default_factory=dict)  # the last message of each other kind
    origin: tuple[float, float, float] | None = None  # the EKF origin (lat deg, lon deg, alt m)
    px4_origin_alt_m: float = 0.0  # PX4's origin altitude (NaN: none yet); 0 once height is set on vision
    local_z_shift_m: float = 0.0  # how far the origin's altitude moved PX4's local frame (NED z)
    origin_requests: int = 0  # MAV_CMD_REQUEST_MESSAGE GPS_GLOBAL_ORIGIN received
    attitude: Callable[[float], Rotation | None] | None = None  # true R_world_body (ENU/FLU) at a wall time (s)
    attitude_hz: float = 25.0
    attitude_delay_s: float = 0.015  # measurement to send
    attitude_noise_deg: float = 0.5  # per sample, per axis (roll, pitch)
    attitude_bias_deg: float = 0.5  # per run, per axis (roll, pitch)
    attitude_yaw_offset_deg: float = 30.0  # the heading is the autopilot's own, not the world file's
    attitude_seed: int = 0
    rates: Callable[[float], np.ndarray | None] | None = None  # true body rates (FLU, rad/s) at a wall time (s)
    gyro: GyroNoise = field(default_factory=GyroNoise)
    velocity: Callable[[float], np.ndarray | None] | None = None  # true velocity (world ENU, m/s) at a wall time (s)
    ekf_velocity: EkfVelocityNoise = field(default_factory=EkfVelocityNoise)
    clock_ppm: float = 0.0  # the autopilot's clock against the wall clock (time_boot_ms)
    attitude_sent: int = 0
    attitude_interval_requests: int = 0  # MAV_CMD_SET_MESSAGE_INTERVAL for ATTITUDE received
    # Bench check (preflight): parameters answered to PARAM_REQUEST_READ (as REAL32), and LOCAL_POSITION_NED
    # streamed at local_position_hz (0: not streamed) as the last vision position received (an EKF on vision).
    params: dict[str, float] = field(default_factory=dict)
    local_position_hz: float = 0.0
    param_requests: int = 0
    timesync_hz: float = 0.0  # TIMESYNC requests sent (PX4 sends them at 10 Hz in the Onboard stream set)
    # LANDING_TARGET received (arrival, fields); with a lander, the vehicle flies on them (sim/lander.py),
    # knowing its own position from the last vision pose received.
    landing_targets: list[tuple[float, dict[str, Any]]] = field(default_factory=list)
    lander: Lander | None = None

    def __post_init__(self) -> None:
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM if self.tcp else socket.SOCK_DGRAM)
        if self.tcp:
            # Only for the TCP server (a restart may find its port in TIME_WAIT). On UDP, SO_REUSEADDR
            # lets the kernel hand the same "free" port to two endpoints bound to port 0, and one of
            # them then receives the other's traffic (seen in the swarm: one drone's poses at another's).
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("127.0.0.1", self.port))
        if self.tcp:
            self._sock.listen(1)
        elif _SO_TIMESTAMPNS is not None:
            # The kernel stamps each datagram as it is queued, so arrival times measure the node, not
            # how promptly this thread (which shares a GIL with the test or benchmark) got to read it.
            try:
                self._sock.setsockopt(socket.SOL_SOCKET, _SO_TIMESTAMPNS, 1)
            except OSError:
                pass
        self._sock.settimeout(0.005 if self.attitude is not None else 0.05)
        self.port = self._sock.getsockname()[1]
        self._client: socket.socket | None = None
        self.connections = 0
        self._mav = mavlink.MAVLink(None, srcSystem=self.system_id, srcComponent=1)
        self._mav.robust_parsing = True
        self._peer: tuple[str, int] | None = None
        self._arrival = 0.0
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name=f"sim-autopilot-{self.system_id}", daemon=True)
        self._boot_s = time.time()
        rng = np.random.default_rng(self.attitude_seed)
        self._att_rng = rng
        self._att_bias_rad = np.radians(rng.normal(0.0, self.attitude_bias_deg, 2))
        self._next_attitude_s = 0.0
        self._gyro = Gyro(self.gyro, self.attitude_seed * 7919 + 17)
        self._ekf_velocity = EkfVelocity(self.ekf_velocity, self.attitude_seed * 7919 + 29, self.attitude_delay_s,
                                         self.attitude_yaw_offset_deg)  # fmt: skip
        # (send at, t_meas, roll, pitch, yaw, body rates FRD)
        self._att_queue: list[tuple[float, float, float, float, float, tuple[float, float, float]]] = []
        self._next_local_s = 0.0
        self._next_timesync_s = 0.0

    def start(self) -> SimAutopilot:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        if self._client is not None:
            self._client.close()
        self._sock.close()

    def snapshot(self) -> list[Received]:
        with self._lock:
            return list(self.received)

    def send(self, msg: mavlink.MAVLink_message, source: tuple[int, int] | None = None) -> None:
        """Send a message to the node (e.g. a TIMESYNC request or GPS_GLOBAL_ORIGIN), from the autopilot,
        or with ``source`` (system, component) from another program behind it (a GCS through a router)."""
        self._send(msg, source)

    def _send(self, msg: mavlink.MAVLink_message, source: tuple[int, int] | None = None) -> None:
        mav = self._mav if source is None else mavlink.MAVLink(None, srcSystem=source[0], srcComponent=source[1])
        try:
            if self.tcp:
                if self._client is not None:
                    self._client.sendall(msg.pack(mav))
            elif self._peer is not None:
                self._sock.sendto(msg.pack(mav), self._peer)
        except OSError:
            pass

    def _receive(self) -> bytes | None:
        """Next chunk of bytes, or None when there is nothing yet (UDP: a datagram; TCP: a read)."""
        if not self.tcp:
            data, ancillary, _flags, self._peer = self._sock.recvmsg(65535, socket.CMSG_SPACE(16))
            self._arrival = time.time()
            for level, kind, raw in ancillary:
                if level == socket.SOL_SOCKET and kind == _SO_TIMESTAMPNS and len(raw) >= 16:
                    sec, nsec = struct.unpack("qq", raw[:16])
                    self._arrival = sec + nsec * 1e-9
            return data
        if self._client is None:
            self._client, _ = self._sock.accept()
            self._client.settimeout(0.05)
            self.connections += 1
            return None
        data = self._client.recv(65535)
        self._arrival = time.time()
        if not data:  # the node closed the connection: wait for the next one
            self._client.close()
            self._client = None
            return None
        return data

    def _run(self) -> None:
        next_heartbeat = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if now >= next_heartbeat:
                next_heartbeat = now + 1.0
                self._send(
                    self._mav.heartbeat_encode(
                        mavlink.MAV_TYPE_QUADROTOR, self.autopilot_type, 0, 0, mavlink.MAV_STATE_STANDBY
                    )
                )
            if self.attitude is not None:
                self._attitude_tick()
            if self.lander is not None:
                self.lander.tick(time.time(), self._own_position_enu())
            if self.local_position_hz > 0:
                self._local_position_tick(now)
            if self.timesync_hz > 0 and now >= self._next_timesync_s:
                self._next_timesync_s = now + 1.0 / self.timesync_hz
                self._send(self._mav.timesync_encode(0, time.monotonic_ns()))
            try:
                data = self._receive()
            except TimeoutError:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                self._client = None
                continue
            if data is None:
                continue
            try:
                msgs = self._mav.parse_buffer(data) or []
            except mavlink.MAVError:
                continue
            for msg in msgs:
                self._handle(msg)

    def _attitude_tick(self) -> None:
        """Measure the attitude at the stream's rate; send each measurement ``attitude_delay_s`` later."""
        now = time.time()
        if self.attitude_hz > 0 and now >= self._next_attitude_s:
            self._next_attitude_s = max(self._next_attitude_s + 1.0 / self.attitude_hz, now - 0.5 / self.attitude_hz)
            R = self.attitude(now) if self.attitude is not None else None
            if R is not None:
                R_ned_frd = frames.R_ENU_NED.inv() * R * frames.R_FLU_FRD
                yaw, pitch, roll = R_ned_frd.as_euler("ZYX")
                noise = self._att_rng.normal(0.0, math.radians(self.attitude_noise_deg), 2) + self._att_bias_rad
                yaw += math.radians(self.attitude_yaw_offset_deg)
                w = self._gyro.read_frd(now, self.rates(now) if self.rates is not None else None, self.attitude_hz)
                self._att_queue.append((now + self.attitude_delay_s, now, roll + noise[0], pitch + noise[1], yaw, w))
        while self._att_queue and self._att_queue[0][0] <= now:
            _, t_meas, roll, pitch, yaw, w = self._att_queue.pop(0)
            boot_ms = int((t_meas - self._boot_s) * (1.0 + self.clock_ppm * 1e-6) * 1000) & 0xFFFFFFFF
            yaw = math.atan2(math.sin(yaw), math.cos(yaw))
            self._send(self._mav.attitude_encode(boot_ms, roll, pitch, yaw, *w))
            self.attitude_sent += 1

    def _handle(self, msg: mavlink.MAVLink_message) -> None:
        kind = msg.get_type()
        arrival = self._arrival
        if kind == "HEARTBEAT":
            key = (msg.get_srcSystem(), msg.get_srcComponent())
            self.heartbeats_from[key] = self.heartbeats_from.get(key, 0) + 1
            self.heartbeat_states.append((key, msg.system_status))
        elif kind == "TIMESYNC" and msg.tc1 == 0:
            self._send(self._mav.timesync_encode(time.monotonic_ns(), msg.ts1))
            self.timesync_answered += 1
        elif kind == "TIMESYNC":
            self.last[kind] = msg  # the node's answer to our request
            # Its target fields are extensions this pymavlink's common.xml lacks: read from the
            # payload (after tc1 and ts1; MAVLink 2 trims trailing zero bytes).
            payload = bytes(msg.get_msgbuf()[10 : 10 + msg.get_msgbuf()[1]]).ljust(18, b"\0")
            self.timesync_replies.append((msg.tc1, msg.ts1, payload[16], payload[17]))
        elif kind == "LANDING_TARGET":
            fields = msg.to_dict()
            with self._lock:
                self.landing_targets.append((arrival, fields))
            if self.lander is not None:
                self.lander.on_target(fields, arrival, self._own_position_enu())
        elif kind in ("VISION_POSITION_ESTIMATE", "ODOMETRY"):
            rec = Received.of(msg, arrival)
            with self._lock:
                self.received.append(rec)
        else:
            self.other[kind] = self.other.get(kind, 0) + 1
            self.last[kind] = msg
            if kind == "SET_GPS_GLOBAL_ORIGIN" and msg.target_system == self.system_id:
                self._set_origin(msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
            elif kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL and msg.param1 == 30:
                self.attitude_interval_requests += 1
                if msg.param2 > 0:
                    self.attitude_hz = 1e6 / msg.param2
            elif kind == "PARAM_REQUEST_READ":
                self._answer_param(msg)
            elif kind == "COMMAND_LONG" and msg.command == mavlink.MAV_CMD_REQUEST_MESSAGE and msg.param1 == 49:
                self.origin_requests += 1
                self._send_origin()
            if kind == "STATUSTEXT":
                text = msg.text
                self.statustexts.append(text.encode() if isinstance(text, str) else bytes(text))
                with self._lock:
                    self.statustext_poses.append(len(self.received))

    def _own_position_enu(self) -> np.ndarray:
        """The vehicle's own position as its EKF has it from vision: the last pose received (NED -> ENU)."""
        with self._lock:
            last = self.received[-1] if self.received else None
        return np.zeros(3) if last is None else frames.R_ENU_NED.apply(np.asarray(last.xyz_m, dtype=float))

    def _answer_param(self, msg: mavlink.MAVLink_message) -> None:
        name = msg.param_id if isinstance(msg.param_id, str) else msg.param_id.decode(errors="replace")
        name = name.rstrip("\0")
        self.param_requests += 1
        if name in self.params:  # an unknown name gets no answer, as on PX4
            names = sorted(self.params)
            value = self.params[name]
            self._send(self._mav.param_value_encode(name.encode(), value, mavlink.MAV_PARAM_TYPE_REAL32,
                                                    len(names), names.index(name)))  # fmt: skip

    def _local_position_tick(self, now: float) -> None:
        if now < self._next_local_s:
            return
        self._next_local_s = now + 1.0 / self.local_position_hz
        with self._lock:
            last = self.received[-1] if self.received else None
        vision = None if last is None else (last.arrival_s, last.xyz_m)
        sample = self._ekf_velocity.local_position(time.time(), vision, self.velocity)
        if sample is not None:
            boot_ms = int((sample.t_s - self._boot_s) * (1.0 + self.clock_ppm * 1e-6) * 1000) & 0xFFFFFFFF
            self._send(self._mav.local_position_ned_encode(boot_ms, *sample.xyz_m, *sample.v_ned_m_s))

    def _set_origin(self, lat_deg: float, lon_deg: float, alt_m: float) -> None:
        if self.autopilot_type == mavlink.MAV_AUTOPILOT_PX4:
            if math.isfinite(self.px4_origin_alt_m):  # setAltOrigin: the origin moves, the state does not
                self.local_z_shift_m += alt_m - self.px4_origin_alt_m
            self.px4_origin_alt_m = alt_m
            self.origin = (lat_deg, lon_deg, alt_m)
            self._send_origin()  # PX4 answers with GPS_GLOBAL_ORIGIN
        elif self.origin is None:  # ArduPilot: only while it has none, silently ignored afterwards
            self.origin = (lat_deg, lon_deg, alt_m)
            self._send_origin()

    def _send_origin(self) -> None:
        if self.origin is not None:
            lat, lon, alt = self.origin
            self._send(self._mav.gps_global_origin_encode(round(lat * 1e7), round(lon * 1e7), round(alt * 1e3), 0))
