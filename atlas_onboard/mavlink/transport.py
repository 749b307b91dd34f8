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
from atlas_onboard.core.attitude import AttitudeHistory
from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.records import AutopilotPose, Inbound, PoseState, Telemetry
from atlas_onboard.core.rejection import Rejection
from atlas_onboard.core.shutter import BodyRate, BodyVelocity
from atlas_onboard.counters import Counters
from atlas_onboard.mavlink import autopilot, codec, framing
from atlas_onboard.mavlink.autopilot_link import (
    AutopilotLink,
    wall_ns,
)
from atlas_onboard.mavlink.gate import OriginBinding, PeerGate, ReportLimiter, TokenBucket
from atlas_onboard.mavlink.link import Link

_logger = logging.getLogger(__name__)

__all__ = ["MavlinkTransport", "TokenBucket"]

NS = 1_000_000_000
MAV_TYPE_ONBOARD_CONTROLLER = autopilot.MAV_TYPE_ONBOARD_CONTROLLER
MAV_TYPE_GCS = 6
PEER_LOST_NS = 3 * NS
REPORT_EVERY_S = 10.0  # a STATUSTEXT or a warning of one reason goes out at most this often


class MavlinkTransport:
    """Implements :class:`atlas_onboard.node.ports.Transport` over pymavlink links."""

    def __init__(self, world: WorldConfig, config: NodeConfig, wall_clock: Callable[[], float] = time.time) -> None:
        self.world = world
        self.config = config
        self.fingerprint = world.fingerprint()
        self.wall = wall_clock
        self.counters_ = Counters()
        ap = config.autopilot
        compid = ap.component_id if ap is not None else defaults(AutopilotConfig)["component_id"]
        self.autopilot_link = AutopilotLink(config, compid, wall_clock)
        # A peer's observations are decoded only when the node takes them (most wait for the newest of
        # their edge, and the others are never taken); its fused poses only say that it is alive.
        lazy = ("ATLAS_OBSERVATION", "ATLAS_FUSED_POSE")
        self.peers = [
            Link(
                p,
                f"peer{i}",
                config.system_id,
                compid,
                config.state_dir,
                i + 1,
                wall_clock=wall_clock,
                deferred=lazy,
                origin_ok=self._is_peer,
            )
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
        self.pose_state = PoseState.NONE
        self._start_ns = time.monotonic_ns()
        self.peers_seen: dict[int, int] = {}  # system id -> last arrival (ns)
        self._peers_alive: set[int] = set()
        self._fingerprint_warned: set[int] = set()

    def _is_peer(self, msg: Any) -> bool:
        """Whether ``msg`` may prove its sender a UDP client: from a node of the world file other than
        this one, or a ground station's HEARTBEAT (it reads the STATUSTEXT and telemetry)."""
        system_id = msg.get_srcSystem()
        if msg.get_type() == "HEARTBEAT" and msg.type == MAV_TYPE_GCS:
            return system_id != self.config.system_id
        return system_id != self.config.system_id and self.binding.is_node(system_id)

    @staticmethod
    def _alive(link: Link, msg: Any) -> bool:
        """Whether ``msg`` may say its sender is alive: on a signed link, only a signed frame."""
        return link.signing is None or framing.is_signed(msg)

    @property
    def attitude(self) -> AttitudeHistory:
        """The autopilot's attitude history: gravity for a single tag's ambiguity."""
        return self.autopilot_link.attitude

    # --- Transport ------------------------------------------------------------------------------------

    def start(self, deliver: Callable[[Sequence[Inbound]], None], may_read: threading.Event | None = None) -> None:
        self._deliver = deliver
        self._warn_at_start()
        self.autopilot_link.start()
        for i, link in enumerate(self.peers):
            link.start(
                lambda lk, msg, t, i=i: self._on_peer(i, lk, msg, t),
                may_read,
                read_done=lambda lk, i=i: self._hand_on(i),
            )

    def send_autopilot(self, pose: AutopilotPose) -> None:
        """VISION_POSITION_ESTIMATE (or ODOMETRY) of the own entity (see :meth:`AutopilotLink.send_autopilot`)."""
        self.autopilot_link.send_autopilot(pose)

    def send_landing_target(self, fields: dict[str, Any]) -> None:
        """LANDING_TARGET to the autopilot (fields of :mod:`atlas_onboard.mavlink.landing`)."""
        self.autopilot_link.send_landing_target(fields)

    def attitude_at(self, t_us: int) -> Rotation | None:
        """The autopilot's attitude at ``t_us`` (see :meth:`AutopilotLink.attitude_at`)."""
        return self.autopilot_link.attitude_at(t_us)

    def rate_at(self, t_us: int) -> BodyRate | None:
        """The autopilot's body rate at ``t_us`` (see :meth:`AutopilotLink.rate_at`)."""
        return self.autopilot_link.rate_at(t_us)

    def velocity_at(self, t_us: int) -> BodyVelocity | None:
        """The autopilot's velocity at ``t_us`` (see :meth:`AutopilotLink.velocity_at`)."""
        return self.autopilot_link.velocity_at(t_us)

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
        self.autopilot_link.tick(now_ns)

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
        out.update(self.autopilot_link.counters.snapshot())
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
        ap = self.autopilot_link.link
        return ([ap] if ap is not None else []) + self.peers

    def _on_peer(self, index: int, link: Link, msg: Any, arrival_ns: int) -> None:
        kind = msg.get_type()
        origin = msg.get_srcSystem()
        if kind not in ("ATLAS_OBSERVATION", "TUNNEL"):
            if kind == "HEARTBEAT" and self.binding.is_node(origin) and self._alive(link, msg):
                self.peers_seen[origin] = arrival_ns  # a stranger's heartbeat makes no peer
            elif kind == "ATLAS_FUSED_POSE" and self._alive(link, msg):
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
        if self._alive(link, msg):
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
        return wall_ns(self.wall)

    def _warn_fingerprint(self, origin: int) -> None:
        with self._lock:
            first = origin not in self._fingerprint_warned
            self._fingerprint_warned.add(origin & 0xFF)
        if first:
            self._warn("wrong_fingerprint", "peer system %d uses another world file (fingerprint differs): refused",
                       origin)  # fmt: skip
