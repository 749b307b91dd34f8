"""What the node evaluates when: its inbox, its one parking buffer, and the relevance of an observation.

Pure apart from the locks of the two buffers (link threads and camera threads fill them, the node's
loop empties them): no clock is read here, every time is passed in.

- :func:`relevance` decides, from an observation's edge alone (sensor id, marker id: read without
  decoding it), whether it can move the own pose now (:attr:`Relevance.NOW`: accepted, evaluated and
  published at once) or can wait for the next park period (:attr:`Relevance.PARK`).
- :class:`ParkingBuffer` holds what waits, keyed by edge. Where each observation simply replaces its
  edge (the paper's setting), only the newest of an edge is kept (the others counted once as
  superseded, never decoded); otherwise every one is kept, in arrival order, for the edge's filter.
- :class:`Inbox` holds what is taken at once (bounded, oldest dropped, counted).
- :class:`FrameCount` says which images of a batch still have observations to come.
- :class:`Changes` says when the graph is to be evaluated: what was accepted since the last
  evaluation of every entity, and when that was.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from enum import Enum

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.records import ImageKey, Inbound

WORLD = "world"
EdgeKey = tuple[int, int]  # (sensor id, marker id)
Item = tuple[MarkerData, int, bool]  # an accepted-to-be observation, its arrival (monotonic ns), whether local


class Relevance(Enum):
    """When an observation is accepted (:func:`relevance`)."""

    NOW = "now"
    """It can move the own pose: accepted, evaluated and published at once."""
    PARK = "park"
    """It cannot (a ceiling camera's view of another drone): parked, accepted with the others later."""


def near_entities(own_entity: str, levels: Mapping[str, int] | None) -> frozenset[str] | None:
    """The entities whose observations can move the own pose, from the BFS levels of the last
    evaluation: the own entity and those nearer the world (levels 1 to the own level - 1). The
    world's pose never changes: it is never among them, not even for the world's own node. None
    (every observation can) when the own entity has no level: no pose yet, or Dijkstra's paths."""
    level = levels.get(own_entity) if levels is not None else None
    if levels is None or level is None:
        return None
    return frozenset(n for n, lv in levels.items() if 1 <= lv < level) | ({own_entity} - {WORLD})


def relevance(observer: str | None, observed: str | None, near: frozenset[str] | None) -> Relevance:
    """When an observation by a sensor of ``observer`` of a marker of ``observed`` (None: an id the
    world file does not have, left to the listener to refuse and count) is accepted, given
    :func:`near_entities`."""
    if near is None or observer is None or observed is None or observer in near or observed in near:
        return Relevance.NOW
    return Relevance.PARK


class ParkingBuffer:
    """Peer observations that cannot move the own pose, waiting to be accepted together (thread-safe).

    Keyed by edge. With ``newest_wins`` only the newest of each edge (by capture time; of two with
    the same, the first) is kept: every other arrival of an edge counts once in :attr:`superseded`.
    Otherwise every observation is kept. Bounded: beyond ``capacity`` the oldest arrival goes,
    counted in :attr:`dropped`. :meth:`take` returns everything, in arrival order.

    It also tallies, per image, the observations parked since the last :meth:`take` (kept or not):
    the node's :class:`FrameCount` counts them with the image's others, so that it does not wait
    for observations of an image that were parked (at most ``capacity`` images are tallied).
    """

    def __init__(self, capacity: int, newest_wins: bool) -> None:
        if capacity < 1:
            raise ValueError(f"expected a capacity >= 1, got {capacity}")
        self.capacity = capacity
        self.newest_wins = newest_wins
        self._items: dict[int, Inbound] = {}  # by order of arrival here (dicts keep insertion order)
        self._kept: dict[EdgeKey, int] = {}  # with newest_wins: each edge's kept item
        self._n = 0
        self._since_ns: int | None = None
        self._images: dict[ImageKey, tuple[int, int]] = {}  # (observations parked, largest frame_remaining)
        self._lock = threading.Lock()
        self.superseded = 0
        self.dropped = 0

    def put(self, items: Iterable[Inbound]) -> None:
        with self._lock:
            for item in items:
                self._put(item)

    def _put(self, item: Inbound) -> None:
        image = item.image
        tally = self._images.get(image)
        if tally is not None:
            self._images[image] = (tally[0] + 1, max(tally[1], item.frame_remaining))
        elif len(self._images) < self.capacity:
            self._images[image] = (1, item.frame_remaining)
        if self.newest_wins:
            old = self._kept.get(item.edge)
            if old is not None:
                self.superseded += 1
                if item.capture_time_us <= self._items[old].capture_time_us:
                    return
                del self._items[old]
        if len(self._items) >= self.capacity:
            oldest = next(iter(self._items))
            gone = self._items.pop(oldest)
            self.dropped += 1
            if self._kept.get(gone.edge) == oldest:
                del self._kept[gone.edge]
        if not self._items and self._since_ns is None:
            self._since_ns = item.arrival_ns
        self._n += 1
        self._items[self._n] = item
        if self.newest_wins:
            self._kept[item.edge] = self._n

    def parked_of(self, image: ImageKey) -> tuple[int, int] | None:
        """How many observations of a peer's ``image`` were parked since the last :meth:`take`, and
        the largest ``frame_remaining`` among them; None if none (or not tallied)."""
        return self._images.get(image)

    def since_ns(self) -> int | None:
        """When the first observation parked since the last :meth:`take` arrived, or None if none waits."""
        return self._since_ns if self._items else None

    def take(self) -> list[Inbound]:
        """Everything parked, in order of arrival; the buffer is then empty."""
        with self._lock:
            items = sorted(self._items.values(), key=lambda it: it.arrival_ns)
            self._items, self._kept, self._since_ns, self._images = {}, {}, None, {}
        return items

    def clear(self, newest_wins: bool | None = None) -> None:
        """Drop what is parked (uncounted: a reload), switching ``newest_wins`` if given; counts go on."""
        with self._lock:
            self._items, self._kept, self._since_ns, self._images = {}, {}, None, {}
            if newest_wins is not None:
                self.newest_wins = newest_wins

    def __len__(self) -> int:
        return len(self._items)


class Inbox:
    """A bounded FIFO that drops its oldest item when full (thread-safe, counted)."""

    def __init__(self, capacity: int) -> None:
        self._items: deque[Item] = deque()
        self._capacity = capacity
        self._cond = threading.Condition()
        self.dropped = 0

    def put(self, item: Item) -> None:
        self.put_many((item,))

    def put_many(self, items: Sequence[Item], wake: bool = True) -> None:
        """Put several items at once: a consumer never sees part of them. With ``wake`` False, a
        waiting consumer is not woken for them: it takes them with the next items or at its timeout."""
        with self._cond:
            for item in items:
                if len(self._items) >= self._capacity:
                    self._items.popleft()
                    self.dropped += 1
                self._items.append(item)
            if wake or len(self._items) * 2 >= self._capacity:  # half full: take them before any is lost
                self._cond.notify()

    def drain(self) -> list[Item]:
        """Everything queued now, without waiting."""
        with self._cond:
            items = list(self._items)
            self._items.clear()
            return items

    def get(self, timeout_s: float) -> Item | None:
        with self._cond:
            if not self._items:
                self._cond.wait(timeout_s)
            return self._items.popleft() if self._items else None

    def wake(self) -> None:
        with self._cond:
            self._cond.notify()

    def __len__(self) -> int:
        return len(self._items)


class FrameCount:
    """Which images of a batch still have observations to come: fewer of an image's observations
    (same producer, sensor and capture time) are in than the largest ``frame_remaining`` among them
    promises (order-proof: datagrams may be reordered). Updated as items arrive.

    With ``watch``, only images holding an observation for which it is true are waited for (the
    node waits for those that can move its own pose; the others are parked anyway). With
    ``parked``, a peer's image's observations that were parked rather than queued (``(count, largest
    frame_remaining)`` or None, :meth:`ParkingBuffer.parked_of`) count as seen."""

    def __init__(
        self,
        watch: Callable[[MarkerData], bool] | None = None,
        parked: Callable[[ImageKey], tuple[int, int] | None] | None = None,
    ) -> None:
        self._frames: dict[tuple[bool, int, int, int], list[int]] = {}  # [seen, expected, watched]
        self._watch = watch
        self._parked = parked
        self.incomplete = 0  # watched images still waiting for observations

    def add(self, items: Sequence[Item]) -> None:
        for md, _, local in items:
            key = (local, md.origin, md.sensor_id, md.capture_time_us)
            seen = self._frames.get(key)
            if seen is None:
                seen = self._frames[key] = [0, 0, 0]
                tally = self._parked(key[1:]) if self._parked is not None and not local else None
                if tally is not None:
                    seen[0], seen[1] = tally[0], tally[1] + 1
            before = seen[2] and seen[0] < seen[1]
            seen[0] += 1
            seen[1] = max(seen[1], md.frame_remaining + 1)
            if not seen[2] and (self._watch is None or self._watch(md)):
                seen[2] = 1
            self.incomplete += (seen[2] and seen[0] < seen[1]) - before


@dataclass
class Changes:
    """What was accepted since the graph was last evaluated whole, and when that was (monotonic ns):
    when the node evaluates. An observation that can move the own pose is evaluated at once; the
    others at most ``coalesce_ns`` after the last full evaluation, together. Used by the loop's
    thread only."""

    coalesce_ns: int
    last_full_ns: int = 0
    pending: bool = False  # an observation accepted since the last full evaluation
    urgent: bool = False  # one that can move the own pose, not evaluated yet
    others: bool = False  # one of an edge not between the own entity and the world

    def due(self, now_ns: int) -> bool:
        """Whether the graph is to be evaluated now."""
        return self.pending and (self.urgent or now_ns - self.last_full_ns >= self.coalesce_ns)

    def due_ns(self, now_ns: int) -> int | None:
        """When the graph is to be evaluated next, or None if nothing changed."""
        if not self.pending:
            return None
        return now_ns if self.urgent else self.last_full_ns + self.coalesce_ns

    def evaluated(self, now_ns: int, complete: bool, rest_unchanged: bool = False) -> None:
        """After an evaluation at ``now_ns``: of every entity (``complete``), or of the own pose
        alone, after which a full one is still due unless ``rest_unchanged`` (it would give every
        other entity the pose it has) and no other edge changed."""
        self.urgent = False
        if complete:
            self.pending = self.others = False
            self.last_full_ns = now_ns
        elif rest_unchanged and not self.others:
            self.pending = False
