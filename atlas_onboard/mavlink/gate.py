"""The peer gate: what a received observation must pass before it is handed to the node, by origin.

:class:`OriginBinding` decides first, from fields read without decoding: who may send an observation
by a given sensor (the node of the sensor's entity, never anyone for our own entity's sensors).

Pure apart from a lock (several link threads share one gate): the times are passed in. In order:

1. ``own_echo``: our own observation coming back (a mesh or a router echoes broadcasts);
2. ``duplicate``: the same observation already admitted, from another link or a second copy, keyed by
   (origin system id, seq, sensor id, marker id, capture time) within the last ``dedupe_window``;
3. ``rate_limited``: more than the link's rate from one origin (a token bucket per (link, system id),
   so a flooding or broken peer spends only its own tokens and cannot starve the others; a spoofed
   system id on one link cannot drain the real peer's bucket on another).

Memory is bounded whatever arrives: the window is a fixed-size FIFO and there are at most 256 system
ids per link. Clock skew (capture stamp against arrival on the wall clock) is measured here and
reported, rate-limited per origin, for the caller to log.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.rejection import Rejection

NS = 1_000_000_000
DEDUPE_WINDOW = 4096
SKEW_WARN_S = 0.1
MAX_SKEW_S = 1.0
"""A capture stamp farther than this from the receiver's wall clock is refused (``bad_stamp``): years
ahead it would hold back every later pose (a pose goes to the autopilot only for a newer capture);
seconds behind, an old view would be fused as a current one."""
SKEW_WARN_EVERY_S = 10.0


class TokenBucket:
    """At most ``rate_hz`` events per second on average, bursts up to ``burst`` (default one second's worth)."""

    def __init__(self, rate_hz: float, now_ns: int, burst: float | None = None) -> None:
        self.rate_hz = rate_hz
        self.burst = max(rate_hz if burst is None else burst, 1.0)
        self.tokens = self.burst
        self.t_ns = now_ns

    def take(self, now_ns: int) -> bool:
        """Spend one token if there is one (a clock that goes back refills nothing)."""
        if now_ns > self.t_ns:
            self.tokens = min(self.burst, self.tokens + (now_ns - self.t_ns) * self.rate_hz / NS)
            self.t_ns = now_ns
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False


@dataclass(frozen=True, slots=True)
class SkewReport:
    """A peer's capture stamps disagree with our arrival times: log it (already rate-limited per origin)."""

    origin: int
    skew_s: float


class PeerGate:
    """De-duplication, per-peer rate limits and clock-skew checks for observations from peers."""

    def __init__(
        self,
        own_system_id: int,
        dedupe_window: int = DEDUPE_WINDOW,
        skew_warn_s: float = SKEW_WARN_S,
        skew_warn_every_s: float = SKEW_WARN_EVERY_S,
        max_skew_s: float = MAX_SKEW_S,
    ) -> None:
        self.own_system_id = own_system_id
        self.dedupe_window = dedupe_window
        self.skew_warn_s = skew_warn_s
        self.skew_warn_every_ns = int(skew_warn_every_s * NS)
        self.max_skew_ns = int(max_skew_s * NS)
        self._seen: OrderedDict[tuple[int, int, int, int, int], None] = OrderedDict()
        self._buckets: dict[tuple[int, int], TokenBucket] = {}
        self._skew_reported_ns: dict[int, int] = {}
        self._lock = threading.Lock()
        self.skew_warnings = 0

    def admit(self, md: MarkerData, link_index: int, rate_hz: float, arrival_ns: int) -> Rejection | None:
        """None if the observation may go on; otherwise the reason it is dropped.

        ``md.origin`` is the sender's system id; ``arrival_ns`` is on the receiver's monotonic clock.
        A duplicate spends no token; a rate-limited observation is still remembered as seen, so its
        copy from another link is a duplicate too.
        """
        if md.origin == self.own_system_id:
            return Rejection.OWN_ECHO
        key = (md.origin & 0xFF, md.seq & 0xFFFF, md.sensor_id, md.marker_id, md.capture_time_us)
        with self._lock:
            if key in self._seen:
                return Rejection.DUPLICATE
            self._seen[key] = None
            while len(self._seen) > self.dedupe_window:
                self._seen.popitem(last=False)
            bucket_key = (link_index, md.origin & 0xFF)
            bucket = self._buckets.get(bucket_key)
            if bucket is None or bucket.rate_hz != rate_hz:
                bucket = self._buckets[bucket_key] = TokenBucket(rate_hz, arrival_ns)
            if not bucket.take(arrival_ns):
                return Rejection.RATE_LIMITED
        return None

    def check_skew(self, md: MarkerData, arrival_wall_ns: int, arrival_ns: int) -> SkewReport | None:
        """A report when ``md``'s capture stamp and its arrival on our wall clock differ by more than
        ``skew_warn_s`` and this origin was not reported within ``skew_warn_every_s`` (``arrival_ns``,
        monotonic, times the reports). Every such disagreement is counted in ``skew_warnings``."""
        skew_s = (arrival_wall_ns - md.capture_time_us * 1000) / NS
        if abs(skew_s) <= self.skew_warn_s:
            return None
        origin = md.origin & 0xFF
        with self._lock:
            self.skew_warnings += 1
            last = self._skew_reported_ns.get(origin)
            if last is not None and arrival_ns - last < self.skew_warn_every_ns:
                return None
            self._skew_reported_ns[origin] = arrival_ns
        return SkewReport(md.origin, skew_s)

    def stamp_refused(self, md: MarkerData, arrival_wall_ns: int) -> bool:
        """True when ``md``'s capture stamp is more than ``max_skew_s`` from its arrival on our wall clock."""
        return abs(arrival_wall_ns - md.capture_time_us * 1000) > self.max_skew_ns

    def sizes(self) -> tuple[int, int]:
        """(remembered observations, token buckets): both bounded."""
        with self._lock:
            return len(self._seen), len(self._buckets)


class OriginBinding:
    """Which system id may send what, from the world file's ``nodes`` section (pure; read-only after
    construction, so link threads share it without a lock).

    An observation by sensor ``s`` is accepted only from the system id of the node that runs the
    entity ``s`` is mounted on (a world sensor: from the world's node); never an observation by a
    sensor of this node's own entity, whoever claims to send it; never one by a sensor of an entity
    with no node in the file (nothing to bind it to: refused, and :attr:`unbound` lists them for the
    start-up warning). A fused pose of entity ``e`` is the pose of ``e`` only from ``e``'s node.
    """

    def __init__(
        self,
        sensor_entity: Mapping[int, str],
        owners: Mapping[str, int],
        own_entity: str,
    ) -> None:
        self.own_entity = own_entity
        self.owners = dict(owners)
        self.node_ids = frozenset(self.owners.values())
        # sensor id -> the one system id it may come from, or the reason it may come from none
        self._sender: dict[int, int | Rejection] = {}
        unbound: set[str] = set()
        for sensor_id, entity in sensor_entity.items():
            owner = self.owners.get(entity)
            if entity == own_entity:
                self._sender[sensor_id] = Rejection.OWN_SENSOR
            elif owner is None:
                self._sender[sensor_id] = Rejection.UNBOUND_SENSOR
                unbound.add(entity)
            else:
                self._sender[sensor_id] = owner
        self.unbound: tuple[str, ...] = tuple(sorted(unbound))

    def observation(self, sensor_id: int, origin: int) -> Rejection | None:
        """None if an observation by ``sensor_id`` may come from system ``origin``; else why not."""
        sender = self._sender.get(sensor_id, Rejection.UNKNOWN_SENSOR)
        if isinstance(sender, Rejection):
            return sender
        return None if sender == origin else Rejection.NOT_OWNER

    def fused(self, entity: str, origin: int) -> Rejection | None:
        """None if a fused pose of ``entity`` from system ``origin`` is that entity's own node's."""
        if origin not in self.node_ids:
            return Rejection.UNKNOWN_ORIGIN
        return None if self.owners.get(entity) == origin else Rejection.NOT_OWNER

    def is_node(self, origin: int) -> bool:
        """Whether ``origin`` is the system id of a node of the world file (a peer, not a stranger)."""
        return origin in self.node_ids


class ReportLimiter:
    """At most one report per key (a reason) per ``every_s``, with the count of those suppressed
    since the last one: for STATUSTEXT and log lines that an attacker could otherwise multiply.
    Thread-safe; the time (monotonic, ns) is passed in; at most ``max_keys`` keys are remembered."""

    def __init__(self, every_s: float = 10.0, max_keys: int = 1024) -> None:
        self.every_ns = int(every_s * NS)
        self.max_keys = max_keys
        self._last_ns: dict[str, int] = {}
        self._suppressed: dict[str, int] = {}
        self._lock = threading.Lock()
        self.suppressed_total = 0

    def allow(self, key: str, now_ns: int) -> int | None:
        """The number of reports of ``key`` suppressed since the last one if this one may go out, else
        None (counted)."""
        with self._lock:
            last = self._last_ns.get(key)
            if last is not None and now_ns - last < self.every_ns:
                self._suppressed[key] = self._suppressed.get(key, 0) + 1
                self.suppressed_total += 1
                return None
            if last is None and len(self._last_ns) >= self.max_keys:
                self._last_ns.clear()  # bounded whatever keys an attacker makes us see
                self._suppressed.clear()
            self._last_ns[key] = now_ns
            return self._suppressed.pop(key, 0)
