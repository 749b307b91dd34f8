"""The graph's edges: the record a caller sees (:class:`Edge`) and the storage evaluation reads
(:class:`EdgeStore`: one row per edge in arrays, its inverse included, and the records by key).

Time is integer nanoseconds of the caller's monotonic clock. Expiry is exact: an edge whose age
equals the timeout is still live, one nanosecond later it is gone (the paper removes an edge when
its age *exceeds* the timeout).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core import covariance, geometry

WORLD = "world"

EdgeKey = tuple[int, int]
"""(sensor id, marker id): one edge per sensor-marker pair, replaced on every new observation."""


@dataclass(slots=True)
class Edge:
    """One observation between two entities, traversable both ways (Table 2, Edge).

    The graph keeps its edges' numbers in arrays for evaluation (one row per edge, the inverse
    included); this record is the edge as it was given, for callers and tests.
    """

    key: EdgeKey
    a: int  # index of the observing entity (the sensor's)
    b: int  # index of the observed entity (the marker's)
    p_a_b: NDArray[np.float64]
    q_a_b: NDArray[np.float64]  # xyzw
    sigma_m: float
    stamp_ns: int  # arrival on this node's clock: the edge's age is measured from here
    capture_time_us: int  # when the image was taken, on the observer's clock
    cov_a_b: NDArray[np.float64]  # 6x6, see core.covariance
    slot: int = -1  # its row in the graph's arrays


class EdgeStore:
    """The live edges: their records by key, and their numbers one row per edge (with free rows for
    the next ones), so that an evaluation is a handful of array operations however many edges there
    are. Row arrays: ``p``, ``q``, ``cov`` hold ``[0]`` T_a_b and ``[1]`` its inverse T_b_a."""

    def __init__(self, capacity: int = 64) -> None:
        self.edges: dict[EdgeKey, Edge] = {}
        self.used = np.zeros(capacity, dtype=bool)
        self.anchored = np.zeros(capacity, dtype=bool)  # observed by one of the node's own sensors
        self.a = np.zeros(capacity, dtype=np.intp)
        self.b = np.zeros(capacity, dtype=np.intp)
        self.p = np.zeros((2, capacity, 3))
        self.q = np.zeros((2, capacity, 4))
        self.cov = np.zeros((2, capacity, 6, 6))
        self.inverted = np.zeros(capacity, dtype=bool)
        self.sigma = np.zeros(capacity)
        self.stamp = np.zeros(capacity, dtype=np.int64)
        self.capture = np.zeros(capacity, dtype=np.int64)
        self.keys: list[EdgeKey | None] = [None] * capacity
        self.free: list[int] = list(range(capacity - 1, -1, -1))
        self.version = 0  # changes whenever an edge appears or goes: the graph's shape, not its values
        # The last record each key held before a newer observation replaced it or a newer image of its
        # view removed it, with whether it was anchored: put back when the newer one is refused as
        # too fast (:meth:`restore`), so a forged newer stamp cannot push the real view out.
        self.displaced: dict[EdgeKey, tuple[Edge, bool]] = {}
        self._restored: dict[EdgeKey, int] = {}  # key -> arrival stamp of the record put back (once only)

    def put(self, edge: Edge, anchored: bool) -> None:
        """Create or refresh ``edge.key`` (its row is set here). Its inverse is computed by
        :meth:`invert_new` when an evaluation first walks it backwards."""
        old = self.edges.get(edge.key)
        if old is None:
            slot = self._take()
        else:
            if self._restored.get(edge.key) != old.stamp_ns:
                self.displaced[edge.key] = (old, bool(self.anchored[old.slot]))
            slot = old.slot
            if (old.a, old.b) != (edge.a, edge.b):  # the key now joins other entities: a new shape
                self.version += 1
        edge.slot = slot
        self.used[slot], self.keys[slot] = True, edge.key
        self.anchored[slot] = anchored
        self.a[slot], self.b[slot] = edge.a, edge.b
        self.p[0, slot], self.q[0, slot], self.cov[0, slot] = edge.p_a_b, edge.q_a_b, edge.cov_a_b
        self.inverted[slot] = False
        self.sigma[slot], self.stamp[slot], self.capture[slot] = edge.sigma_m, edge.stamp_ns, edge.capture_time_us
        self.edges[edge.key] = edge

    def clear(self) -> None:
        """Forget every edge."""
        for e in self.edges.values():
            self._release(e.slot)
        self.edges.clear()
        self.displaced.clear()
        self._restored.clear()

    def live_slots(self) -> NDArray[np.intp]:
        """The rows of the live edges, in row order."""
        return np.flatnonzero(self.used)

    def expire(self, now_ns: int, timeout_ns: int) -> NDArray[np.intp]:
        """Remove edges older than the timeout (age > timeout); returns their entities' indices
        (``a`` then ``b`` of each removed edge)."""
        dead = np.flatnonzero(self.used & (now_ns - self.stamp > timeout_ns))
        if dead.size == 0:
            return dead
        ends = np.concatenate((self.a[dead], self.b[dead]))
        for slot in dead.tolist():
            key = self.keys[slot]
            self._release(slot)
            del self.edges[key]
        return ends

    def next_expiry_ns(self, timeout_ns: int) -> int | None:
        """The first time at which an edge will have expired, or None without edges."""
        if not self.edges:
            return None
        return int(self.stamp[self.used].min()) + timeout_ns + 1

    def invert_new(self, rows: NDArray[np.intp] | None = None) -> None:
        """T_b_a and its covariance for every edge put since it was last inverted; with ``rows``, for
        those rows only (the ones an evaluation walks backwards: the others wait until one does)."""
        if rows is None:
            new = np.flatnonzero(self.used & ~self.inverted)
        else:
            new = rows[~self.inverted[rows]]
        if new.size == 0:
            return
        p_ab, q_ab = self.p[0, new], self.q[0, new]
        R_ab = geometry.quat_matrix(q_ab)
        self.p[1, new] = -np.einsum("nji,nj->ni", R_ab, p_ab)
        self.q[1, new] = q_ab * [-1.0, -1.0, -1.0, 1.0]
        self.cov[1, new] = covariance.transform(covariance.inverse_jacobian(p_ab, R_ab), self.cov[0, new])
        self.inverted[new] = True

    def superseded(self, key: EdgeKey, arrival_ns: int, capture_time_us: int) -> bool:
        """Whether the edge ``key`` already holds a newer observation than one that arrived at
        ``arrival_ns`` from an image captured at ``capture_time_us``: one that arrived later, or one
        of a later image (a datagram overtaken on the way)."""
        edge = self.edges.get(key)
        return edge is not None and (edge.stamp_ns > arrival_ns or edge.capture_time_us > capture_time_us)

    def remove(self, key: EdgeKey, displaced: bool = False) -> bool:
        """Remove the edge ``key`` if there is one; whether there was. ``displaced``: a newer image of its
        view removed it (it may be put back: :meth:`restore`)."""
        edge = self.edges.pop(key, None)
        if edge is None:
            return False
        if displaced and self._restored.get(key) != edge.stamp_ns:
            self.displaced[key] = (edge, bool(self.anchored[edge.slot]))
        self._release(edge.slot)
        return True

    def restore(self, refused: EdgeKey, now_ns: int, timeout_ns: int) -> bool:
        """Put back what the refused observation of ``refused`` displaced: its own previous record and
        the edges of its view (same sensor, same two entities) that a newer image removed, where they
        are still live and their key holds nothing newer. Whether anything was put back."""
        edge = self.edges.get(refused)
        if edge is None:
            return False
        back = []
        for key, (old, anchored) in self.displaced.items():
            if key[0] != refused[0] or (old.a, old.b) != (edge.a, edge.b) or now_ns - old.stamp_ns > timeout_ns:
                continue
            held = self.edges.get(key)
            if key == refused or held is None:
                back.append((key, old, anchored))
        for key, old, anchored in back:
            del self.displaced[key]
            self.put(old, anchored)
            self.displaced.pop(key, None)  # the refused record is not worth putting back in turn
            self._restored[key] = old.stamp_ns
        return bool(back)

    def _take(self) -> int:
        if not self.free:
            self._grow()
        self.version += 1
        return self.free.pop()

    def _release(self, slot: int) -> None:
        self.version += 1
        self.used[slot] = False
        self.keys[slot] = None
        self.free.append(slot)

    def _grow(self) -> None:
        old = len(self.used)
        for name in ("used", "anchored", "a", "b", "inverted", "sigma", "stamp", "capture"):
            arr = getattr(self, name)
            setattr(self, name, np.concatenate([arr, np.zeros_like(arr)]))
        for name in ("p", "q", "cov"):
            arr = getattr(self, name)
            setattr(self, name, np.concatenate([arr, np.zeros_like(arr)], axis=1))
        self.keys.extend([None] * old)
        self.free.extend(range(2 * old - 1, old - 1, -1))
