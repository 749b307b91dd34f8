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
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import fusion, geometry
from atlas_onboard.errors import GeometryError

WORLD = "world"

EdgeKey = tuple[int, int]
"""(sensor id, marker id): one edge per sensor-marker pair, replaced on every new observation."""


@dataclass(slots=True)
class Edge:
    """One observation between two entities, traversable both ways (Table 2, Edge)."""

    key: EdgeKey
    a: int  # index of the observing entity (the sensor's)
    b: int  # index of the observed entity (the marker's)
    p_a_b: NDArray[np.float64]
    q_a_b: NDArray[np.float64]  # xyzw
    p_b_a: NDArray[np.float64] | None  # the inverse, filled in at the next evaluation
    q_b_a: NDArray[np.float64] | None  # xyzw
    sigma_m: float
    stamp_ns: int  # arrival on this node's clock: the edge's age is measured from here
    capture_time_us: int  # when the image was taken, on the observer's clock


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

    def pose(self, name: str) -> EntityPose | None:
        return self.poses.get(name)


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
        self.edges: dict[EdgeKey, Edge] = {}

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
    ) -> None:
        """Create or refresh the edge ``key``: ``T_a_b`` of ``observed`` (b) in ``observer`` (a).

        The inverse is computed once here, so evaluation walks both directions at no extra cost.
        """
        a, b = self.index[observer], self.index[observed]
        if a == b:
            raise GeometryError(f"an edge must join two entities, got {observer!r} twice")
        p = np.asarray(p_a_b, dtype=float)
        q = np.asarray(q_a_b_xyzw, dtype=float)
        q = q / np.linalg.norm(q)
        # The inverse (for walking the edge backwards) is computed at evaluation, for all new edges at once.
        self.edges[key] = Edge(key, a, b, p, q, None, None, float(sigma_m), int(now_ns), int(capture_time_us))

    def _invert_new_edges(self, edges: list[Edge]) -> None:
        new = [e for e in edges if e.p_b_a is None]
        if not new:
            return
        p_inv, q_inv = geometry.invert_arrays(np.array([e.p_a_b for e in new]), np.array([e.q_a_b for e in new]))
        for e, pi, qi in zip(new, p_inv, q_inv, strict=True):
            e.p_b_a, e.q_b_a = pi, qi

    def expire(self, now_ns: int) -> int:
        """Remove edges older than the timeout (age > timeout); returns how many were removed."""
        dead = [k for k, e in self.edges.items() if now_ns - e.stamp_ns > self.edge_timeout_ns]
        for k in dead:
            del self.edges[k]
        return len(dead)

    def live_edges(self, now_ns: int) -> list[Edge]:
        """Edges whose age is at most the timeout (not removed: :meth:`expire` does that)."""
        return [e for e in self.edges.values() if now_ns - e.stamp_ns <= self.edge_timeout_ns]

    def broad_phase(self, edges: Sequence[Edge], root: int | None = None) -> tuple[list[int], dict[int, int]]:
        """BFS from ``root`` (world by default): the visiting order and each reached vertex's level.

        Neighbours are visited in the order of the world file, so the order is deterministic.
        """
        neighbours = self._neighbours(edges)
        start = self.index[WORLD] if root is None else root
        level = {start: 0}
        order = [start]
        queue = deque([start])
        while queue:
            v = queue.popleft()
            for child in sorted(neighbours[v]):
                if child not in level:
                    level[child] = level[v] + 1
                    order.append(child)
                    queue.append(child)
        return order, level

    def dijkstra_phase(self, edges: Sequence[Edge], root: int | None = None) -> tuple[list[int], dict[int, float]]:
        """Shortest paths from ``root`` with each edge's variance (sigma^2) as its length.

        Variances add along a chain of independent transforms, so the distance of a vertex is the
        variance of its best chain: the paper's future work ("use the standard deviation information
        of the graph as distance ... Dijkstra").
        """
        best: dict[tuple[int, int], float] = {}
        for e in edges:
            k = (min(e.a, e.b), max(e.a, e.b))
            best[k] = min(best.get(k, np.inf), e.sigma_m**2)
        adj: list[list[tuple[int, float]]] = [[] for _ in self.names]
        for (a, b), w in best.items():
            adj[a].append((b, w))
            adj[b].append((a, w))
        start = self.index[WORLD] if root is None else root
        dist = {start: 0.0}
        order: list[int] = []
        heap = [(0.0, start)]
        done: set[int] = set()
        while heap:
            d, v = heapq.heappop(heap)
            if v in done:
                continue
            done.add(v)
            order.append(v)
            for u, w in adj[v]:
                nd = d + w
                if u not in done and nd < dist.get(u, np.inf):
                    dist[u] = nd
                    heapq.heappush(heap, (nd, u))
        return order, dist

    def _sigma(self, e: Edge, now_ns: int) -> float:
        if self.age_sigma_m_per_s <= 0.0:
            return e.sigma_m
        age_s = max(now_ns - e.stamp_ns, 0) / 1e9
        return float(np.hypot(e.sigma_m, age_s * self.age_sigma_m_per_s))

    def _neighbours(self, edges: Sequence[Edge]) -> list[set[int]]:
        neighbours: list[set[int]] = [set() for _ in self.names]
        for e in edges:
            neighbours[e.a].add(e.b)
            neighbours[e.b].add(e.a)
        return neighbours

    def evaluate(self, now_ns: int) -> GraphResult:
        """Expire old edges, then run the broad phase and the pose phase (eq. 2) from world.

        With the paper's method (``path="bfs"``) a vertex's candidates come from every live edge to
        a parent exactly one level lower; edges within a level (cycles such as the paper's A-B) and
        towards higher levels are ignored. With ``path="dijkstra"`` the candidates come from every
        neighbour whose best chain to world has a smaller variance, weighted by the variance of the
        whole chain, so a long precise chain can outvote a short noisy one.

        With ``relative=True``, each group of entities that has no path to world is evaluated from
        its first entity (in world-file order), and its poses are reported relative to that entity.
        """
        self.expire(now_ns)
        edges = list(self.edges.values())
        self._invert_new_edges(edges)
        world = self.index[WORLD]
        poses, order, levels = self._evaluate_from(edges, world, now_ns)
        reached = set(order)
        unreached = tuple(self.names[v] for v in range(len(self.names)) if v not in reached)
        relative: dict[str, dict[str, EntityPose]] = {}
        if self.relative:
            remaining = [v for v in range(len(self.names)) if v not in reached]
            while remaining:
                root = remaining[0]
                rel, rel_order, _ = self._evaluate_from(edges, root, now_ns)
                if len(rel_order) > 1:
                    relative[self.names[root]] = rel
                remaining = [v for v in remaining if v not in set(rel_order)]
        return GraphResult(
            poses=poses,
            order=tuple(self.names[v] for v in order),
            levels={self.names[v]: levels[v] for v in order},
            unreached=unreached,
            n_edges=len(edges),
            relative=relative,
        )

    def _evaluate_from(
        self, edges: list[Edge], root: int, now_ns: int
    ) -> tuple[dict[str, EntityPose], list[int], dict[int, int]]:
        """Poses of every vertex reachable from ``root``, in ``root``'s frame."""
        n = len(self.names)
        order, level = self.broad_phase(edges, root)
        if self.path == "dijkstra":
            d_order, dist = self.dijkstra_phase(edges, root)
            order = d_order

            def is_parent(u: int, v: int) -> bool:
                return dist[u] < dist[v]
        else:

            def is_parent(u: int, v: int) -> bool:
                return level[u] == level[v] - 1

        # A vertex's stage is one more than its deepest parent's, so that a whole stage can be
        # composed and fused in one batched call (for BFS the stage is the level).
        stage = {root: 0}
        cands_of: dict[int, list[tuple[int, NDArray[np.float64], NDArray[np.float64], float, int]]] = {}
        for e in edges:
            if e.a not in level or e.b not in level:
                continue
            if is_parent(e.a, e.b):
                cands_of.setdefault(e.b, []).append((e.a, e.p_a_b, e.q_a_b, self._sigma(e, now_ns), e.capture_time_us))
            elif is_parent(e.b, e.a):
                cands_of.setdefault(e.a, []).append((e.b, e.p_b_a, e.q_b_a, self._sigma(e, now_ns), e.capture_time_us))
        for v in order[1:]:
            stage[v] = 1 + max(stage[c[0]] for c in cands_of[v])

        p_world = np.zeros((n, 3))
        q_world = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        sigma = np.zeros(n)
        stamp_us = np.zeros(n, dtype=np.int64)
        count = np.zeros(n, dtype=np.intp)
        by_stage: dict[int, list[int]] = {}
        for v in order[1:]:
            by_stage.setdefault(stage[v], []).append(v)

        for st in sorted(by_stage):
            cands = [(c[0], v, *c[1:]) for v in by_stage[st] for c in cands_of[v]]
            m = len(cands)
            parent = np.fromiter((c[0] for c in cands), dtype=np.intp, count=m)
            child = np.fromiter((c[1] for c in cands), dtype=np.intp, count=m)
            p_pc = np.array([c[2] for c in cands])
            q_pc = np.array([c[3] for c in cands])
            s_edge = np.fromiter((c[4] for c in cands), dtype=float, count=m)
            t_edge = np.fromiter((c[5] for c in cands), dtype=np.int64, count=m)
            # eq. 2: each candidate is P_parent * T_parent_child
            p_cand, q_cand = geometry.compose_arrays(p_world[parent], q_world[parent], p_pc, q_pc)
            # The candidate's sigma carries its parent's: variances add along a chain.
            s_cand = np.sqrt(s_edge**2 + sigma[parent] ** 2)
            # eq. 6-7 per child, vectorised: w_i = sigma_min / sigma_i (squared for inverse variance).
            # The paper weighs by the sensor's sigma; Dijkstra weighs by the whole chain's.
            s_weigh = s_cand if self.path == "dijkstra" else s_edge
            s_min = np.full(n, np.inf)
            np.minimum.at(s_min, child, s_weigh)
            weights = s_min[child] / s_weigh
            if self.inverse_variance:
                weights = weights**2
            p_f, q_f, s_f, counts = fusion.fuse_groups(child, n, p_cand, q_cand, s_cand, weights)
            got = counts > 0
            p_world[got] = p_f[got]
            q_world[got] = q_f[got]
            sigma[got] = s_f[got]
            count[got] = counts[got]
            newest = np.zeros(n, dtype=np.int64)
            np.maximum.at(newest, child, np.maximum(t_edge, stamp_us[parent]))
            stamp_us[got] = newest[got]

        poses = {}
        for rank, v in enumerate(order):
            poses[self.names[v]] = EntityPose(
                name=self.names[v],
                p_world_m=p_world[v].copy(),
                q_world_xyzw=q_world[v].copy(),
                level=level[v],
                order=rank,
                n_observations=int(count[v]),
                sigma_m=float(sigma[v]),
                capture_time_us=int(stamp_us[v]),
                frame=self.names[root],
            )
        return poses, order, level
