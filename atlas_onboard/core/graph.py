"""The transform graph of the paper's section 3.2: static vertices, expiring bidirectional edges,
a broad phase (BFS levels from ``world``) and a pose phase (fusion of parents one level lower).

Vertices are the entities of the world file; edges are observations keyed by (sensor id, marker id),
each holding ``T_a_b`` (the observed entity b in the observer entity a) and its inverse, so it can be
walked both ways. Time is passed in as integer nanoseconds of the caller's monotonic clock: the graph
never reads a clock, and expiry is exact (an edge whose age equals ``edge_timeout`` is still live, one
nanosecond later it is gone: the paper removes an edge when its age *exceeds* the timeout).
"""

from __future__ import annotations

import heapq
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import covariance, fusion, geometry
from atlas_onboard.errors import GeometryError

WORLD = "world"

EdgeKey = tuple[int, int]
"""(sensor id, marker id): one edge per sensor-marker pair, replaced on every new observation."""

MAX_SPEED_M_S = 3.0
"""The outlier gate's allowance for motion since the last estimate (an indoor drone's top speed)."""
MAX_RATE_RAD_S = 3.0
"""And for rotation since the last estimate (about 170 deg/s)."""


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


@dataclass(frozen=True, slots=True)
class Candidate:
    """One edge's vote for an entity's pose (eq. 2: the parent's pose times the edge), for a filter.

    ``covariance`` is 6x6 in the convention of :mod:`atlas_onboard.core.covariance` (position in the
    frame of the result, small rotation about the entity's body axes), including the parent's.
    ``parent`` is None when the parent is the frame's root (world, exact); otherwise the candidate
    is the parent's fused pose times the edge ``p_pc``, ``q_pc`` (parent to entity) whose own
    covariance is ``edge_covariance``, so that a filter can compose it with its own estimate of the
    parent instead.
    """

    entity: str
    key: EdgeKey
    stamp_ns: int
    capture_time_us: int
    p_m: NDArray[np.float64]
    q_xyzw: NDArray[np.float64]
    covariance: NDArray[np.float64]
    parent: str | None = None
    p_pc: NDArray[np.float64] | None = None
    q_pc: NDArray[np.float64] | None = None
    edge_covariance: NDArray[np.float64] | None = None


@dataclass(frozen=True, slots=True)
class EntityPose:
    """The fused world pose of one entity (Table 2, Vertex, plus what the publisher needs).

    Attributes:
        name: entity name.
        p_world_m: position in the world frame (ENU), metres, shape (3,).
        q_world_xyzw: orientation of the entity's body frame (FLU) in the world, x-first, shape (4,).
        level: hops from ``world`` (world itself is 0).
        order: position in the evaluation order (world is 0).
        n_observations: number of candidates fused for this entity (edges from parents one level lower).
        sigma_m: standard deviation of the fused position, metres, propagated along the chain.
        capture_time_us: capture time of the newest observation that contributed (through the chain).
        frame: the entity whose frame the pose is in: ``world``, or for a relative pose the first
            entity of a group that has no path to world.
        covariance: 6x6 covariance of (position in ``frame``, small rotation about the body axes),
            propagated along the chains of transforms (None: not computed).
        velocity_m_s: velocity in ``frame`` (None unless a filter estimates it).
        angular_rate_rad_s: body angular rate about the body axes (None unless a filter estimates it).
        velocity_covariance: 6x6 covariance of (velocity, angular rate) (None unless a filter
            estimates them).
    """

    name: str
    p_world_m: NDArray[np.float64]
    q_world_xyzw: NDArray[np.float64]
    level: int
    order: int
    n_observations: int
    sigma_m: float
    capture_time_us: int
    frame: str = WORLD
    covariance: NDArray[np.float64] | None = None
    velocity_m_s: NDArray[np.float64] | None = None
    angular_rate_rad_s: NDArray[np.float64] | None = None
    velocity_covariance: NDArray[np.float64] | None = None

    @property
    def T_world_entity(self) -> RigidTransform:
        return RigidTransform.from_components(self.p_world_m, Rotation.from_quat(self.q_world_xyzw))


@dataclass(frozen=True, slots=True)
class GraphResult:
    """The output of one evaluation: poses of the entities reachable from world, and the rest."""

    poses: dict[str, EntityPose]
    order: tuple[str, ...]  # evaluation order (BFS order from world)
    levels: dict[str, int]  # broad-phase level of each reached entity
    unreached: tuple[str, ...]  # entities with no edge path to world: no pose this time
    n_edges: int  # live edges used in this evaluation
    relative: dict[str, dict[str, EntityPose]] = field(default_factory=dict)  # root -> poses in root's frame
    candidates: dict[str, list[Candidate]] = field(default_factory=dict)  # only with keep_candidates
    gated: int = 0  # candidates rejected by the outlier gate in this evaluation
    complete: bool = True  # False: ``poses`` holds only the target of the evaluation and those below it

    def pose(self, name: str) -> EntityPose | None:
        return self.poses.get(name)


