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
    cov_a_b: NDArray[np.float64] | None = None  # 6x6, see core.covariance
    cov_b_a: NDArray[np.float64] | None = None  # of the inverse, filled in with it


@dataclass(frozen=True, slots=True)
class Candidate:
    """One edge's vote for an entity's pose (eq. 2: the parent's pose times the edge), for a filter.

    ``covariance`` is 6x6 in the convention of :mod:`atlas_onboard.core.covariance` (position in the
    frame of the result, small rotation about the entity's body axes), including the parent's.
    """

    entity: str
    key: EdgeKey
    stamp_ns: int
    capture_time_us: int
    p_m: NDArray[np.float64]
    q_xyzw: NDArray[np.float64]
    covariance: NDArray[np.float64]


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
        outlier_gate_sigma: float = 0.0,
        keep_candidates: bool = False,
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
        # Beyond the paper: a candidate farther than this many sigma from the consensus of the others
        # (or, with fewer than three, from the entity's last estimate) is left out. 0: off.
        self.outlier_gate_sigma = outlier_gate_sigma
        self.keep_candidates = keep_candidates
        self.edges: dict[EdgeKey, Edge] = {}
        # The last estimate of each entity per frame root, for the gate: (p, q, sigma, sigma_att, stamp).
        self._prior: dict[tuple[int, int], tuple[NDArray[np.float64], NDArray[np.float64], float, float, int]] = {}
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
        p = np.asarray(p_a_b, dtype=float)
        q = np.asarray(q_a_b_xyzw, dtype=float)
        q = q / np.linalg.norm(q)
        att = (
            covariance.attitude_sigma_rad(sigma_m, float(np.linalg.norm(p))) if sigma_att_rad is None else sigma_att_rad
        )
        cov = covariance.diagonal(float(sigma_m), float(att)) if cov_a_b is None else np.asarray(cov_a_b, dtype=float)
        # The inverse (for walking the edge backwards) is computed at evaluation, for all new edges at once.
        self.edges[key] = Edge(key, a, b, p, q, None, None, float(sigma_m), int(now_ns), int(capture_time_us), cov)

    def _invert_new_edges(self, edges: list[Edge]) -> None:
        new = [e for e in edges if e.p_b_a is None]
        if not new:
            return
        p_ab = np.array([e.p_a_b for e in new])
        q_ab = np.array([e.q_a_b for e in new])
        p_inv, q_inv = geometry.invert_arrays(p_ab, q_ab)
        J = covariance.inverse_jacobian(p_ab, Rotation.from_quat(q_ab).as_matrix())
        c_inv = covariance.transform(J, np.array([e.cov_a_b for e in new]))
        for e, pi, qi, ci in zip(new, p_inv, q_inv, c_inv, strict=True):
            e.p_b_a, e.q_b_a, e.cov_b_a = pi, qi, ci

    def expire(self, now_ns: int) -> int:
        """Remove edges older than the timeout (age > timeout); returns how many were removed."""
        dead = [k for k, e in self.edges.items() if now_ns - e.stamp_ns > self.edge_timeout_ns]
        for k in dead:
            del self.edges[k]
        return len(dead)

    def next_expiry_ns(self) -> int | None:
        """The first time at which an edge will have expired (its age exceeds the timeout), or None
        without edges: until then a new evaluation can only differ by the age of the edges."""
        if not self.edges:
            return None
        return min(e.stamp_ns for e in self.edges.values()) + self.edge_timeout_ns + 1

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
        cands: dict[str, list[Candidate]] | None = {} if self.keep_candidates else None
        poses, order, levels, gated = self._evaluate_from(edges, world, now_ns, cands)
        reached = set(order)
        unreached = tuple(self.names[v] for v in range(len(self.names)) if v not in reached)
        relative: dict[str, dict[str, EntityPose]] = {}
        if self.relative:
            remaining = [v for v in range(len(self.names)) if v not in reached]
            while remaining:
                root = remaining[0]
                rel, rel_order, _, g = self._evaluate_from(edges, root, now_ns)
                gated += g
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
            candidates=cands or {},
            gated=gated,
        )

    def _evaluate_from(
        self, edges: list[Edge], root: int, now_ns: int, out: dict[str, list[Candidate]] | None = None
    ) -> tuple[dict[str, EntityPose], list[int], dict[int, int], int]:
        """Poses of every vertex reachable from ``root``, in ``root``'s frame (and how many candidates
        the gate left out). ``out`` collects each entity's candidates when given."""
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
        cands_of: dict[int, list[tuple[int, NDArray[np.float64], NDArray[np.float64], float, Edge, NDArray]]] = {}
        for e in edges:
            if e.a not in level or e.b not in level:
                continue
            if is_parent(e.a, e.b):
                cands_of.setdefault(e.b, []).append((e.a, e.p_a_b, e.q_a_b, self._sigma(e, now_ns), e, e.cov_a_b))
            elif is_parent(e.b, e.a):
                cands_of.setdefault(e.a, []).append((e.b, e.p_b_a, e.q_b_a, self._sigma(e, now_ns), e, e.cov_b_a))
        for v in order[1:]:
            stage[v] = 1 + max(stage[c[0]] for c in cands_of[v])

        p_world = np.zeros((n, 3))
        q_world = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        cov_world = np.zeros((n, 6, 6))
        sigma = np.zeros(n)
        stamp_us = np.zeros(n, dtype=np.int64)
        count = np.zeros(n, dtype=np.intp)
        by_stage: dict[int, list[int]] = {}
        for v in order[1:]:
            by_stage.setdefault(stage[v], []).append(v)

        gated = 0
        for st in sorted(by_stage):
            cands = [(c[0], v, *c[1:]) for v in by_stage[st] for c in cands_of[v]]
            m = len(cands)
            parent = np.fromiter((c[0] for c in cands), dtype=np.intp, count=m)
            child = np.fromiter((c[1] for c in cands), dtype=np.intp, count=m)
            p_pc = np.array([c[2] for c in cands])
            q_pc = np.array([c[3] for c in cands])
            s_edge = np.fromiter((c[4] for c in cands), dtype=float, count=m)
            t_edge = np.fromiter((c[5].capture_time_us for c in cands), dtype=np.int64, count=m)
            c_edge = np.array([c[6] for c in cands])
            # eq. 2: each candidate is P_parent * T_parent_child
            p_cand, q_cand = geometry.compose_arrays(p_world[parent], q_world[parent], p_pc, q_pc)
            # The candidate's sigma carries its parent's: variances add along a chain.
            s_cand = np.sqrt(s_edge**2 + sigma[parent] ** 2)
            # Beyond the paper: the full 6x6 covariance along the chain (lever arms included).
            if self.age_sigma_m_per_s > 0.0:
                c_edge = c_edge.copy()
                grow = (s_edge**2 - np.fromiter((c[5].sigma_m for c in cands), dtype=float, count=m) ** 2).clip(0.0)
                c_edge[:, [0, 1, 2], [0, 1, 2]] += grow[:, None]
            R_wp = Rotation.from_quat(q_world[parent]).as_matrix()
            Jp, Je = covariance.compose_jacobians(R_wp, p_pc, Rotation.from_quat(q_pc).as_matrix())
            edge_term = covariance.transform(Je, c_edge)
            keep = np.ones(m, dtype=bool)
            if self.outlier_gate_sigma > 0.0:
                c_cand = covariance.transform(Jp, cov_world[parent]) + edge_term
                keep = self._gate(root, child, p_cand, q_cand, c_cand, now_ns)
                for c, k in zip(cands, keep, strict=True):
                    if not k and self._gated_stamp.get(c[5].key) != c[5].stamp_ns:
                        self._gated_stamp[c[5].key] = c[5].stamp_ns
                        self.gated_total += 1
                gated += int(m - keep.sum())
            if out is not None:
                c_all = covariance.transform(Jp, cov_world[parent]) + edge_term
                for i in np.flatnonzero(keep):
                    e = cands[i][5]
                    out.setdefault(self.names[child[i]], []).append(
                        Candidate(
                            self.names[child[i]], e.key, e.stamp_ns, int(max(t_edge[i], stamp_us[parent[i]])),
                            p_cand[i], q_cand[i], c_all[i],
                        )
                    )  # fmt: skip
            # A child whose every candidate was gated keeps its last estimate (not re-sent: same stamp).
            for v in set(child[~keep].tolist()) - set(child[keep].tolist()):
                prior = self._prior[(root, v)]
                p_world[v], q_world[v], sigma[v] = prior[0], prior[1], prior[2]
                cov_world[v] = covariance.diagonal(prior[2], prior[3])
                stamp_us[v] = prior[5]
            parent, child, p_cand, q_cand = parent[keep], child[keep], p_cand[keep], q_cand[keep]
            s_edge, s_cand, t_edge, Jp, edge_term = s_edge[keep], s_cand[keep], t_edge[keep], Jp[keep], edge_term[keep]
            if len(child) == 0:
                continue
            # eq. 6-7 per child, vectorised: w_i = sigma_min / sigma_i (squared for inverse variance).
            # The paper weighs by the sensor's sigma; Dijkstra weighs by the whole chain's.
            s_weigh = s_cand if self.path == "dijkstra" else s_edge
            s_min = np.full(n, np.inf)
            np.minimum.at(s_min, child, s_weigh)
            weights = s_min[child] / s_weigh
            if self.inverse_variance:
                weights = weights**2
            p_f, q_f, s_f, counts = fusion.fuse_groups(child, n, p_cand, q_cand, s_cand, weights)
            c_f = covariance.fuse(child, parent, n, weights, Jp, cov_world, edge_term)
            got = counts > 0
            p_world[got] = p_f[got]
            q_world[got] = q_f[got]
            sigma[got] = s_f[got]
            cov_world[got] = c_f[got]
            count[got] = counts[got]
            newest = np.zeros(n, dtype=np.int64)
            np.maximum.at(newest, child, np.maximum(t_edge, stamp_us[parent]))
            stamp_us[got] = newest[got]
            if self.outlier_gate_sigma > 0.0:
                for v in np.flatnonzero(got):
                    att = float(np.sqrt(max(np.trace(c_f[v][3:, 3:]) / 3.0, 0.0)))
                    self._prior[(root, int(v))] = (
                        p_f[v].copy(),
                        q_f[v].copy(),
                        float(s_f[v]),
                        att,
                        now_ns,
                        int(newest[v]),
                    )

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
                covariance=cov_world[v].copy(),
            )
        return poses, order, level, gated

    def _gate(
        self,
        root: int,
        child: NDArray[np.intp],
        p: NDArray[np.float64],
        q: NDArray[np.float64],
        cov: NDArray[np.float64],
        now_ns: int,
    ) -> NDArray[np.bool_]:
        """Which candidates agree with the consensus of their entity's candidates.

        With three or more candidates the reference is their median (position per axis; orientation:
        the candidate nearest to all others), which one wrong candidate cannot move. With fewer, the
        reference is the entity's last estimate if it is younger than the edge timeout, widened by
        what the entity may have moved since. A candidate is out when its position or attitude is
        more than ``outlier_gate_sigma`` standard deviations (its own and the reference's) away.
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
            rot = Rotation.from_quat(q[idx])
            if len(idx) >= 3:
                ref_p = np.median(p[idx], axis=0)
                angles = np.array([(rot[i].inv() * rot).magnitude().sum() for i in range(len(idx))])
                ref_q = rot[int(np.argmin(angles))]
                ref_s, ref_a, slack_p, slack_a = 0.0, 0.0, 0.0, 0.0
            else:
                prior = self._prior.get((root, int(v)))
                if prior is None or now_ns - prior[4] > self.edge_timeout_ns:
                    continue
                age_s = (now_ns - prior[4]) / 1e9
                ref_p, ref_q, ref_s, ref_a = prior[0], Rotation.from_quat(prior[1]), prior[2], prior[3]
                slack_p, slack_a = MAX_SPEED_M_S * age_s, MAX_RATE_RAD_S * age_s
            d_p = np.linalg.norm(p[idx] - ref_p, axis=1)
            d_a = (ref_q.inv() * rot).magnitude()
            ok = (d_p <= k * np.hypot(s_pos[idx], ref_s) + slack_p) & (d_a <= k * np.hypot(s_att[idx], ref_a) + slack_a)
            if len(idx) >= 3:
                if ok.sum() * 2 >= len(idx):
                    keep[idx] = ok
            elif len(idx) == 2 and not ok.any():
                # Both contradict the last estimate: if they agree with each other, it is the estimate
                # that is out of date (kept both); if not, nothing can be trusted (both out).
                d2 = float(np.linalg.norm(p[idx[0]] - p[idx[1]]))
                a2 = float((rot[0].inv() * rot[1]).magnitude())
                agree = d2 <= k * np.hypot(s_pos[idx[0]], s_pos[idx[1]]) and a2 <= k * np.hypot(*s_att[idx])
                keep[idx] = agree
            else:
                keep[idx] = ok
        return keep
