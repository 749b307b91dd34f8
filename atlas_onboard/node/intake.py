"""The node's intake, called from the camera and link threads (never from the loop's): an own image's
detections stamped and queued together; a peer datagram's observations queued when they can move the own
pose (decoded in the link's thread) and parked otherwise (:func:`atlas_onboard.node.schedule.relevance`).
The loop that takes them is :class:`atlas_onboard.node.loop.Node`."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from dataclasses import replace

from atlas_onboard.config import NodeConfig
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.peerclock import PeerClocks
from atlas_onboard.core.records import Inbound
from atlas_onboard.node.output import NodeOutput
from atlas_onboard.node.schedule import Inbox, Item, ParkingBuffer, Relevance, relevance
from atlas_onboard.node.setup import WorldBlocks


class Intake:
    """The inbox, the parking buffer and the pause of the peer links, and what goes where. It reads
    the output's ``near`` (the entities whose observations are evaluated at once)."""

    def __init__(self, config: NodeConfig, blocks: WorldBlocks, clock: Callable[[], int], output: NodeOutput) -> None:
        self.system_id = config.system_id
        self.clock = clock
        self.output = output
        self.entity_of = blocks.entity_of  # the entity of every sensor id, of every marker id
        self.inbox = Inbox(config.queue_size)
        # Peer observations that cannot move the own pose are parked and accepted together (see
        # :attr:`atlas_onboard.node.loop.Node.park_ns`).
        self.parking = ParkingBuffer(config.queue_size * 4, blocks.supersedes)
        self.may_read = threading.Event()  # cleared while the own pose is evaluated and published
        self.may_read.set()
        self._seq = 0
        # Each peer's clock, measured from its observations' stamps against their arrival: a stamp
        # further in the future than it allows is refused (``future_stamp``) before it is parked or
        # queued. Link threads share it.
        self.clocks = PeerClocks()
        self._clock_lock = threading.Lock()
        self.future_refused = 0

    def use(self, blocks: WorldBlocks) -> None:
        """A re-read world file's lookups; what is parked is dropped."""
        self.entity_of = blocks.entity_of
        self.parking.clear(newest_wins=blocks.supersedes)

    def deliver_local(self, frame: Sequence[MarkerData]) -> None:
        """One image's detections from one of this node's cameras, queued together: each stamped with
        our system id, a sequence number and how many of the image's observations follow it."""
        now = self.clock()
        items = []
        for i, md in enumerate(frame):
            self._seq = (self._seq + 1) & 0xFFFF
            stamped = replace(md, origin=self.system_id, seq=self._seq, frame_remaining=len(frame) - 1 - i)
            items.append((stamped, now, True))
        self.inbox.put_many(items)

    def deliver_peers(self, items: Sequence[Inbound]) -> None:
        """Observations from a peer (those of one datagram), as the transport delivers them (checked
        before decoding), with their arrival times. Those that can move the own pose (:func:`relevance`)
        are taken (decoded and checked) here, in the link's thread, and queued together; the others
        are parked. Where only the newest of an edge counts they are parked undecoded: most are
        superseded before the park period ends, and are never decoded.

        The last observation of an image that can move the own pose also pauses the peer links (see
        :meth:`atlas_onboard.node.loop.Node._process`): the link's thread stops before its next datagram and
        leaves the processor to the loop, which would otherwise wait its turn behind the decoding of the
        rest of a burst. Parked views do not wake the loop: it takes them when their park period ends (at
        most ``LOOP_TICK_S`` late), so that a swarm's traffic does not switch threads hundreds of times a
        second.
        """
        now: list[Item] = []
        parked: list[Inbound] = []
        pause = False
        items = self._in_time(items)
        for item in items:
            if self.relevance(item.sensor_id, item.marker_id) is Relevance.PARK:
                if self.parking.newest_wins or item.take() is not None:  # every one counts: decoded here
                    parked.append(item)
                continue
            md = item.take()
            if md is not None:
                now.append((md, item.arrival_ns, False))
                pause |= md.frame_remaining == 0 and self.output.near is not None
        if parked:
            self.parking.put(parked)
        if pause:
            self.may_read.clear()  # before the put: the loop sets it again once it has published
        if now:
            self.inbox.put_many(now)

    def _in_time(self, items: Sequence[Inbound]) -> list[Inbound]:
        """``items`` without those stamped further in the future than their origin's measured clock
        allows (:class:`PeerClocks`), counted in ``future_refused``."""
        wall_minus_mono_us = (self.output.wall() - self.clock()) / 1000.0  # arrival on the wall clock
        kept = []
        with self._clock_lock:
            for item in items:
                arrival_wall_us = int(item.arrival_ns / 1000.0 + wall_minus_mono_us)
                if self.clocks.future(item.origin, item.capture_time_us, arrival_wall_us):
                    self.future_refused += 1
                else:
                    kept.append(item)
        return kept

    def deliver_peer(self, md: MarkerData, arrival_ns: int) -> None:
        """One observation from a peer, already decoded and checked (:meth:`deliver_peers`)."""
        self.deliver_peers((Inbound.of(md, arrival_ns),))

    def relevance(self, sensor_id: int, marker_id: int) -> Relevance:
        return relevance(self.entity_of[0].get(sensor_id), self.entity_of[1].get(marker_id), self.output.near)

    def concerns_own_pose(self, md: MarkerData) -> bool:
        """Whether an observation can change this node's own pose right away (:func:`relevance`):
        every one while the own entity has no pose or paths are Dijkstra's. Others (a ceiling
        camera's view of another drone) are evaluated together, at most ``park_ns`` later: in a
        swarm they are most of a node's input."""
        return self.relevance(md.sensor_id, md.marker_id) is Relevance.NOW
