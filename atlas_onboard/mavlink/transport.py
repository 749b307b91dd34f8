"""The node's MAVLink transport: an autopilot link and peer links, with origin binding (who may send
which observation, decided before decoding: :class:`~atlas_onboard.mavlink.gate.OriginBinding`),
de-duplication, per-peer rate limits, clock-skew warnings, heartbeats, TIMESYNC, the EKF origin and
every message the node sends; STATUSTEXT and warnings at most one per reason per 10 s."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Sequence
from functools import partial
from typing import Any

from scipy.spatial.transform import Rotation

from atlas_onboard.config import AutopilotConfig, NodeConfig, WorldConfig, defaults
from atlas_onboard.core.attitude import AttitudeHistory, BootClock
from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.rejection import Rejection
from atlas_onboard.counters import Counters
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import autopilot, codec, framing
from atlas_onboard.mavlink.gate import OriginBinding, PeerGate, ReportLimiter, TokenBucket
from atlas_onboard.mavlink.link import Link
from atlas_onboard.publisher import AutopilotPose, PoseState, Telemetry
from atlas_onboard.schedule import Inbound

_logger = logging.getLogger(__name__)

__all__ = ["MavlinkTransport", "TokenBucket"]

NS = 1_000_000_000
MAV_TYPE_ONBOARD_CONTROLLER = autopilot.MAV_TYPE_ONBOARD_CONTROLLER
MAV_AUTOPILOT_INVALID = autopilot.MAV_AUTOPILOT_INVALID
PEER_LOST_NS = 3 * NS
REPORT_EVERY_S = 10.0  # a STATUSTEXT or a warning of one reason goes out at most this often
MAV_AUTOPILOT_PX4 = autopilot.MAV_AUTOPILOT_PX4
MAV_COMP_ID_AUTOPILOT1 = 1
ORIGIN_REQUEST_NS = NS // 2  # GPS_GLOBAL_ORIGIN asked for this often until the autopilot reports one
ORIGIN_UNANSWERED = 2  # requests unanswered before SET_GPS_GLOBAL_ORIGIN (then twice as many each time)
ATTITUDE_INTERVAL_US = 20_000  # ATTITUDE asked for at 50 Hz (MAV_CMD_SET_MESSAGE_INTERVAL) when it does not come
ATTITUDE_WAIT_NS = 2 * NS  # silence after which ATTITUDE is asked for again (at most ATTITUDE_ASKS times)
ATTITUDE_ASKS = 5


class MavlinkTransport:
    """Implements :class:`atlas_onboard.node.Transport` over pymavlink links."""

    def __init__(self, world: WorldConfig, config: NodeConfig, wall_clock: Callable[[], float] = time.time) -> None:
        self.world = world
        self.config = config
        self.fingerprint = world.fingerprint()
        self.wall = wall_clock
        self.counters_ = Counters()
        ap = config.autopilot
        compid = ap.component_id if ap is not None else defaults(AutopilotConfig)["component_id"]
        self.autopilot = (
            Link(ap.link, "autopilot", config.system_id, compid, config.state_dir, link_id=0, wall_clock=wall_clock)
            if ap is not None
            else None
        )
        # A peer's observations are decoded only when the node takes them (most wait for the newest of
        # their edge, and the others are never taken); its fused poses only say that it is alive.
        lazy = ("ATLAS_OBSERVATION", "ATLAS_FUSED_POSE")
        self.peers = [
            Link(p, f"peer{i}", config.system_id, compid, config.state_dir, i + 1, wall_clock=wall_clock, deferred=lazy)
            for i, p in enumerate(config.peers)
        ]
        self.entity_index = {name: i for i, name in enumerate(world.entity_names)}
        self._deliver: Callable[[Sequence[Inbound]], None] | None = None
        self._read: list[list[Inbound]] = [[] for _ in self.peers]  # per link, this read's
        self.gate = PeerGate(config.system_id)  # shared by the receive threads of every peer link
        self.binding = OriginBinding(
            {s.id: s.entity for s in world.sensors.values()}, dict(config.owners), config.entity
        )
        self._refused_by_origin: dict[int, int] = {}  # system id -> its messages refused here
        self._reports = ReportLimiter(REPORT_EVERY_S)  # STATUSTEXT and warnings, per reason
        self._lock = threading.Lock()
        self._next_heartbeat_ns = 0
        self._next_origin_ns = 0
        self._origin_unanswered = 0  # origin requests since the last SET_GPS_GLOBAL_ORIGIN, unanswered
        self._origin_sets = 0
        self._origin_skipped = False
        self.origin_known = False
        self.pose_state = PoseState.NONE
        self._start_ns = time.monotonic_ns()
        self.autopilot_system: int | None = None  # from the autopilot's HEARTBEAT
        self.autopilot_component: int | None = None
        self.autopilot_type: int | None = None  # MAV_AUTOPILOT_* (PX4 12, ArduPilot 3)
        self.peers_seen: dict[int, int] = {}  # system id -> last arrival (ns)
        self._peers_alive: set[int] = set()
        self._fingerprint_warned: set[int] = set()
        # --- the autopilot's attitude (issue 19): gravity for a single tag's ambiguity ---
        self.attitude = AttitudeHistory()
        self._boot_clock = BootClock()
        self._attitude_asks = 0
        self._next_attitude_ask_ns = 0

    def attitude_at(self, t_us: int) -> Rotation | None:
        """The autopilot's attitude at ``t_us`` (wall clock, us) as a scipy Rotation of the body FLU in a
        level ENU frame of the autopilot's heading, or None (see :meth:`AttitudeHistory.attitude_at`)."""
        return self.attitude.attitude_at(t_us)

    # --- Transport ------------------------------------------------------------------------------------

    def start(self, deliver: Callable[[Sequence[Inbound]], None], may_read: threading.Event | None = None) -> None:
        self._deliver = deliver
        self._warn_at_start()
        if self.autopilot is not None:
            self.autopilot.start(self._on_autopilot)
        for i, link in enumerate(self.peers):
            link.start(
                lambda lk, msg, t, i=i: self._on_peer(i, lk, msg, t),
                may_read,
                read_done=lambda lk, i=i: self._hand_on(i),
            )

    def _hand_on(self, index: int) -> None:
        """The observations of one read of peer link ``index``, to the node together."""
        items = self._read[index]
        if items and self._deliver is not None:
            self._read[index] = []
            self._deliver(items)

    def send_observations(self, mds: Sequence[MarkerData]) -> None:
        """Our own observations to every peer link (as ATLAS_OBSERVATION, or TUNNEL where configured),
        packed together: an image's detections travel in one datagram where they fit."""
        encoded: dict[bool, list[Any]] = {}
        for link in self.peers:
            tunnel = bool(link.config.tunnel)
            if tunnel not in encoded:
                encoded[tunnel] = []
                for md in mds:
                    try:
                        encode = codec.encode_tunnel if tunnel else codec.encode_observation
                        encoded[tunnel].append(encode(link.dialect, md, self.fingerprint))
                    except Exception as exc:  # a value that does not fit its wire type: counted, never raised
                        self.counters_.inc("tx_observation_encode_errors")
                        _logger.debug("cannot encode observation %s: %s", (md.sensor_id, md.marker_id), exc)
            if encoded[tunnel]:
                link.send_many(encoded[tunnel])

    def send_fused(self, poses: Sequence[EntityPose], world: WorldConfig) -> None:
        """Every entity's fused pose to every peer link, together (as few datagrams as fit)."""
        if not self.peers:
            return
        d = self.peers[0].dialect  # one generated dialect module for every link
        msgs = []
        for pose in poses:
            idx = self.entity_index.get(pose.name)
            if pose.name == "world" or idx is None:
                continue
            msgs.append(codec.encode_fused(d, pose, idx, self.entity_index.get(pose.frame, 0), self.fingerprint))
        if msgs:
            for link in self.peers:
                link.send_many(msgs)

    def send_autopilot(self, pose: AutopilotPose) -> None:
        """VISION_POSITION_ESTIMATE (or ODOMETRY) of the own entity; a non-finite pose is counted, not sent."""
        if self.autopilot is None or self.config.autopilot is None:
            return
        d = self.autopilot.dialect
        speed = None
        try:
            if self.config.autopilot.output.value == "odometry":
                msg = codec.odometry(d, pose.pose, pose.reset_counter)
            else:
                msg = codec.vision_position_estimate(d, pose.pose, pose.reset_counter)
                speed = codec.vision_speed_estimate(d, pose.pose, pose.reset_counter)
        except AtlasError as exc:
            self.counters_.inc("autopilot_pose_refused")
            _logger.debug("pose not sent to the autopilot: %s", exc)
            return
        self.autopilot.send(msg)
        if speed is not None:
            self.autopilot.send(speed)  # the EKF velocity, for ArduPilot (EK3_SRC1_VELXY=6); PX4 ignores it

    def send_status(self, text: str, severity: int, reason: str | None = None) -> None:
        """STATUSTEXT on every link, at most one per ``reason`` (default: the text) per REPORT_EVERY_S;
        the next one that goes out says how many were suppressed meanwhile."""
        suppressed = self._reports.allow(f"status:{reason or text}", time.monotonic_ns())
        if suppressed is None:
            self.counters_.inc("statustext_suppressed")
            return
        if suppressed:
            text = f"{text} (+{suppressed})"
        for link in self._links():
            link.send(
                link.dialect.MAVLink_statustext_message(
                    severity=severity, text=text.encode("utf-8")[:50], id=0, chunk_seq=0
                )
            )

    def set_pose_state(self, state: PoseState) -> None:
        """The HEARTBEAT's system_status from now on (STANDBY, ACTIVE, CRITICAL)."""
        self.pose_state = state

    def send_telemetry(self, telemetry: Telemetry) -> None:
        """NAMED_VALUE_FLOAT on every peer link (the ground station's): names in TELEMETRY_NAMES."""
        time_boot_ms = (time.monotonic_ns() - self._start_ns) // 1_000_000 & 0xFFFFFFFF
        values = autopilot.telemetry_values(
            telemetry.sigma_m, telemetry.detections_hz, telemetry.latency_ms, len(self._peers_alive)
        )
        for link in self.peers:
            msgs = [
                link.dialect.MAVLink_named_value_float_message(time_boot_ms, name.encode("ascii"), value)
                for name, value in values
            ]
            link.send_many(msgs)

    def tick(self, now_ns: int) -> None:
        self._peer_changes(now_ns)
        if now_ns >= self._next_heartbeat_ns:
            self._next_heartbeat_ns = now_ns + int(NS / self.config.heartbeat_hz)
            for link in self._links():
                link.send(link.dialect.MAVLink_heartbeat_message(**autopilot.heartbeat_fields(int(self.pose_state))))
        self._origin_tick(now_ns)
        self._attitude_tick(now_ns)

    def _attitude_tick(self, now_ns: int) -> None:
        """Ask the autopilot for ATTITUDE (MAV_CMD_SET_MESSAGE_INTERVAL) when none came for
        ATTITUDE_WAIT_NS after its HEARTBEAT; at most ATTITUDE_ASKS times (a link without it works as before)."""
        if self.autopilot is None or self.autopilot_system is None or self._attitude_asks >= ATTITUDE_ASKS:
            return
        last = self.attitude.latest_us()
        if last is not None and self._wall_ns() // 1000 - last < ATTITUDE_WAIT_NS // 1000:
            return
        if self._next_attitude_ask_ns == 0:
            self._next_attitude_ask_ns = now_ns + ATTITUDE_WAIT_NS  # give the autopilot's own streams a chance
        if now_ns < self._next_attitude_ask_ns:
            return
        self._next_attitude_ask_ns = now_ns + ATTITUDE_WAIT_NS
        self._attitude_asks += 1
        fields = autopilot.set_message_interval_fields(
            self.autopilot_system, self.autopilot_component or 0, autopilot.MSG_ATTITUDE, ATTITUDE_INTERVAL_US
        )
        self.autopilot.send(self.autopilot.dialect.MAVLink_command_long_message(**fields))
        self.counters_.inc("attitude_requested")

    def _on_attitude(self, msg: Any, arrival_ns: int) -> None:
        """ATTITUDE or ATTITUDE_QUATERNION into the history, stamped on the wall clock (see BootClock)."""
        try:
            if msg.get_type() == "ATTITUDE":
                R = autopilot.attitude_level_flu(msg.roll, msg.pitch, msg.yaw)
            else:
                R = autopilot.attitude_quaternion_level_flu((msg.q1, msg.q2, msg.q3, msg.q4))
        except AtlasError:
            self.counters_.inc("attitude_rejected")
            return
        arrival_wall_us = (self._wall_ns() - (time.monotonic_ns() - arrival_ns)) // 1000
        self.attitude.add(self._boot_clock.wall_us(int(msg.time_boot_ms) * 1000, arrival_wall_us), R)

    def _origin_tick(self, now_ns: int) -> None:
        """The EKF origin: asked for (MAV_CMD_REQUEST_MESSAGE GPS_GLOBAL_ORIGIN) every
        ORIGIN_REQUEST_NS until the autopilot reports one; set (SET_GPS_GLOBAL_ORIGIN) only after
        ORIGIN_UNANSWERED requests went unanswered, each later set after twice as many. ArduPilot
        with an origin ignores SET_GPS_GLOBAL_ORIGIN without a word, so sending it blindly would only
        repeat. PX4 needs no origin to hold position, and v1.16 shifts its local height by a new
        origin's altitude once height is initialised (ekf2 ``setAltOrigin``): it gets one only with
        ``origin.send_to_px4``, and then at altitude 0, where neither branch of that rule moves the
        local frame (an origin altitude of 0 or none)."""
        ap = self.config.autopilot
        if ap is None or ap.origin is None or self.origin_known or self.autopilot is None:
            return
        if self.autopilot_type is None or now_ns < self._next_origin_ns:
            return  # the autopilot's HEARTBEAT first: what to send depends on which autopilot it is
        px4 = self.autopilot_type == MAV_AUTOPILOT_PX4
        if px4 and not ap.origin.send_to_px4:
            if not self._origin_skipped:
                self._origin_skipped = True
                _logger.info("PX4 needs no EKF origin to hold position: autopilot.origin not sent (see send_to_px4)")
            return
        self._next_origin_ns = now_ns + ORIGIN_REQUEST_NS
        target = self.autopilot_system if self.autopilot_system is not None else self.config.system_id
        d = self.autopilot.dialect
        if self._origin_unanswered >= ORIGIN_UNANSWERED << min(self._origin_sets, 4):
            alt_m = 0.0 if px4 else ap.origin.alt_m
            fields = autopilot.set_gps_global_origin_fields(
                target, ap.origin.lat_deg, ap.origin.lon_deg, alt_m, int(self.wall() * 1e6)
            )
            self.autopilot.send(d.MAVLink_set_gps_global_origin_message(**fields))
            self.counters_.inc("origin_set_sent")
            self._origin_sets += 1
            self._origin_unanswered = 0
            _logger.info("autopilot reports no EKF origin: SET_GPS_GLOBAL_ORIGIN sent (altitude %.1f m)", alt_m)
        fields = autopilot.request_message_fields(
            target, self.autopilot_component or 0, autopilot.MSG_GPS_GLOBAL_ORIGIN
        )
        self.autopilot.send(d.MAVLink_command_long_message(**fields))
        self._origin_unanswered += 1

    def _peer_changes(self, now_ns: int) -> None:
        """STATUSTEXT and a log line when a peer appears or falls silent for PEER_LOST_S."""
        for sysid, last in list(self.peers_seen.items()):
            alive = now_ns - last <= PEER_LOST_NS
            if alive and sysid not in self._peers_alive:
                self._peers_alive.add(sysid)
                # Per peer: only the world file's nodes become peers, so an attacker cannot multiply these.
                self._log(logging.INFO, f"peer_seen_{sysid}", "peer system %d seen", sysid)
                self.send_status(f"atlas: peer {sysid} seen", 6, f"peer_seen_{sysid}")
            elif not alive and sysid in self._peers_alive:
                self._peers_alive.discard(sysid)
                self._log(logging.WARNING, f"peer_lost_{sysid}", "peer system %d lost", sysid)
                self.send_status(f"atlas: peer {sysid} lost", 4, f"peer_lost_{sysid}")

    def counters(self) -> dict[str, int]:
        out = self.counters_.snapshot()
        out["clock_skew_warnings"] = self.gate.skew_warnings
        with self._lock:
            out.update({f"refused_from_{sysid}": n for sysid, n in self._refused_by_origin.items()})
        for link in self._links():
            out.update({f"{link.name}_{k}": v for k, v in link.counters.items()})
        return out

    def close(self) -> None:
        for link in self._links():
            link.close()

    # --- receiving ------------------------------------------------------------------------------------

    def _links(self) -> list[Link]:
        return ([self.autopilot] if self.autopilot is not None else []) + self.peers

    def _on_autopilot(self, link: Link, msg: Any, arrival_ns: int) -> None:
        kind = msg.get_type()
        if kind == "HEARTBEAT" and msg.autopilot != MAV_AUTOPILOT_INVALID:
            source = (msg.get_srcSystem(), msg.get_srcComponent())
            if self.autopilot_system is not None and source != (self.autopilot_system, self.autopilot_component):
                if source[1] != MAV_COMP_ID_AUTOPILOT1:
                    return  # another component of the vehicle (a gimbal, a camera): the autopilot stays
            if self.autopilot_system is None:
                _logger.info(
                    "autopilot found: system %d, component %d, autopilot type %d",
                    msg.get_srcSystem(), msg.get_srcComponent(), msg.autopilot,
                )  # fmt: skip
                if msg.get_srcSystem() != self.config.system_id:
                    _logger.warning(
                        "autopilot's system id %d differs from system_id %d in the node settings",
                        msg.get_srcSystem(), self.config.system_id,
                    )  # fmt: skip
            self.autopilot_system = msg.get_srcSystem()
            self.autopilot_component = msg.get_srcComponent()
            self.autopilot_type = msg.autopilot
        elif kind == "TIMESYNC":
            # Answer only the autopilot's own requests (PX4 trusts our usec once this converges), on
            # the wall clock of our usec stamps, addressed to it: behind a router a GCS's or MAVSDK's
            # request also arrives here, and an answer to it would reach PX4 as a bogus reply.
            requester = (msg.get_srcSystem(), msg.get_srcComponent())
            if requester != (self.autopilot_system, self.autopilot_component):
                if msg.tc1 == 0:
                    self.counters_.inc("timesync_not_from_autopilot")
                return
            target = getattr(msg, "target_system", 0)
            reply = autopilot.timesync_reply(msg.tc1, msg.ts1, self._wall_ns(), requester, link.system_id, target)
            if reply is not None:
                link.send(link.dialect.MAVLink_timesync_message(**reply))
        elif kind in ("ATTITUDE", "ATTITUDE_QUATERNION"):
            if (msg.get_srcSystem(), msg.get_srcComponent()) == (self.autopilot_system, self.autopilot_component):
                self._on_attitude(msg, arrival_ns)
        elif kind == "GPS_GLOBAL_ORIGIN":
            if not self.origin_known:
                _logger.info(
                    "autopilot reports its EKF origin (%.7f, %.7f, %.1f m): no more requests",
                    msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3,
                )  # fmt: skip
            self.origin_known = True

    def _on_peer(self, index: int, link: Link, msg: Any, arrival_ns: int) -> None:
        kind = msg.get_type()
        origin = msg.get_srcSystem()
        if kind not in ("ATLAS_OBSERVATION", "TUNNEL"):
            if kind == "HEARTBEAT" and self.binding.is_node(origin):
                self.peers_seen[origin] = arrival_ns  # a stranger's heartbeat makes no peer
            elif kind == "ATLAS_FUSED_POSE":
                self._on_fused(msg, origin, arrival_ns)
            return
        if kind == "TUNNEL":  # its sensor is known only once decoded: decoded and checked now
            md = self._admit(index, link, kind, msg, origin, arrival_ns)
            if md is not None:
                self._read[index].append(Inbound.of(md, arrival_ns))
            return
        # Who sent it, when it was taken and for which world file, read from the frame without
        # decoding it, before the node can park it (a forged one must never supersede the real one)
        # or it costs a decode; the rest is checked when the node takes it.
        refusal = self.binding.observation(msg.sensor_id, origin)
        wall_ns = self._wall_ns()
        if refusal is None and abs(wall_ns - msg.time_usec * 1000) > self.gate.max_skew_ns:
            refusal = Rejection.BAD_STAMP
        if refusal is not None:
            self._refuse(refusal, origin)
            return
        if msg.format_version != codec.FORMAT_VERSION:
            self._refuse(Rejection.BAD_VERSION, origin)
            return
        if msg.fingerprint != self.fingerprint & 0xFFFFFFFF:
            self._refuse(Rejection.WRONG_FINGERPRINT, origin)
            self._warn_fingerprint(origin)
            return
        admit = partial(self._admit, index, link, kind, msg, origin, arrival_ns, wall_ns)
        item = Inbound(origin, msg.sensor_id, msg.marker_id, msg.time_usec, msg.frame_remaining, arrival_ns, admit)
        self._read[index].append(item)

    def _on_fused(self, msg: Any, origin: int, arrival_ns: int) -> None:
        """A peer's fused pose only says that its sender is alive; it is the pose of its entity only
        from that entity's node (every node also sends the poses it fused of the others: not counted)."""
        index = msg.entity_index
        entity = self.world.entity_names[index] if index < len(self.world.entity_names) else ""
        refusal = self.binding.fused(entity, origin)
        if refusal is None:
            self.peers_seen[origin] = arrival_ns
        elif refusal is Rejection.UNKNOWN_ORIGIN:
            self._refuse(refusal, origin)

    def _refuse(self, reason: Rejection, origin: int) -> None:
        """Count a refused peer message by reason and by origin (at most 256 origins)."""
        self.counters_.inc(reason)
        with self._lock:
            self._refused_by_origin[origin & 0xFF] = self._refused_by_origin.get(origin & 0xFF, 0) + 1

    def _warn(self, reason: str, fmt: str, *args: Any) -> None:
        """A warning at most once per ``reason`` per REPORT_EVERY_S, with the count suppressed meanwhile."""
        self._log(logging.WARNING, reason, fmt, *args)

    def _log(self, level: int, reason: str, fmt: str, *args: Any) -> None:
        suppressed = self._reports.allow(f"log:{reason}", time.monotonic_ns())
        if suppressed is None:
            return
        if suppressed:
            _logger.log(level, fmt + " (%d more of these suppressed)", *args, suppressed)
        else:
            _logger.log(level, fmt, *args)

    def _warn_at_start(self) -> None:
        """Once at start: peer links anyone on the network can write to, and sensors bound to no node."""
        for link in self.peers:
            if link.config.signing is None:
                _logger.warning(
                    "peer link %s is not signed: any host on the network can move this drone's pose"
                    " (atlas-onboard keygen, then signing.key_file; docs/signing.md)", link.config.url,
                )  # fmt: skip
            elif not link.config.signing.require:
                _logger.warning(
                    "peer link %s accepts unsigned observations (signing.require: false): any host on the"
                    " network can move this drone's pose", link.config.url,
                )  # fmt: skip
        if self.peers and self.binding.unbound:
            _logger.warning(
                "no node (system id) in the world file's nodes section for %s: observations by their"
                " sensors are refused from every peer", ", ".join(self.binding.unbound),
            )  # fmt: skip

    def _admit(
        self, index: int, link: Link, kind: str, msg: Any, origin: int, arrival_ns: int, wall_ns: int | None = None
    ) -> MarkerData | None:
        """A peer's observation decoded and checked (world file, duplicates, rate, clock), or None
        (counted) if it must go no further. ``wall_ns``: its arrival on the wall clock (now if not
        given), for the clock checks."""
        try:
            if isinstance(msg, framing.Deferred):
                msg = msg.decoded()
            if kind == "TUNNEL":
                md = codec.decode_tunnel(msg.payload_type, msg.payload_length, msg.payload, origin, self.fingerprint)
            else:
                md = codec.decode_observation(msg, origin, self.fingerprint)
        except codec.RejectionError as exc:
            self._refuse(exc.reason, origin)
            if exc.reason is Rejection.WRONG_FINGERPRINT:
                self._warn_fingerprint(origin)
            return None
        except link.dialect.MAVError:  # a deferred frame that pymavlink cannot make a message of
            self._refuse(Rejection.BAD_DATA, origin)
            return None
        refusal = self.binding.observation(md.sensor_id, origin)  # TUNNEL's is known only now
        if refusal is not None:
            self._refuse(refusal, origin)
            return None
        reason = self.gate.admit(md, index, link.config.rate_limit_hz, arrival_ns)
        if reason is not None:
            self._refuse(reason, origin)
            return None
        self.peers_seen[origin] = arrival_ns
        if wall_ns is None:
            wall_ns = self._wall_ns()
        skew = self.gate.check_skew(md, wall_ns, arrival_ns)
        if skew is not None:
            self._warn(
                "clock_skew", "peer system %d: capture stamps and arrival disagree by %.0f ms; sync the clocks"
                " (chrony)", skew.origin, skew.skew_s * 1e3,
            )  # fmt: skip
        if self.gate.stamp_refused(md, wall_ns):
            self._refuse(Rejection.BAD_STAMP, origin)
            return None
        return md

    def _wall_ns(self) -> int:
        """The wall clock (UNIX epoch) in ns, to the microsecond (the resolution of a float of seconds)."""
        return round(self.wall() * 1e6) * 1000

    def _warn_fingerprint(self, origin: int) -> None:
        with self._lock:
            first = origin not in self._fingerprint_warned
            self._fingerprint_warned.add(origin & 0xFF)
        if first:
            self._warn("wrong_fingerprint", "peer system %d uses another world file (fingerprint differs): refused",
                       origin)  # fmt: skip
