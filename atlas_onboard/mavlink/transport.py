"""The node's MAVLink transport: an autopilot link and peer links, with de-duplication, per-peer rate
limits, clock-skew warnings, heartbeats, TIMESYNC, the EKF origin and every message the node sends."""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable, Sequence
from typing import Any

from atlas_onboard.config import NodeConfig, WorldConfig
from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.mavlink import codec
from atlas_onboard.mavlink.link import Link
from atlas_onboard.publisher import AutopilotPose

_logger = logging.getLogger(__name__)

NS = 1_000_000_000
DEDUPE_WINDOW = 4096
SKEW_WARN_S = 0.1
SKEW_WARN_EVERY_S = 10.0
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_STATE_ACTIVE = 4
PEER_LOST_NS = 3 * NS


class TokenBucket:
    """At most ``rate`` events per second on average, bursts up to one second's worth."""

    def __init__(self, rate: float, now_ns: int) -> None:
        self.rate = rate
        self.tokens = rate
        self.t_ns = now_ns

    def take(self, now_ns: int) -> bool:
        self.tokens = min(self.rate, self.tokens + (now_ns - self.t_ns) * self.rate / NS)
        self.t_ns = now_ns
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


class MavlinkTransport:
    """Implements :class:`atlas_onboard.node.Transport` over pymavlink links."""

    def __init__(self, world: WorldConfig, config: NodeConfig, wall_clock: Callable[[], float] = time.time) -> None:
        self.world = world
        self.config = config
        self.fingerprint = world.fingerprint()
        self.wall = wall_clock
        self.counters_: Counter[str] = Counter()
        ap = config.autopilot
        compid = ap.component_id if ap is not None else 197
        self.autopilot = (
            Link(ap.link, "autopilot", config.system_id, compid, config.state_dir, link_id=0)
            if ap is not None
            else None
        )
        self.peers = [
            Link(p, f"peer{i}", config.system_id, compid, config.state_dir, link_id=i + 1)
            for i, p in enumerate(config.peers)
        ]
        self.entity_index = {name: i for i, name in enumerate(world.entity_names)}
        self._deliver: Callable[[MarkerData, int], None] | None = None
        self._seen: OrderedDict[tuple[int, ...], None] = OrderedDict()
        self._buckets: dict[tuple[int, int], TokenBucket] = {}
        self._skew_warned: dict[int, float] = {}
        self._lock = threading.Lock()  # receive threads of several links share the dedupe window
        self._next_heartbeat_ns = 0
        self._next_origin_ns = 0
        self.origin_known = False
        self.autopilot_system: int | None = None
        self.peers_seen: dict[int, int] = {}  # system id -> last arrival (ns)
        self._peers_alive: set[int] = set()

    # --- Transport ------------------------------------------------------------------------------------

    def start(self, deliver: Callable[[MarkerData, int], None]) -> None:
        self._deliver = deliver
        if self.autopilot is not None:
            self.autopilot.start(self._on_autopilot)
        for i, link in enumerate(self.peers):
            link.start(lambda lk, msg, t, i=i: self._on_peer(i, lk, msg, t))

    def send_observation(self, md: MarkerData) -> None:
        for link in self.peers:
            if link.config.tunnel:
                payload = codec.tunnel_payload(md, self.fingerprint)
                msg = link.dialect.MAVLink_tunnel_message(
                    target_system=0, target_component=0, payload_type=codec.TUNNEL_PAYLOAD_OBSERVATION,
                    payload_length=len(payload), payload=list(payload) + [0] * (128 - len(payload)),
                )  # fmt: skip
            else:
                msg = codec.encode_observation(link.dialect, md, self.fingerprint)
            link.send(msg)

    def send_fused(self, poses: Sequence[EntityPose], world: WorldConfig) -> None:
        for pose in poses:
            if pose.name == "world":
                continue
            idx = self.entity_index.get(pose.name)
            frame = self.entity_index.get(pose.frame, 0)
            if idx is None:
                continue
            for link in self.peers:
                link.send(codec.encode_fused(link.dialect, pose, idx, frame, self.fingerprint))

    def send_autopilot(self, pose: AutopilotPose) -> None:
        if self.autopilot is None or self.config.autopilot is None:
            return
        d = self.autopilot.dialect
        if self.config.autopilot.output.value == "odometry":
            msg = codec.odometry(d, pose.pose, pose.reset_counter)
        else:
            msg = codec.vision_position_estimate(d, pose.pose, pose.reset_counter)
        self.autopilot.send(msg)

    def send_status(self, text: str, severity: int) -> None:
        for link in self._links():
            link.send(
                link.dialect.MAVLink_statustext_message(severity=severity, text=text[:50].encode(), id=0, chunk_seq=0)
            )

    def tick(self, now_ns: int) -> None:
        self._peer_changes(now_ns)
        if now_ns >= self._next_heartbeat_ns:
            self._next_heartbeat_ns = now_ns + int(NS / self.config.heartbeat_hz)
            for link in self._links():
                link.send(
                    link.dialect.MAVLink_heartbeat_message(
                        type=MAV_TYPE_ONBOARD_CONTROLLER, autopilot=MAV_AUTOPILOT_INVALID, base_mode=0, custom_mode=0,
                        system_status=MAV_STATE_ACTIVE, mavlink_version=3,
                    )
                )  # fmt: skip
        ap = self.config.autopilot
        if ap is not None and ap.origin is not None and not self.origin_known and now_ns >= self._next_origin_ns:
            self._next_origin_ns = now_ns + NS
            assert self.autopilot is not None
            self.autopilot.send(
                self.autopilot.dialect.MAVLink_set_gps_global_origin_message(
                    target_system=self.autopilot_system or self.config.system_id,
                    latitude=round(ap.origin.lat_deg * 1e7), longitude=round(ap.origin.lon_deg * 1e7),
                    altitude=round(ap.origin.alt_m * 1000), time_usec=int(self.wall() * 1e6),
                )
            )  # fmt: skip

    def _peer_changes(self, now_ns: int) -> None:
        """STATUSTEXT and a log line when a peer appears or falls silent for PEER_LOST_S."""
        for sysid, last in list(self.peers_seen.items()):
            alive = now_ns - last <= PEER_LOST_NS
            if alive and sysid not in self._peers_alive:
                self._peers_alive.add(sysid)
                _logger.info("peer system %d seen", sysid)
                self.send_status(f"atlas: peer {sysid} seen", 6)
            elif not alive and sysid in self._peers_alive:
                self._peers_alive.discard(sysid)
                _logger.warning("peer system %d lost", sysid)
                self.send_status(f"atlas: peer {sysid} lost", 4)

    def counters(self) -> dict[str, int]:
        out = dict(self.counters_)
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
            if self.autopilot_system is None:
                _logger.info("autopilot found: system %d, component %d", msg.get_srcSystem(), msg.get_srcComponent())
                if msg.get_srcSystem() != self.config.system_id:
                    _logger.warning(
                        "autopilot's system id %d differs from system_id %d in the node settings",
                        msg.get_srcSystem(), self.config.system_id,
                    )  # fmt: skip
            self.autopilot_system = msg.get_srcSystem()
        elif kind == "TIMESYNC" and msg.tc1 == 0:
            # Answer the autopilot's time-sync request (PX4 trusts our usec only once this converges).
            link.send(link.dialect.MAVLink_timesync_message(tc1=time.monotonic_ns(), ts1=msg.ts1))
        elif kind == "GPS_GLOBAL_ORIGIN":
            if not self.origin_known:
                _logger.info("autopilot reports its EKF origin; no more SET_GPS_GLOBAL_ORIGIN")
            self.origin_known = True

    def _on_peer(self, index: int, link: Link, msg: Any, arrival_ns: int) -> None:
        kind = msg.get_type()
        origin = msg.get_srcSystem()
        if kind not in ("ATLAS_OBSERVATION", "TUNNEL"):
            if kind in ("HEARTBEAT", "ATLAS_FUSED_POSE"):
                self.peers_seen[origin] = arrival_ns
            return
        if origin == self.config.system_id:
            self.counters_["rejected_own_echo"] += 1
            return
        try:
            if kind == "TUNNEL":
                md = codec.decode_tunnel(msg.payload_type, msg.payload_length, msg.payload, origin, self.fingerprint)
            else:
                md = codec.decode_observation(msg, origin, self.fingerprint)
        except codec.RejectionError as exc:
            self.counters_[f"rejected_{exc.reason}"] += 1
            if exc.reason == "wrong_fingerprint" and self.counters_["rejected_wrong_fingerprint"] == 1:
                _logger.error("peer system %d uses another world file (fingerprint differs): refused", origin)
            return
        key = (origin, md.seq, md.sensor_id, md.marker_id, md.capture_time_us)
        with self._lock:
            if key in self._seen:
                self.counters_["rejected_duplicate"] += 1
                return
            self._seen[key] = None
            if len(self._seen) > DEDUPE_WINDOW:
                self._seen.popitem(last=False)
            bucket = self._buckets.get((index, origin))
            if bucket is None:
                if len(self._buckets) > 1024:  # bound the table against spoofed system ids
                    self._buckets.clear()
                bucket = self._buckets[(index, origin)] = TokenBucket(link.config.rate_limit_hz, arrival_ns)
            if not bucket.take(arrival_ns):
                self.counters_["rejected_rate_limited"] += 1
                return
        self.peers_seen[origin] = arrival_ns
        self._check_skew(origin, md)
        if self._deliver is not None:
            self._deliver(md, arrival_ns)

    def _check_skew(self, origin: int, md: MarkerData) -> None:
        skew = self.wall() - md.capture_time_us / 1e6
        if abs(skew) > SKEW_WARN_S:
            self.counters_["clock_skew_warnings"] += 1
            now = time.monotonic()
            if now - self._skew_warned.get(origin, -1e9) > SKEW_WARN_EVERY_S:
                self._skew_warned[origin] = now
                _logger.warning(
                    "peer system %d: capture stamps and arrival disagree by %.0f ms; sync the clocks (chrony)",
                    origin, skew * 1e3,
                )  # fmt: skip
