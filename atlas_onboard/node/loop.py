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

import gc
import logging
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path

from atlas_onboard.config import (
    WORLD,
    NodeConfig,
    RefineConfig,
    WorldConfig,
)
from atlas_onboard.core.graph import GraphResult
from atlas_onboard.core.markerdata import MarkerData, Rejection
from atlas_onboard.core.records import Inbound, PoseState
from atlas_onboard.node.intake import Intake
from atlas_onboard.node.output import NS, NodeOutput, Stats
from atlas_onboard.node.ports import Camera, Transport
from atlas_onboard.node.refine import LiveRefinement
from atlas_onboard.node.schedule import Changes, FrameCount
from atlas_onboard.node.setup import (
    WorldBlocks,
    reread_world,
    wire,
    write_refined_map,
)

_logger = logging.getLogger(__name__)

LOOP_TICK_S = 0.05  # the loop runs at least this often (links' periodic messages, stop and reload flags)
FRAME_WAIT_S = 0.005  # wait at most this long for the rest of an image's observations
COALESCE_NS = 50_000_000  # observations that cannot move the own pose wait at most this long
FLUSH_CHUNK = 32  # parked observations accepted at a time: between two chunks, the own pose's go first


class Node:
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
        self.config = config
        self.transport = transport
        self.cameras = list(cameras)
        self.clock = monotonic_ns
        self.wall = wall_ns  # capture times are on the swarm's wall clock: the EKF predicts to it
        self.notifier = notifier
        self.config_path = config_path
        blocks = wire(world, config, transport)
        self._use(blocks)
        self.refinement: LiveRefinement | None = None  # live map refinement, opt-in
        if config.refine is not None:
            self.enable_refinement(config.refine)
        self.stats = Stats()
        self.changes = Changes(COALESCE_NS)  # when the graph is to be evaluated
        self.output = NodeOutput(config, blocks, transport, self.stats, self.changes, clock=monotonic_ns, wall=wall_ns)
        # The producers' side (camera and link threads): its entry points are the node's.
        self.intake = Intake(config, blocks, monotonic_ns, self.output)
        self.inbox, self.parking, self._may_read = self.intake.inbox, self.intake.parking, self.intake.may_read
        self.deliver_local, self.deliver_peers = self.intake.deliver_local, self.intake.deliver_peers
        self.deliver_peer = self.intake.deliver_peer
        self._stop = threading.Event()
        self._reload = threading.Event()
        # Peer observations that cannot move the own pose are parked and accepted together, as often
        # as the fused poses of others go out (at least every COALESCE_NS, at most every half edge
        # timeout so that no edge expires while its refresh waits): others' poses are needed no
        # faster, and one vectorised batch costs far less than dozens of small ones.
        timeout_ns = round(world.fusion.edge_timeout_s * NS)
        self.park_ns = int(min(max(NS / config.fused_rate_hz, COALESCE_NS), timeout_ns // 2))
        self._unflushed: deque[Inbound] = deque()  # parked observations taken, not yet accepted
        self._next_status_ns = 0
        self._next_watchdog_ns = 0
        self.watchdog_interval_ns = NS  # the service layer shortens it to half of WatchdogSec if needed

    def _use(self, blocks: WorldBlocks) -> None:
        self.world, self.graph, self.listener = blocks.world, blocks.graph, blocks.listener

    @property
    def last_result(self) -> GraphResult | None:
        """The last evaluation's result (the output side's)."""
        return self.output.last_result

    def enable_refinement(self, refine: RefineConfig) -> None:
        """Refine the world markers' poses from the observations this node accepts (docs/mapping.md): its
        peers' only when every peer link requires signatures (else anyone on the network could move the map)."""
        signed = all(p.signing is not None and p.signing.require for p in self.config.peers)
        own = frozenset(s.id for s in self.world.entity(self.config.entity).sensors)
        if not signed:
            _logger.warning("refine: a peer link is not signed (require: true): only this node's cameras move the map")
        self.refinement = LiveRefinement(self.world, refine, None if signed else own)

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
        self.output.start()
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
            if self.output.publisher.has_pose:  # the autopilot and the GCS hear it from us, not from a timeout
                _logger.warning("%s: pose lost (node stopping)", self.config.entity)
                self.transport.send_status(f"atlas {self.config.entity}: pose lost (stopping)", 4)
            for cam in self.cameras:
                cam.stop()
            self.transport.close()
            write_refined_map(self.refinement)
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
            self.output.publisher.next_fused_ns(),
        ]
        since = self.parking.since_ns()
        if since is not None:
            due.append(since + self.park_ns)
        output = self.output
        for t in (self.changes.due_ns(now), self.graph.next_expiry_ns(), output.publisher.next_autopilot_ns(),
                  output.next_prediction_ns()):  # fmt: skip
            if t is not None:
                due.append(t)
        if self._unflushed:
            return 0.0
        return max(min(due) - now, 0) / NS

    def _collect(self, first: tuple[MarkerData, int, bool]) -> list[tuple[MarkerData, int, bool]]:
        """``first`` and everything queued, and then what arrives until every image in the batch that
        can move the own pose is whole (its last observation, ``frame_remaining`` 0, is in), for at
        most ``FRAME_WAIT_S``: an image's observations are evaluated together, never part of them with
        the previous image. (Images that cannot move it are parked or sent on, not waited for.)"""
        batch = [first, *self.inbox.drain()]
        frames = FrameCount(self.intake.concerns_own_pose, self.parking.parked_of)
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
        :meth:`Intake.concerns_own_pose`), the autopilot should not. Meanwhile the peer links hold their
        reading (their datagrams wait in the sockets), so that this thread has the interpreter."""
        concerns = [self.intake.concerns_own_pose(md) for md, _, _ in batch]
        first = [x for x, c in zip(batch, concerns, strict=True) if c]
        rest = [x for x, c in zip(batch, concerns, strict=True) if not c]
        local: list[MarkerData] = []
        if first:
            self._may_read.clear()
            # Nor does the cyclic collector stop it halfway: it runs, if due, once the pose is out.
            collect = gc.isenabled()
            gc.disable()
            try:
                local = self._handle(first)
                self.output.evaluate_and_publish(self.clock(), own_first=True)
            finally:
                if collect:
                    gc.enable()
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

    def _flush_parked(self) -> bool:
        """Accept the parked observations (decoding those parked undecoded), except those superseded:
        one whose edge has meanwhile been refreshed by a newer arrival (taken at once because the own
        pose's needs changed) or already holds a later image of the same sensor (a datagram overtaken
        on the way). (Where only the newest of an edge counts, the parking buffer kept only that one.)

        ``FLUSH_CHUNK`` at a time: when observations wait in the inbox after a chunk (they can move the
        own pose), it stops and returns False, so that the loop takes them first and comes back for the
        rest at once; True when every parked observation taken is accepted."""
        if not self._unflushed:
            self._unflushed.extend(self.parking.take())
        pending = self._unflushed
        while pending:
            fresh = []
            for _ in range(min(FLUSH_CHUNK, len(pending))):
                item = pending.popleft()
                md = item.take()
                if md is None:
                    continue
                if self.graph.is_superseded(item.edge, item.arrival_ns, md.capture_time_us):
                    self.stats.superseded += 1
                else:
                    fresh.append((md, item.arrival_ns, False))
            self._handle(fresh)
            if pending and len(self.inbox):
                return False
        return True

    def _handle(self, batch: list[tuple[MarkerData, int, bool]]) -> list[MarkerData]:
        """Accept observations; returns the local ones that were accepted (for peers)."""
        if not batch:
            return []
        local: list[MarkerData] = []
        reasons = self.listener.accept_many([(md, arrival) for md, arrival, _ in batch])
        if self.refinement is not None:
            self.refinement.add([md for (md, _, _), r in zip(batch, reasons, strict=True) if r is None], self.clock())
        for (md, _, is_local), reason in zip(batch, reasons, strict=True):
            if is_local:
                self.stats.local_observations += 1
                if reason is None:
                    local.append(md)
            else:
                self.stats.peer_observations += 1
            if reason is None:
                changes = self.changes
                changes.pending = True
                if not changes.urgent:
                    changes.urgent = self.intake.concerns_own_pose(md)
                if not changes.others:
                    entity_of = self.intake.entity_of
                    ends = (entity_of[0].get(md.sensor_id), entity_of[1].get(md.marker_id))
                    changes.others = not all(e in (self.config.entity, WORLD) for e in ends)
                _logger.debug(
                    "obs %d/%d cap %d sigma %.4f err %.3f ambiguity %.3f p %s", md.sensor_id, md.marker_id,
                    md.capture_time_us, md.sigma_m, md.reprojection_error_px, md.ambiguity_ratio, md.p_sensor_marker_m,
                )  # fmt: skip
            elif reason is not Rejection.UNKNOWN_MARKER:
                _logger.debug(
                    "rejected observation %s from %d: %s", (md.sensor_id, md.marker_id), md.origin, reason.value
                )
        self.output.check_lateness(local)
        return local

    def _step(self, now: int) -> None:
        """Evaluate when something changed or an edge has expired, publish what is due.

        Between new observations and expiries the graph can only differ by the age of its edges, and
        the autopilot gets a pose only for a new capture: the graph is not re-evaluated then (this is
        most of a node's time in a swarm). With the EKF, the prediction to now is published every
        ``PREDICT_NS``, and a pose held back by the rate cap goes when the cap allows.
        """
        since = self.parking.since_ns()
        if (self._unflushed or (since is not None and now - since >= self.park_ns)) and not self._flush_parked():
            return  # the inbox first: the loop is back here at once
        self.output.evaluate_and_publish(now)
        self._duties(now)
        if self.refinement is not None:
            for u in self.refinement.step(now, self.listener):  # the detectors' places are relative to the file
                for cam in self.cameras:
                    cam.map_pose_changed(u.marker_id)
            for text in self.refinement.take_status():
                self.transport.send_status(text, 4)  # WARNING

    def _duties(self, now: int) -> None:
        """The rest: fused poses to peers and telemetry (the output's), the links' periodic messages,
        the cameras' warnings, systemd, the status line."""
        self.output.duties(now)
        self.transport.tick(now)
        for cam in self.cameras:  # a camera's detector's warnings (a marker that disagrees), rate-limited there
            for text in cam.take_status():
                self.transport.send_status(text, 4)  # WARNING
        if now >= self._next_watchdog_ns:
            self._notify("WATCHDOG=1")
            self._next_watchdog_ns = now + self.watchdog_interval_ns
        if now >= self._next_status_ns:
            if self._next_status_ns:
                self._log_status()
            self._next_status_ns = now + int(self.config.status_interval_s * NS)

    def counters(self) -> dict[str, int]:
        """Every counter of the node: rejections by reason, drops, rates, links, cameras."""
        out: dict[str, int] = self.listener.rejected.snapshot()
        out.update(
            accepted=self.listener.accepted,
            inbox_dropped=self.inbox.dropped + self.parking.dropped,
            local_observations=self.stats.local_observations,
            peer_observations=self.stats.peer_observations,
            evaluations=self.stats.evaluations,
            autopilot_sent=self.stats.autopilot_sent,
            autopilot_rate_suppressed=self.output.publisher.suppressed_rate,
            fused_sent=self.stats.fused_sent,
            superseded=self.stats.superseded + self.parking.superseded,
            late_observations=self.stats.late_observations,
            reset_counter=self.output.publisher.reset_counter,
        )
        out.update(self.listener.counters.snapshot())  # ambiguity resolved / swapped / undecided, alt ignored
        out[Rejection.OUTLIER.counter] = out.get(Rejection.OUTLIER.counter, 0) + self.graph.gated_total
        out[Rejection.TOO_FAST.counter] = out.get(Rejection.TOO_FAST.counter, 0) + self.graph.too_fast_total
        out[Rejection.FUTURE_STAMP.counter] = out.get(Rejection.FUTURE_STAMP.counter, 0) + self.intake.future_refused
        if self.output.ekf is not None:
            out.update({f"ekf_{k}": v for k, v in self.output.ekf.outcomes.items()})
        for name, n in self.transport.counters().items():  # a reason both refuse for (unknown_sensor): summed
            out[name] = out.get(name, 0) + n
        for cam in self.cameras:
            out.update({f"camera_{cam.name}_{k}": v for k, v in cam.counters().items()})
        if self.refinement is not None:
            out.update(self.refinement.counters())
        return out

    def _log_status(self, final: bool = False) -> None:
        c = Counter(self.counters())
        text = " ".join(f"{k}={v}" for k, v in sorted(c.items()))
        _logger.info("%s %s", "final" if final else "status", text)

    def _notify(self, *lines: str) -> None:
        if self.notifier is not None:
            self.notifier.notify(*lines)  # type: ignore[attr-defined]

    def _do_reload(self) -> None:
        """SIGHUP: switch to the re-read world file only if it is valid and has the same entities."""
        if self.config_path is None:
            return
        world = reread_world(self.config_path, self.world, self.config, self._notify)
        if world is None:
            return
        self.graph.clear()
        self._unflushed.clear()  # observations of the old world file, like those parked
        blocks = wire(world, self.config, self.transport)
        self._use(blocks)
        self.intake.use(blocks)
        if self.refinement is not None:  # the re-read file's poses, refined afresh
            self.enable_refinement(self.refinement.config)
        self.output.attach(blocks)
        _logger.info("reloaded %s (fingerprint %08x)", self.config_path, world.fingerprint())