@dataclass(frozen=True, slots=True)
class _Plan:
    """What an evaluation does, given which edges exist (not their values): the broad phase's order
    and levels, and every candidate (edge row, direction, parent, child) sorted by stage, child and
    parent, with each stage's run. With BFS paths it is kept until an edge appears or goes."""

    order: NDArray[np.intp]
    level: NDArray[np.intp]
    stage_of: NDArray[np.intp]
    row: NDArray[np.intp]
    direction: NDArray[np.intp]
    parent: NDArray[np.intp]
    child: NDArray[np.intp]
    stages: tuple[slice, ...]
    runs: tuple[tuple[fusion.Runs, fusion.Runs], ...]  # per stage: runs of each child, of each (child, parent)
    from_root: tuple[bool, ...]  # per stage: every parent is the root (exact: identity, no covariance)


class _EdgeArrays:
    """The live edges' numbers, one row per edge (and free rows for the next ones), so that an
    evaluation is a handful of array operations however many edges there are."""

    def __init__(self, capacity: int = 64) -> None:
        self.used = np.zeros(capacity, dtype=bool)
        self.anchored = np.zeros(capacity, dtype=bool)  # observed by one of the node's own sensors
        self.a = np.zeros(capacity, dtype=np.intp)
        self.b = np.zeros(capacity, dtype=np.intp)
        self.p = np.zeros((2, capacity, 3))  # [0]: T_a_b, [1]: its inverse T_b_a
        self.q = np.zeros((2, capacity, 4))
        self.cov = np.zeros((2, capacity, 6, 6))
        self.inverted = np.zeros(capacity, dtype=bool)
        self.sigma = np.zeros(capacity)
        self.stamp = np.zeros(capacity, dtype=np.int64)
        self.capture = np.zeros(capacity, dtype=np.int64)
        self.keys: list[EdgeKey | None] = [None] * capacity
        self.free: list[int] = list(range(capacity - 1, -1, -1))
        self.version = 0  # changes whenever an edge appears or goes: the graph's shape, not its values

    def take(self) -> int:
        if not self.free:
            self._grow()
        self.version += 1
        return self.free.pop()

    def release(self, slot: int) -> None:
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


