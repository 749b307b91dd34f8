"""The running node: one owner of the graph, fed by bounded queues, publishing to the autopilot and peers.

Threads: each camera and each MAVLink link has its own thread that only decodes and enqueues; the
main loop (this module) is the only code that touches the listener, the graph and the publisher, so
the core needs no locks. The inbox is bounded and drops its oldest entry when full (counted): a
flooding peer or a stalled loop costs old observations, never memory or freshness.

Signals only set flags (and wake the loop); SIGTERM/SIGINT end the loop cleanly (exit status 0),
SIGHUP re-reads the world file and switches to it only if it validates and describes the same
entities. systemd's notify protocol (READY, WATCHDOG, STOPPING) is spoken when NOTIFY_SOCKET is set.
"""

from __future__ import annotations

import logging
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from atlas_onboard.config import (
    WORLD,
    AutopilotConfig,
    ConfigError,
    NodeConfig,
    RefineConfig,
    WorldConfig,
    defaults,
    load_node,
)
from atlas_onboard.core.graph import GraphResult
from atlas_onboard.core.markerdata import MarkerData, Rejection
from atlas_onboard.errors import AtlasError
from atlas_onboard.listener import Listener, make_graph
from atlas_onboard.node_output import (  # noqa: F401 (were defined here)
    LATE_REPORT_NS,
    LATE_S,
    LATE_STREAK,
    NS,
    PREDICT_NS,
    TELEMETRY_NS,
    NodeOutput,
    Stats,
    _make_ekf,
    fused_poses,
)
from atlas_onboard.node_ports import Camera, Transport  # were defined here (imported from here elsewhere)
from atlas_onboard.publisher import PoseState, Publisher
from atlas_onboard.schedule import Changes, FrameCount, Inbound, Inbox, Item, ParkingBuffer, Relevance, relevance
from atlas_onboard.state import ResetCounterStore

if TYPE_CHECKING:
    from atlas_onboard.node_refine import LiveRefinement

_logger = logging.getLogger(__name__)

LOOP_TICK_S = 0.05  # the loop runs at least this often (links' periodic messages, stop and reload flags)
FRAME_WAIT_S = 0.005  # wait at most this long for the rest of an image's observations
COALESCE_NS = 50_000_000  # observations that cannot move the own pose wait at most this long


class Node(NodeOutput):
    """The service of one entity. Construct, then :meth:`run` until :meth:`stop` or a signal."""

    def __init__(
        self,
        world: WorldConfig,
        config: NodeConfig,
        transport: Transport,
        cameras: Sequence[Camera] = (),
        *,
        monotonic_ns: Callable[[], int] = time.monotonic_ns,
        wall_ns: Callable[[], int] = time.time_ns,
        notifier: object | None = None,
        config_path: Path | None = None,
    ) -> None:
        self.world = world
        self._entity_of = _entity_lookup(world)
        self._supersedes = _supersedes(world)
        self.config = config
        self.transport = transport
        self.cameras = list(cameras)
        self.clock = monotonic_ns
        self.wall = wall_ns  # capture times are on the swarm's wall clock: the EKF predicts to it
        self.notifier = notifier
        self.config_path = config_path
        self.graph = make_graph(world, config.entity)
        self.listener = Listener(world, self.graph)
        self._attach_attitude()
        self.refinement: LiveRefinement | None = None  # live map refinement (issue 21), opt-in
        if config.refine is not None:
            self.enable_refinement(config.refine)
        self.ekf = _make_ekf(world)
        ap = config.autopilot
        ap_default = defaults(AutopilotConfig)
        self.publisher = Publisher(
            config.entity,
            rate_hz=ap.rate_hz if ap else ap_default["rate_hz"],
            fused_rate_hz=config.fused_rate_hz,
            reset_jump_m=ap.reset_jump_m if ap else ap_default["reset_jump_m"],
            reset_gap_s=world.fusion.edge_timeout_s,  # lost means no observation for this long
        )
        self._reset_store = ResetCounterStore(config.state_dir, config.entity)
        self.publisher.reset_counter = self._reset_store.initial(self.wall())  # a restart is a reset
        self.inbox = Inbox(config.queue_size)
        self.stats = Stats()
        self.last_result: GraphResult | None = None
        self._seq = 0
        self._stop = threading.Event()
        self._may_read = threading.Event()  # cleared while the own pose is evaluated and published
        self._may_read.set()
        self._reload = threading.Event()
        self.changes = Changes(COALESCE_NS)  # when the graph is to be evaluated
        self._last_publish_ns = 0
        # Peer observations that cannot move the own pose are parked and accepted together, as often
        # as the fused poses of others go out (at least every COALESCE_NS, at most every half edge
        # timeout so that no edge expires while its refresh waits): others' poses are needed no
        # faster, and one vectorised batch costs far less than dozens of small ones.
        self.parking = ParkingBuffer(config.queue_size * 4, _supersedes(world))
        timeout_ns = round(world.fusion.edge_timeout_s * NS)
        self.park_ns = int(min(max(NS / config.fused_rate_hz, COALESCE_NS), timeout_ns // 2))
        self._near: frozenset[str] | None = None  # entities whose observations are evaluated at once
        self._next_status_ns = 0
        self._next_telemetry_ns = 0
        self._telemetry_since = (0, 0)  # (monotonic ns, local observations) at the last telemetry
        self._latency_sum_ms, self._latency_n = 0.0, 0

        self._next_late_report_ns = 0
        self._min_age_us: int | None = None  # the smallest age of an own observation seen (see LATE_S)
        self._late_streak = 0  # own images in a row with a late observation
        self._next_watchdog_ns = 0
        self.watchdog_interval_ns = NS  # the service layer shortens it to half of WatchdogSec if needed

    # --- producers (any thread) ---------------------------------------------------------------------

    def deliver_local(self, frame: Sequence[MarkerData]) -> None:
        """One image's detections from one of this node's cameras, queued together: each stamped with
        our system id, a sequence number and how many of the image's observations follow it."""
        now = self.clock()
        items = []
        for i, md in enumerate(frame):
            self._seq = (self._seq + 1) & 0xFFFF
            stamped = replace(md, origin=self.config.system_id, seq=self._seq, frame_remaining=len(frame) - 1 - i)
            items.append((stamped, now, True))
        self.inbox.put_many(items)

    def deliver_peers(self, items: Sequence[Inbound]) -> None:
        """Observations from a peer (those of one datagram), as the transport delivers them (checked
        before decoding), with their arrival times. Those that can move the own pose (:func:`relevance`)
        are taken (decoded and checked) here, in the link's thread, and queued together; the others
        are parked. Where only the newest of an edge counts they are parked undecoded: most are
        superseded before the park period ends, and are never decoded.

        The last observation of an image that can move the own pose also pauses the peer links (see
        :meth:`_process`): the link's thread stops before its next datagram and leaves the processor
        to the loop, which would otherwise wait its turn behind the decoding of the rest of a burst.
        Parked views do not wake the loop: it takes them when their park period ends (at most
        ``LOOP_TICK_S`` late), so that a swarm's traffic does not switch threads hundreds of times a second.
        """
        now: list[Item] = []
        parked: list[Inbound] = []
        pause = False
        for item in items:
            if self._relevance(item.sensor_id, item.marker_id) is Relevance.PARK:
                if self.parking.newest_wins or item.take() is not None:  # every one counts: decoded here
                    parked.append(item)
                continue
            md = item.take()
            if md is not None:
                now.append((md, item.arrival_ns, False))
                pause |= md.frame_remaining == 0 and self._near is not None
        if parked:
            self.parking.put(parked)
        if pause:
            self._may_read.clear()  # before the put: the loop sets it again once it has published
        if now:
            self.inbox.put_many(now)

    def deliver_peer(self, md: MarkerData, arrival_ns: int) -> None:
        """One observation from a peer, already decoded and checked (:meth:`deliver_peers`)."""
        self.deliver_peers((Inbound.of(md, arrival_ns),))

    def enable_refinement(self, refine: RefineConfig) -> None:
        """Refine the world markers' poses from the observations this node accepts (docs/mapping.md)."""
        from atlas_onboard.node_refine import LiveRefinement  # here: its scipy.stats costs every start-up

        self.refinement = LiveRefinement(self.world, refine)

    def stop(self) -> None:
        """Ask the loop to end (safe from a signal handler: it only sets a flag; the loop polls it)."""
        self._stop.set()

    def request_reload(self) -> None:
        """Ask the loop to re-read the world file (safe from a signal handler)."""
        self._reload.set()

    # --- the loop (one thread) ------------------------------------------------------------------------

    def run(self) -> int:
        """Run until stopped; returns the exit status (0)."""
        self.transport.start(self.deliver_peers, self._may_read)
        self.transport.set_pose_state(PoseState.NONE)
        self._telemetry_since = (self.clock(), 0)
        for cam in self.cameras:
            cam.start(self.deliver_local)
        self._notify("READY=1", f"STATUS=running as {self.config.entity}")
        _logger.info("node %s (system %d) running", self.config.entity, self.config.system_id)
        try:
            while not self._stop.is_set():
                item = self.inbox.get(timeout_s=self._wait_s(self.clock()))
                now = self.clock()
                if item is not None:
                    self._process(self._collect(item))
                    now = self.clock()
                self._step(now)
                if self._reload.is_set():
                    self._reload.clear()
                    self._do_reload()
        finally:
            self._notify("STOPPING=1")
            if self.publisher.has_pose:  # the autopilot and the GCS hear it from us, not from a timeout
                _logger.warning("%s: pose lost (node stopping)", self.config.entity)
                self.transport.send_status(f"atlas {self.config.entity}: pose lost (stopping)", 4)
            for cam in self.cameras:
                cam.stop()
            self.transport.close()
            self._write_refined_map()
            self._log_status(final=True)
        return 0

    def _wait_s(self, now: int) -> float:
        """How long the loop may wait for input: until the first thing due (parked observations,
        coalesced evaluation, an edge's expiry, a held pose, the EKF's prediction, fused poses, the
        watchdog, the status line), at most ``LOOP_TICK_S``. A node fed at 30 Hz then wakes for its
        frames and what is due, not a hundred times a second to find nothing to do."""
        due = [
            now + int(LOOP_TICK_S * NS),
            self._next_watchdog_ns,
            self._next_status_ns,
            self.publisher.next_fused_ns(),
        ]
        since = self.parking.since_ns()
        if since is not None:
            due.append(since + self.park_ns)
        for t in (self.changes.due_ns(now), self.graph.next_expiry_ns(), self.publisher.next_autopilot_ns()):
            if t is not None:
                due.append(t)
        if self.ekf is not None and self.last_result is not None:
            due.append(self._last_publish_ns + PREDICT_NS)
        return max(min(due) - now, 0) / NS

    def _collect(self, first: tuple[MarkerData, int, bool]) -> list[tuple[MarkerData, int, bool]]:
        """``first`` and everything queued, and then what arrives until every image in the batch that
        can move the own pose is whole (its last observation, ``frame_remaining`` 0, is in), for at
        most ``FRAME_WAIT_S``: an image's observations are evaluated together, never part of them with
        the previous image. (Images that cannot move it are parked or sent on, not waited for.)"""
        batch = [first, *self.inbox.drain()]
        frames = FrameCount(self._concerns_own_pose, self.parking.parked_of)
        frames.add(batch)
        deadline = time.monotonic() + FRAME_WAIT_S
        while frames.incomplete and not self._stop.is_set():
            left = deadline - time.monotonic()
            nxt = self.inbox.get(left) if left > 0 else None
            if nxt is None:
                break
            more = [nxt, *self.inbox.drain()]
            frames.add(more)
            batch += more
        return batch

    def _process(self, batch: list[tuple[MarkerData, int, bool]]) -> None:
        """Accept a batch. The observations that can move the own pose go first, and the own pose is
        evaluated and published before the others are even accepted: they can wait (see
        :meth:`_concerns_own_pose`), the autopilot should not. Meanwhile the peer links hold their
        reading (their datagrams wait in the sockets), so that this thread has the interpreter."""
        concerns = [self._concerns_own_pose(md) for md, _, _ in batch]
        first = [x for x, c in zip(batch, concerns, strict=True) if c]
        rest = [x for x, c in zip(batch, concerns, strict=True) if not c]
        local: list[MarkerData] = []
        if first:
            self._may_read.clear()
            try:
                local = self._handle(first)
                self._evaluate_and_publish(self.clock(), own_first=True)
            finally:
                self._may_read.set()
        # Our own camera's views of others go out at once (they may be urgent for them); a peer's
        # views that cannot move our pose wait, to be accepted together.
        local += self._handle([x for x in rest if x[2]])
        self.parking.put([Inbound.of(md, arrival_ns) for md, arrival_ns, is_local in rest if not is_local])
        # Our accepted detections go to peers, each image's last one marked as such.
        left = Counter((md.sensor_id, md.capture_time_us) for md in local)
        marked = []
        for md in local:
            key = (md.sensor_id, md.capture_time_us)
            left[key] -= 1
            marked.append(replace(md, frame_remaining=left[key]))
        if marked:
            self.transport.send_observations(marked)

    def _flush_parked(self) -> None:
        """Accept the parked observations (decoding those parked undecoded), except those superseded:
        one whose edge has meanwhile been refreshed by a newer arrival (taken at once because the own
        pose's needs changed) or already holds a later image of the same sensor (a datagram overtaken
        on the way). (Where only the newest of an edge counts, the parking buffer kept only that one.)"""
        fresh = []
        for item in self.parking.take():
            md = item.take()
            if md is None:
                continue
            if self.graph.is_superseded(item.edge, item.arrival_ns, md.capture_time_us):
                self.stats.superseded += 1
            else:
                fresh.append((md, item.arrival_ns, False))
        self._handle(fresh)

    def _handle(self, batch: list[tuple[MarkerData, int, bool]]) -> list[MarkerData]:
        """Accept observations; returns the local ones that were accepted (for peers)."""
        if not batch:
            return []
        local: list[MarkerData] = []
        reasons = self.listener.accept_many([(md, arrival) for md, arrival, _ in batch])
        if self.refinement is not None:
            self.refinement.add([md for (md, _, _), r in zip(batch, reasons, strict=True) if r is None], self.clock())
        wall_us = self.wall() // 1000
        late, oldest_us = 0, 0
        for (md, _, is_local), reason in zip(batch, reasons, strict=True):
            if is_local:
                self.stats.local_observations += 1
                if reason is None:
                    local.append(md)
                    age_us = wall_us - md.capture_time_us
                    if self._min_age_us is None or age_us < self._min_age_us:
                        self._min_age_us = age_us
                    if age_us - self._min_age_us > LATE_S * 1e6:
                        late, oldest_us = late + 1, max(oldest_us, age_us - self._min_age_us)
            else:
                self.stats.peer_observations += 1
            if reason is None:
                changes = self.changes
                changes.pending = True
                if not changes.urgent:
                    changes.urgent = self._concerns_own_pose(md)
                if not changes.others:
                    ends = (self._entity_of[0].get(md.sensor_id), self._entity_of[1].get(md.marker_id))
                    changes.others = not all(e in (self.config.entity, WORLD) for e in ends)
                _logger.debug(
                    "obs %d/%d cap %d sigma %.4f err %.3f ambiguity %.3f p %s", md.sensor_id, md.marker_id,
                    md.capture_time_us, md.sigma_m, md.reprojection_error_px, md.ambiguity_ratio, md.p_sensor_marker_m,
                )  # fmt: skip
            elif reason is not Rejection.UNKNOWN_MARKER:
                _logger.debug(
                    "rejected observation %s from %d: %s", (md.sensor_id, md.marker_id), md.origin, reason.value
                )
        if late:
            self.stats.late_observations += late
            self._late_streak += 1
            if self._late_streak >= LATE_STREAK:
                self._report_late(oldest_us / 1e6)
        elif local:
            self._late_streak = 0
        return local

    def _step(self, now: int) -> None:
        """Evaluate when something changed or an edge has expired, publish what is due.

        Between new observations and expiries the graph can only differ by the age of its edges, and
        the autopilot gets a pose only for a new capture: the graph is not re-evaluated then (this is
        most of a node's time in a swarm). With the EKF, the prediction to now is published every
        ``PREDICT_NS``, and a pose held back by the rate cap goes when the cap allows.
        """
        since = self.parking.since_ns()
        if since is not None and now - since >= self.park_ns:
            self._flush_parked()
        self._evaluate_and_publish(now)
        self._duties(now)
        if self.refinement is not None:
            self.refinement.step(now, self.listener)
            for text in self.refinement.take_status():
                self.transport.send_status(text, 4)  # WARNING

    def _concerns_own_pose(self, md: MarkerData) -> bool:
        """Whether an observation can change this node's own pose right away (:func:`relevance`):
        every one while the own entity has no pose or paths are Dijkstra's. Others (a ceiling
        camera's view of another drone) are evaluated together, at most ``park_ns`` later: in a
        swarm they are most of a node's input."""
        return self._relevance(md.sensor_id, md.marker_id) is Relevance.NOW

    def _relevance(self, sensor_id: int, marker_id: int) -> Relevance:
        return relevance(self._entity_of[0].get(sensor_id), self._entity_of[1].get(marker_id), self._near)

    def _do_reload(self) -> None:
        """SIGHUP: switch to the re-read world file only if it is valid and has the same entities."""
        if self.config_path is None:
            return
        try:
            world, config = load_node(self.config_path, self.config.entity)
        except ConfigError as exc:
            _logger.error("reload refused, keeping the running configuration: %s", exc)
            self._notify("STATUS=reload refused: invalid world file")
            return
        if world.entity_names != self.world.entity_names or config != self.config:
            _logger.error("reload refused: entities or node settings changed; restart the service to apply them")
            return
        self.world = world
        self._entity_of = _entity_lookup(world)
        self._supersedes = _supersedes(world)
        self.parking.clear(newest_wins=self._supersedes)
        self.graph.clear()
        self.graph = make_graph(world, self.config.entity)
        self.listener = Listener(world, self.graph)
        self._attach_attitude()
        if self.refinement is not None:  # the re-read file's poses, refined afresh
            self.enable_refinement(self.refinement.config)
        self.ekf = _make_ekf(world)
        _logger.info("reloaded %s (fingerprint %08x)", self.config_path, world.fingerprint())

    def _write_refined_map(self) -> None:
        """At exit, the refined world file, if asked (``refine.write_map`` or ``run --write-map``)."""
        if self.refinement is None or self.refinement.config.write_map is None:
            return
        path = self.refinement.config.write_map
        try:
            self.refinement.write(path)
        except AtlasError as exc:
            _logger.error("%s", exc)
            return
        _logger.info(
            "refined world file written to %s (%d marker(s) refined)", path, len(self.refinement.markers_refined)
        )

    def _attach_attitude(self) -> None:
        """The autopilot's attitude (issue 19), if the transport keeps one, resolves single tags' flips."""
        history = getattr(self.transport, "attitude", None)
        if history is not None and self.config.autopilot is not None:
            self.listener.set_attitude(self.config.entity, history.up_at)


def _entity_lookup(world: WorldConfig) -> tuple[dict[int, str], dict[int, str]]:
    """The entity of every sensor id and of every marker id."""
    return {s.id: s.entity for s in world.sensors.values()}, {m.id: m.entity for m in world.markers.values()}


def _supersedes(world: WorldConfig) -> bool:
    """Whether each observation simply replaces its edge (the paper's setting: ``ema_alpha`` 1, no
    ``age_sigma_m_per_s``), so that of several waiting observations of an edge only the newest counts."""
    return world.fusion.ema_alpha == 1.0 and world.fusion.age_sigma_m_per_s == 0.0


def install_signal_handlers(node: Node) -> None:
    """SIGTERM/SIGINT stop the loop; SIGHUP asks for a reload. Handlers only set flags."""
    signal.signal(signal.SIGTERM, lambda *_: node.stop())
    signal.signal(signal.SIGINT, lambda *_: node.stop())
    signal.signal(signal.SIGHUP, lambda *_: node.request_reload())