class TransformGraph:
    """Vertices fixed at construction; edges added by :meth:`update_edge`, expired by age."""

    def __init__(
        self,
        entity_names: Sequence[str],
        edge_timeout_ns: int,
        inverse_variance: bool = False,
        path: str = "bfs",
        relative: bool = False,
        age_sigma_m_per_s: float = 0.0,
        outlier_gate_sigma: float = 0.0,
        age_sigma_rad_per_s: float = 0.0,
        keep_candidates: bool = False,
        anchor_sensors: frozenset[int] = frozenset(),
    ) -> None:
        names = list(entity_names)
        if WORLD not in names:
            names.insert(0, WORLD)
        if len(set(names)) != len(names):
            raise GeometryError(f"expected unique entity names, got {names}")
        if edge_timeout_ns <= 0:
            raise GeometryError(f"expected a positive edge timeout, got {edge_timeout_ns} ns")
        self.names: tuple[str, ...] = tuple(names)
        self.index: dict[str, int] = {n: i for i, n in enumerate(names)}
        self.edge_timeout_ns = int(edge_timeout_ns)
        self.inverse_variance = inverse_variance
        if path not in ("bfs", "dijkstra"):
            raise GeometryError(f"expected path 'bfs' or 'dijkstra', got {path!r}")
        self.path = path
        self.relative = relative
        # An edge's information ages: the entities may have moved since it arrived. With this > 0,
        # an edge of age a (s) counts with sigma sqrt(sigma^2 + (a * age_sigma)^2), so fresh
        # observations outvote stale ones (0: the paper's method, every live edge counts as new).
        self.age_sigma_m_per_s = age_sigma_m_per_s
        # The same for the attitude (rad/s): only the covariance grows, no weight changes.
        self.age_sigma_rad_per_s = age_sigma_rad_per_s
        # Beyond the paper: a candidate farther than this many sigma from the consensus of the others
        # (or, with fewer than three, from the entity's last estimate) is left out. 0: off.
        self.outlier_gate_sigma = outlier_gate_sigma
        # The node's own sensors: their candidates are the gate's anchor, which no peer's outvotes.
        self.anchor_sensors = frozenset(anchor_sensors)
        self.keep_candidates = keep_candidates
        self.edges: dict[EdgeKey, Edge] = {}
        self._arr = _EdgeArrays()
        self._plans: dict[tuple[int, int, int | None], _Plan] = {}
        # The last estimate of each entity per frame root, for the gate: (p, q, sigma, sigma_att, stamp).
        self._prior: dict[tuple[int, int], tuple[NDArray[np.float64], NDArray[np.float64], float, float, int, int]] = {}
        self._gated_stamp: dict[EdgeKey, int] = {}
        self.gated_total = 0  # distinct edge observations the gate rejected (counted once each)

    def update_edge(
        self,
        key: EdgeKey,
        observer: str,
        observed: str,
        p_a_b: NDArray[np.float64],
        q_a_b_xyzw: NDArray[np.float64],
        sigma_m: float,
        now_ns: int,
        capture_time_us: int = 0,
        sigma_att_rad: float | None = None,
        cov_a_b: NDArray[np.float64] | None = None,
    ) -> None:
        """Create or refresh the edge ``key``: ``T_a_b`` of ``observed`` (b) in ``observer`` (a).

        ``cov_a_b`` is the edge's 6x6 covariance (:func:`covariance.observation` models a detection);
        without it, isotropic: ``sigma_m`` and ``sigma_att_rad`` (by default from ``sigma_m`` and the
        distance, :func:`covariance.attitude_sigma_rad`). The inverse is computed at evaluation.
        """
        a, b = self.index[observer], self.index[observed]
        if a == b:
            raise GeometryError(f"an edge must join two entities, got {observer!r} twice")
        p = np.array(p_a_b, dtype=float)
        q = np.array(q_a_b_xyzw, dtype=float)
        q /= math.sqrt(float(q @ q))
        if cov_a_b is None:
            att = (
                covariance.attitude_sigma_rad(sigma_m, math.sqrt(float(p @ p)))
                if sigma_att_rad is None
                else sigma_att_rad
            )
            cov = covariance.diagonal(float(sigma_m), float(att))
        else:
            cov = np.asarray(cov_a_b, dtype=float)
        old = self.edges.get(key)
        arr = self._arr
        slot = arr.take() if old is None else old.slot
        arr.used[slot], arr.keys[slot] = True, key
        arr.anchored[slot] = key[0] in self.anchor_sensors
        arr.a[slot], arr.b[slot] = a, b
        arr.p[0, slot], arr.q[0, slot], arr.cov[0, slot] = p, q, cov
        arr.inverted[slot] = False  # the inverse is computed at evaluation, for all new edges at once
        arr.sigma[slot], arr.stamp[slot], arr.capture[slot] = sigma_m, now_ns, capture_time_us
        self.edges[key] = Edge(key, a, b, p, q, float(sigma_m), int(now_ns), int(capture_time_us), cov, slot)

    def clear(self) -> None:
        """Forget every edge."""
        for e in self.edges.values():
            self._arr.release(e.slot)
        self.edges.clear()

    def _invert_new_edges(self) -> None:
        arr = self._arr
        new = np.flatnonzero(arr.used & ~arr.inverted)
        if new.size == 0:
            return
        p_ab, q_ab = arr.p[0, new], arr.q[0, new]
        R_ab = geometry.quat_matrix(q_ab)
        arr.p[1, new] = -np.einsum("nji,nj->ni", R_ab, p_ab)
        arr.q[1, new] = q_ab * [-1.0, -1.0, -1.0, 1.0]
        arr.cov[1, new] = covariance.transform(covariance.inverse_jacobian(p_ab, R_ab), arr.cov[0, new])
        arr.inverted[new] = True

    def expire(self, now_ns: int) -> int:
        """Remove edges older than the timeout (age > timeout); returns how many were removed."""
        arr = self._arr
        dead = np.flatnonzero(arr.used & (now_ns - arr.stamp > self.edge_timeout_ns))
        for slot in dead.tolist():
            key = arr.keys[slot]
            arr.release(slot)
            del self.edges[key]
        return len(dead)

    def next_expiry_ns(self) -> int | None:
        """The first time at which an edge will have expired (its age exceeds the timeout), or None
        without edges: until then a new evaluation can only differ by the age of the edges."""
        if not self.edges:
            return None
        return int(self._arr.stamp[self._arr.used].min()) + self.edge_timeout_ns + 1

    def live_edges(self, now_ns: int) -> list[Edge]:
        """Edges whose age is at most the timeout (not removed: :meth:`expire` does that)."""
        return [e for e in self.edges.values() if now_ns - e.stamp_ns <= self.edge_timeout_ns]

    def broad_phase(self, root: int | None = None) -> tuple[list[int], dict[int, int]]:
        """BFS over the current edges from ``root`` (world by default): the visiting order and each
        reached vertex's level."""
        slots = np.flatnonzero(self._arr.used)
        order, level = self._bfs(self._arr.a[slots], self._arr.b[slots], self.index[WORLD] if root is None else root)
        return order.tolist(), {int(v): int(level[v]) for v in order}

    def _bfs(self, a: NDArray[np.intp], b: NDArray[np.intp], root: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
        """Breadth-first search on the edge arrays, one level at a time.

        Returns the visiting order and the level of every vertex (-1: not reached). The order is a
        queue's: a level's vertices in the order of the parent that found them first, and those of
        one parent in the order of the world file, so it is deterministic.
        """
        n = len(self.names)
        level = np.full(n, -1, dtype=np.intp)
        rank = np.full(n, n, dtype=np.intp)
        level[root], rank[root] = 0, 0
        order = [np.array([root], dtype=np.intp)]
        found, depth = 1, 0
        while True:
            la, lb = level[a], level[b]
            down = (la == depth) & (lb < 0)
            up = (lb == depth) & (la < 0)
            child = np.concatenate((b[down], a[up]))
            if child.size == 0:
                break
            parent = np.concatenate((a[down], b[up]))
            first = np.full(n, n, dtype=np.intp)
            np.minimum.at(first, child, rank[parent])
            new = np.unique(child)
            new = new[np.lexsort((new, first[new]))]
            depth += 1
            level[new] = depth
            rank[new] = np.arange(found, found + new.size)
            found += new.size
            order.append(new)
        return np.concatenate(order), level

    def dijkstra_phase(self, root: int | None = None) -> tuple[list[int], dict[int, float]]:
        """Shortest paths over the current edges from ``root`` with each edge's variance (sigma^2)
        as its length: the visiting order and each reached vertex's distance."""
        slots = np.flatnonzero(self._arr.used)
        arr = self._arr
        order, dist = self._dijkstra(
            arr.a[slots], arr.b[slots], arr.sigma[slots], self.index[WORLD] if root is None else root
        )
        return order.tolist(), {int(v): float(dist[v]) for v in order}

    def _dijkstra(
        self, a: NDArray[np.intp], b: NDArray[np.intp], sigma: NDArray[np.float64], root: int
    ) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
        """Variances add along a chain of independent transforms, so the distance of a vertex is the
        variance of its best chain: the paper's future work ("use the standard deviation information
        of the graph as distance ... Dijkstra"). Distances are inf for vertices not reached."""
        best: dict[tuple[int, int], float] = {}
        for u, v, s in zip(a.tolist(), b.tolist(), (sigma**2).tolist(), strict=True):
            k = (min(u, v), max(u, v))
            best[k] = min(best.get(k, np.inf), s)
        adj: list[list[tuple[int, float]]] = [[] for _ in self.names]
        for (u, v), w in best.items():
            adj[u].append((v, w))
            adj[v].append((u, w))
        dist = np.full(len(self.names), np.inf)
        dist[root] = 0.0
        order: list[int] = []
        heap = [(0.0, root)]
        done: set[int] = set()
        while heap:
            d, v = heapq.heappop(heap)
            if v in done:
                continue
            done.add(v)
            order.append(v)
            for u, w in adj[v]:
                nd = d + w
                if u not in done and nd < dist[u]:
                    dist[u] = nd
                    heapq.heappush(heap, (nd, u))
        return np.array(order, dtype=np.intp), dist

    def evaluate(self, now_ns: int, target: str | None = None) -> GraphResult:
        """Expire old edges, then run the broad phase and the pose phase (eq. 2) from world.

        With ``target``, the pose phase computes only what ``target``'s pose depends on: every entity
        of a lower stage (level), and of its own stage only ``target`` (the node's own pose, when
        others can wait). Its pose is the one a full evaluation gives (tested); the result says
        ``complete=False`` and its ``poses`` hold only the entities computed. A target with no path to
        world gets the full evaluation (relative poses included).

        With the paper's method (``path="bfs"``) a vertex's candidates come from every live edge to
        a parent exactly one level lower; edges within a level (cycles such as the paper's A-B) and
        towards higher levels are ignored. With ``path="dijkstra"`` the candidates come from every
        neighbour whose best chain to world has a smaller variance, weighted by the variance of the
        whole chain, so a long precise chain can outvote a short noisy one.

        With ``relative=True``, each group of entities that has no path to world is evaluated from
        its first entity (in world-file order), and its poses are reported relative to that entity.
        """
        self.expire(now_ns)
        self._invert_new_edges()
        slots = np.flatnonzero(self._arr.used)
        world = self.index[WORLD]
        cands: dict[str, list[Candidate]] | None = {} if self.keep_candidates else None
        goal = self.index[target] if target is not None else None
        poses, order, levels, gated = self._evaluate_from(slots, world, now_ns, cands, goal)
        reached = set(order)
        if goal is not None and goal not in reached:
            goal = None  # _evaluate_from has evaluated everything: the relative poses follow
        unreached = tuple(self.names[v] for v in range(len(self.names)) if v not in reached)
        relative: dict[str, dict[str, EntityPose]] = {}
        if self.relative:
            remaining = [v for v in range(len(self.names)) if v not in reached]
            while remaining:
                root = remaining[0]
                rel, rel_order, _, g = self._evaluate_from(slots, root, now_ns)
                gated += g
                if len(rel_order) > 1:
                    relative[self.names[root]] = rel
                remaining = [v for v in remaining if v not in set(rel_order)]
        return GraphResult(
            poses=poses,
            order=tuple(self.names[v] for v in order),
            levels={self.names[v]: levels[v] for v in order},
            unreached=unreached,
            n_edges=len(slots),
            relative=relative,
            candidates=cands or {},
            gated=gated,
            complete=goal is None,
        )

    def _plan(self, slots: NDArray[np.intp], root: int, goal: int | None) -> _Plan:
        """The plan of an evaluation from ``root`` over the live edges ``slots`` (see :class:`_Plan`).
        With BFS it depends only on which edges exist, so it is reused until one appears or goes
        (most evaluations only refresh edges); Dijkstra's depends on the sigmas, so it is made anew."""
        key = (self._arr.version, root, goal)
        cached = self._plans.get(key) if self.path == "bfs" else None
        if cached is not None:
            return cached
        n = len(self.names)
        arr = self._arr
        a, b = arr.a[slots], arr.b[slots]
        order_arr, level = self._bfs(a, b, root)
        la, lb = level[a], level[b]
        reached = (la >= 0) & (lb >= 0)
        if self.path == "dijkstra":
            order_arr, dist = self._dijkstra(a, b, arr.sigma[slots], root)
            down = reached & (dist[a] < dist[b])  # a is b's parent: the edge is walked as given
            up = reached & (dist[b] < dist[a])  # b is a's parent: the edge is walked backwards
        else:
            down = reached & (lb == la + 1)
            up = reached & (la == lb + 1)
        rank = np.full(n, n, dtype=np.intp)
        rank[order_arr] = np.arange(order_arr.size)
        # Every candidate: (edge row, direction); parent and child.
        row = np.concatenate((slots[down], slots[up]))
        direction = np.concatenate((np.zeros(down.sum(), dtype=np.intp), np.ones(up.sum(), dtype=np.intp)))
        parent_all = np.concatenate((a[down], b[up]))
        child_all = np.concatenate((b[down], a[up]))
        # A vertex's stage is one more than its deepest parent's, so that a whole stage can be
        # composed and fused in one batched call (for BFS the stage is the level).
        if self.path == "dijkstra":
            stage_of = np.zeros(n, dtype=np.intp)
            while True:
                nxt = np.zeros(n, dtype=np.intp)
                np.maximum.at(nxt, child_all, stage_of[parent_all] + 1)
                if np.array_equal(nxt, stage_of):
                    break
                stage_of = nxt
        else:
            stage_of = np.maximum(level, 0)
        if goal is not None and level[goal] >= 0:
            wanted = (stage_of[child_all] < stage_of[goal]) | (child_all == goal)
            row, direction = row[wanted], direction[wanted]
            parent_all, child_all = parent_all[wanted], child_all[wanted]
        # Sorted by stage, then child (evaluation order), then parent, then edge.
        sort = np.lexsort((row, parent_all, rank[child_all], stage_of[child_all]))
        row, direction, parent_all, child_all = row[sort], direction[sort], parent_all[sort], child_all[sort]
        cuts = [0, *(np.flatnonzero(np.diff(stage_of[child_all])) + 1).tolist(), row.size] if row.size else []
        stages = tuple(slice(i, j) for i, j in itertools.pairwise(cuts))
        runs = tuple(covariance.runs_by_parent(child_all[sel], parent_all[sel]) for sel in stages)
        from_root = tuple(bool((parent_all[sel] == root).all()) for sel in stages)
        plan = _Plan(order_arr, level, stage_of, row, direction, parent_all, child_all, stages, runs, from_root)
        if self.path == "bfs":
            if len(self._plans) >= 8:  # old shapes are never asked for again
                self._plans.clear()
            self._plans[key] = plan
        return plan

    def _evaluate_from(
        self,
        slots: NDArray[np.intp],
        root: int,
        now_ns: int,
        out: dict[str, list[Candidate]] | None = None,
        goal: int | None = None,
    ) -> tuple[dict[str, EntityPose], list[int], dict[int, int], int]:
        """Poses of every vertex reachable from ``root``, in ``root``'s frame (and how many candidates
        the gate left out). ``out`` collects each entity's candidates when given. With ``goal`` (if
        reached), only the vertices of lower stages and ``goal`` itself get a pose."""
        n = len(self.names)
        arr = self._arr
        plan = self._plan(slots, root, goal)
        order_arr, level, stage_of = plan.order, plan.level, plan.stage_of
        row, direction, parent_all, child_all = plan.row, plan.direction, plan.parent, plan.child
        sigma_raw = arr.sigma[row]
        ageing = self.age_sigma_m_per_s > 0.0 or self.age_sigma_rad_per_s > 0.0
        age_s = np.maximum(now_ns - arr.stamp[row], 0) / 1e9 if ageing else None
        if self.age_sigma_m_per_s > 0.0:
            sigma_all = np.hypot(sigma_raw, age_s * self.age_sigma_m_per_s)
        else:
            sigma_all = sigma_raw
        p_all, q_all, c_all = arr.p[direction, row], arr.q[direction, row], arr.cov[direction, row]
        t_all = arr.capture[row]

        p_world = np.zeros((n, 3))
        q_world = np.zeros((n, 4))
        q_world[:, 3] = 1.0
        cov_world = np.zeros((n, 6, 6))
        sigma = np.zeros(n)
        stamp_us = np.zeros(n, dtype=np.int64)
        count = np.zeros(n, dtype=np.intp)

        gated = 0
        for sel, (kids, pairs), from_root in zip(plan.stages, plan.runs, plan.from_root, strict=True):
            parent, child = parent_all[sel], child_all[sel]
            p_pc, q_pc, s_edge = p_all[sel], q_all[sel], sigma_all[sel]
            t_cand = np.maximum(t_all[sel], stamp_us[parent])  # a candidate is as new as its newest part
            c_edge = c_all[sel]
            if age_s is not None:
                c_edge = c_edge.copy()
                grow = (s_edge**2 - sigma_raw[sel] ** 2).clip(0.0)
                c_edge[:, [0, 1, 2], [0, 1, 2]] += grow[:, None]
                turn = (age_s[sel] * self.age_sigma_rad_per_s) ** 2
                c_edge[:, [3, 4, 5], [3, 4, 5]] += turn[:, None]
            Jp: NDArray[np.float64] | None = None
            if from_root:  # the root's pose is the identity, exactly, with no uncertainty
                p_cand, q_cand, s_cand, edge_term = p_pc, q_pc, s_edge, c_edge
            else:
                # eq. 2: each candidate is P_parent * T_parent_child
                R_wp = geometry.quat_matrix(q_world[parent])
                p_cand = p_world[parent] + (R_wp @ p_pc[:, :, None])[:, :, 0]
                q_cand = geometry.quat_multiply(q_world[parent], q_pc)
                # The candidate's sigma carries its parent's: variances add along a chain.
                s_cand = np.sqrt(s_edge**2 + sigma[parent] ** 2)
                # Beyond the paper: the full 6x6 covariance along the chain (lever arms included).
                Jp, Je = covariance.compose_jacobians(R_wp, p_pc, geometry.quat_matrix(q_pc))
                edge_term = covariance.transform(Je, c_edge)
            keep = None
            if self.outlier_gate_sigma > 0.0:
                c_cand = edge_term if Jp is None else covariance.transform(Jp, cov_world[parent]) + edge_term
                rows_sel = row[sel]
                # The anchor: the own cameras' direct views of the root's markers (through another
                # entity, a candidate also rests on that entity's estimate: a peer's work).
                anchor = arr.anchored[rows_sel] & (parent == root)
                keep = self._gate(root, child, p_cand, q_cand, c_cand, now_ns, t_cand, anchor, arr.stamp[rows_sel])
                for slot in row[sel][~keep].tolist():
                    key, stamp = arr.keys[slot], int(arr.stamp[slot])
                    if self._gated_stamp.get(key) != stamp:
                        self._gated_stamp[key] = stamp
                        self.gated_total += 1
                gated += int(keep.size - keep.sum())
            if out is not None:
                c_full = edge_term if Jp is None else covariance.transform(Jp, cov_world[parent]) + edge_term
                rows = row[sel]
                for i in range(len(child)) if keep is None else np.flatnonzero(keep):
                    slot = int(rows[i])
                    via = None if parent[i] == root else self.names[parent[i]]
                    out.setdefault(self.names[child[i]], []).append(
                        Candidate(
                            self.names[child[i]], arr.keys[slot], int(arr.stamp[slot]),
                            int(t_cand[i]), p_cand[i], q_cand[i], c_full[i],
                            via, p_pc[i], q_pc[i], c_edge[i],
                        )
                    )  # fmt: skip
            if keep is not None and not keep.all():
                # A child whose every candidate was gated keeps its last estimate (not re-sent: same stamp).
                for v in set(child[~keep].tolist()) - set(child[keep].tolist()):
                    prior = self._prior[(root, v)]
                    p_world[v], q_world[v], sigma[v] = prior[0], prior[1], prior[2]
                    cov_world[v] = covariance.diagonal(prior[2], prior[3])
                    stamp_us[v] = prior[5]
                parent, child, p_cand, q_cand = parent[keep], child[keep], p_cand[keep], q_cand[keep]
                s_edge, s_cand, t_cand = s_edge[keep], s_cand[keep], t_cand[keep]
                Jp, edge_term = None if Jp is None else Jp[keep], edge_term[keep]
                if len(child) == 0:
                    continue
                kids, pairs = covariance.runs_by_parent(child, parent)
            # eq. 6-7 per child, vectorised: w_i = sigma_min / sigma_i (squared for inverse variance).
            # The paper weighs by the sensor's sigma; Dijkstra weighs by the whole chain's.
            s_weigh = s_cand if self.path == "dijkstra" else s_edge
            if self.inverse_variance:
                # Beyond the paper: weights from each candidate's propagated position variance (its
                # covariance's position block, the detector's own where it reported one, aged), so a
                # fresh precise view outweighs a stale or a poorly placed one whatever their sigma says.
                c_weigh = (
                    edge_term
                    if Jp is None or self.path != "dijkstra"
                    else edge_term + covariance.transform(Jp, cov_world[parent])
                )
                s_weigh = np.sqrt(np.maximum(np.trace(c_weigh[:, :3, :3], axis1=1, axis2=2) / 3.0, 1e-30))
            weights = np.repeat(np.minimum.reduceat(s_weigh, kids.starts), kids.sizes) / s_weigh
            if self.inverse_variance:
                weights = weights**2
            ids = kids.ids
            p_world[ids], q_world[ids], sigma[ids] = fusion.fuse_runs(kids, p_cand, q_cand, s_cand, weights)
            cov_world[ids] = covariance.fuse_runs(kids, pairs, weights, Jp, cov_world, edge_term)
            count[ids] = kids.sizes
            newest = np.maximum.reduceat(t_cand, kids.starts)
            stamp_us[ids] = newest
            if self.outlier_gate_sigma > 0.0:
                for k, v in enumerate(ids.tolist()):
                    att = float(np.sqrt(max(np.trace(cov_world[v][3:, 3:]) / 3.0, 0.0)))
                    self._prior[(root, v)] = (
                        p_world[v].copy(), q_world[v].copy(), float(sigma[v]), att, now_ns, int(newest[k])
                    )  # fmt: skip

        order = order_arr.tolist()
        levels, counts, sigmas, stamps = level.tolist(), count.tolist(), sigma.tolist(), stamp_us.tolist()
        frame = self.names[root]
        poses = {}
        below = int(stage_of[goal]) if goal is not None and level[goal] >= 0 else None
        stages = stage_of.tolist()
        for rank_v, v in enumerate(order):
            if below is not None and v != goal and stages[v] >= below:
                continue
            name = self.names[v]
            poses[name] = EntityPose(
                name, p_world[v], q_world[v], levels[v], rank_v, counts[v], sigmas[v], stamps[v], frame, cov_world[v]
            )
        return poses, order, {v: levels[v] for v in order}, gated

    def _gate(
        self,
        root: int,
        child: NDArray[np.intp],
        p: NDArray[np.float64],
        q: NDArray[np.float64],
        cov: NDArray[np.float64],
        now_ns: int,
        capture_us: NDArray[np.int64],
        anchored: NDArray[np.bool_] | None = None,
        arrival_ns: NDArray[np.int64] | None = None,
    ) -> NDArray[np.bool_]:
        """Which candidates agree with the consensus of their entity's candidates.

        First, where some of an entity's candidates are direct views of the root's markers by the
        node's own sensors (``anchored``), those are the anchor: any other candidate (a peer's,
        whoever sent it) that agrees with none of them within ``outlier_gate_sigma`` standard
        deviations (both candidates', plus what the entity may have moved between their captures, at
        most between their arrivals: a sender chooses its stamps, not when they arrive) is out,
        however many such candidates there are and however small their sigma. The rest are then
        judged among themselves as follows.

        With three or more candidates the reference is their median (position per axis; orientation:
        the candidate nearest to all others), which one wrong candidate cannot move. With fewer, the
        reference is the entity's last estimate if it is younger than the edge timeout, widened by
        what the entity may have moved since (since the estimate was made or since the capture of
        its newest observation, ``capture_us`` against the estimate's, whichever is longer: an
        estimate made a moment ago may rest on a frame taken well before). A candidate is out when
        its position or attitude is more than ``outlier_gate_sigma`` standard deviations (its own
        and the reference's) away.
        If the median would leave out more than half of the candidates, there is no consensus and
        all are kept; two candidates that both contradict the last estimate but agree with each other
        are kept (the estimate is out of date). A lone candidate against a fresh estimate loses: the
        entity keeps its estimate until that is older than the edge timeout.
        """
        k = self.outlier_gate_sigma
        keep = np.ones(len(child), dtype=bool)
        s_pos = np.sqrt(np.trace(cov[:, :3, :3], axis1=1, axis2=2) / 3.0)
        s_att = np.sqrt(np.trace(cov[:, 3:, 3:], axis1=1, axis2=2) / 3.0)
        for v in np.unique(child):
            idx = np.flatnonzero(child == v)
            if anchored is not None and arrival_ns is not None:
                own = anchored[idx]
                if own.any() and not own.all():
                    agree = self._agrees_with_anchor(idx[~own], idx[own], p, q, s_pos, s_att, capture_us, arrival_ns)
                    keep[idx[~own][~agree]] = False
                    idx = idx[own | np.isin(idx, idx[~own][agree])]
            q_v = q[idx]
            if len(idx) >= 3:
                ref_p = np.median(p[idx], axis=0)
                ref_q = q_v[int(np.argmin(_angles(q_v[:, None, :], q_v[None, :, :]).sum(axis=1)))]
                ref_s, ref_a, slack_p, slack_a = 0.0, 0.0, 0.0, 0.0
            else:
                prior = self._prior.get((root, int(v)))
                if prior is None or now_ns - prior[4] > self.edge_timeout_ns:
                    continue
                # The swarm's capture clock and the evaluation's clock are not compared, only their gaps.
                age_s = np.maximum((now_ns - prior[4]) / 1e9, (capture_us[idx] - prior[5]) / 1e6)
                ref_p, ref_q, ref_s, ref_a = prior[0], prior[1], prior[2], prior[3]
                slack_p, slack_a = MAX_SPEED_M_S * age_s, MAX_RATE_RAD_S * age_s
            d_p = np.linalg.norm(p[idx] - ref_p, axis=1)
            d_a = _angles(ref_q, q_v)
            ok = (d_p <= k * np.hypot(s_pos[idx], ref_s) + slack_p) & (d_a <= k * np.hypot(s_att[idx], ref_a) + slack_a)
            if len(idx) >= 3:
                if ok.sum() * 2 >= len(idx):
                    keep[idx] = ok
            elif len(idx) == 2 and not ok.any():
                # Both contradict the last estimate: if they agree with each other, it is the estimate
                # that is out of date (kept both); if not, nothing can be trusted (both out).
                d2 = float(np.linalg.norm(p[idx[0]] - p[idx[1]]))
                a2 = float(_angles(q_v[0], q_v[1]))
                agree = d2 <= k * np.hypot(s_pos[idx[0]], s_pos[idx[1]]) and a2 <= k * np.hypot(*s_att[idx])
                keep[idx] = agree
            else:
                keep[idx] = ok
        return keep

    def _agrees_with_anchor(
        self,
        others: NDArray[np.intp],
        anchors: NDArray[np.intp],
        p: NDArray[np.float64],
        q: NDArray[np.float64],
        s_pos: NDArray[np.float64],
        s_att: NDArray[np.float64],
        capture_us: NDArray[np.int64],
        arrival_ns: NDArray[np.int64],
    ) -> NDArray[np.bool_]:
        """For each of ``others``: whether it is within the gate of at least one of ``anchors``."""
        k = self.outlier_gate_sigma
        d_p = np.linalg.norm(p[others][:, None, :] - p[anchors][None, :, :], axis=2)  # (others, anchors)
        d_a = _angles(q[others][:, None, :], q[anchors][None, :, :])
        dt_capture_s = np.abs(capture_us[others][:, None] - capture_us[anchors][None, :]) / 1e6
        dt_arrival_s = np.abs(arrival_ns[others][:, None] - arrival_ns[anchors][None, :]) / 1e9
        dt_s = np.minimum(dt_capture_s, dt_arrival_s)
        ok_p = d_p <= k * np.hypot(s_pos[others][:, None], s_pos[anchors][None, :]) + MAX_SPEED_M_S * dt_s
        ok_a = d_a <= k * np.hypot(s_att[others][:, None], s_att[anchors][None, :]) + MAX_RATE_RAD_S * dt_s
        return np.asarray((ok_p & ok_a).any(axis=1))


def _angles(q_a_xyzw: NDArray[np.float64], q_b_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation angle (rad) between unit quaternions, broadcast over leading axes: what
    ``(Rotation.from_quat(a).inv() * Rotation.from_quat(b)).magnitude()`` gives, for the gate's many
    small sets without building Rotation objects (2 acos |a . b|, either sign of a quaternion)."""
    dot = np.abs(np.sum(np.asarray(q_a_xyzw) * np.asarray(q_b_xyzw), axis=-1))
    return 2.0 * np.arccos(np.minimum(dot, 1.0))
