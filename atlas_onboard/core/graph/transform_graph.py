"""The transform graph of the paper's section 3.2: static vertices, expiring bidirectional edges,
a broad phase (BFS levels from ``world``) and a pose phase (fusion of parents one level lower).

Vertices are the entities of the world file; edges are observations keyed by (sensor id, marker id),
each holding ``T_a_b`` (the observed entity b in the observer entity a) and its inverse, so it can be
walked both ways. Time is passed in as integer nanoseconds of the caller's monotonic clock: the graph
never reads a clock, and expiry is exact (an edge whose age equals ``edge_timeout`` is still live, one
nanosecond later it is gone: the paper removes an edge when its age *exceeds* the timeout).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core import covariance
from atlas_onboard.core.graph.candidates import PoseOptions
from atlas_onboard.core.graph.edges import WORLD, Edge, EdgeKey, EdgeStore
from atlas_onboard.core.graph.gate import ConsensusGate
from atlas_onboard.core.graph.paths import PATHS, Planner, bfs, dijkstra
from atlas_onboard.core.graph.pose import FrameEvaluation, PosePhase
from atlas_onboard.core.graph.relative import relative_groups
from atlas_onboard.core.graph.result import Candidate, EntityPose, GraphResult
from atlas_onboard.core.graph.timing import WINDOW_US
from atlas_onboard.errors import GeometryError


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
        max_speed_m_s: float = 0.0,
        align: bool = False,
        max_relayed_sigma_m: float = 0.0,
    ) -> None:
        """``path``: ``bfs`` (the paper) or ``dijkstra`` (see :meth:`evaluate`). ``inverse_variance``:
        weights from each candidate's covariance, squared. ``relative``: poses of the groups without
        a path to world, in their first entity's frame. An edge's information ages (the entities may
        have moved since it arrived): with ``age_sigma_m_per_s`` > 0 an edge of age a (s) counts
        with sigma sqrt(sigma^2 + (a * age_sigma)^2), so fresh observations outvote stale ones; with
        ``age_sigma_rad_per_s`` its attitude covariance grows likewise (0: the paper's method, every
        live edge counts as new). ``outlier_gate_sigma`` > 0: the consensus gate
        (:mod:`~atlas_onboard.core.graph.gate`), whose anchor is the candidates of the node's own
        sensors (``anchor_sensors``). ``max_speed_m_s`` > 0: the speed bound on candidates that rest on
        peers' work (:meth:`~atlas_onboard.core.graph.gate.ConsensusGate.too_fast`). ``keep_candidates``:
        the result lists every candidate. ``align``: a parent that is not the root is taken at its child's
        capture time, interpolated or extrapolated from its recent poses
        (:mod:`~atlas_onboard.core.graph.timing`), its covariance grown by that step;
        ``max_relayed_sigma_m`` > 0: a candidate through such a parent whose position sigma (largest axis)
        exceeds it is left out (a child left with none keeps its last pose, not re-sent, for at most the
        edge timeout or 0.3 s of capture time, then none)."""
        names = list(entity_names)
        if WORLD not in names:
            names.insert(0, WORLD)
        if len(set(names)) != len(names):
            raise GeometryError(f"expected unique entity names, got {names}")
        if edge_timeout_ns <= 0:
            raise GeometryError(f"expected a positive edge timeout, got {edge_timeout_ns} ns")
        if path not in PATHS:
            raise GeometryError(f"expected path 'bfs' or 'dijkstra', got {path!r}")
        self.names: tuple[str, ...] = tuple(names)
        self.index: dict[str, int] = {n: i for i, n in enumerate(names)}
        self.edge_timeout_ns = int(edge_timeout_ns)
        self.relative = relative
        self.anchor_sensors = frozenset(anchor_sensors)
        self.keep_candidates = keep_candidates
        self._store = EdgeStore()
        self._planner = Planner(len(names), path)
        self._gate = ConsensusGate(outlier_gate_sigma, self.edge_timeout_ns, max_speed_m_s)
        options = PoseOptions(
            inverse_variance,
            path,
            age_sigma_m_per_s,
            age_sigma_rad_per_s,
            align,
            max_relayed_sigma_m,
            min(self.edge_timeout_ns // 1000, WINDOW_US),
        )
        self._pose = PosePhase(self.names, options, self._gate, own_known=bool(self.anchor_sensors))
        # For a targeted evaluation: which entities' edges changed (came, were refreshed or went)
        # since the last full evaluation, and whether there has been one.
        self._touched = np.zeros(len(names), dtype=bool)
        self._evaluated = False
        # Each camera's newest view of each pair of entities: (capture time, the edges of that image).
        self._views: dict[tuple[object, int, int], tuple[int, list[EdgeKey]]] = {}
        # The older edges of the view last updated, removed (see update_edge) unless the next updates
        # refresh them from the same image: an image's several views of an entity then keep their rows,
        # and the graph its shape (and its kept plan).
        self._stale: tuple[tuple[object, int, int], int, list[EdgeKey]] | None = None

    # --- settings and counters ----------------------------------------------------------------------

    @property
    def path(self) -> str:
        return self._pose.options.path

    @path.setter
    def path(self, path: str) -> None:
        if path not in PATHS:
            raise GeometryError(f"expected path 'bfs' or 'dijkstra', got {path!r}")
        self._planner = Planner(len(self.names), path)
        self._pose.options = dataclasses.replace(self._pose.options, path=path)

    @property
    def inverse_variance(self) -> bool:
        return self._pose.options.inverse_variance

    @property
    def age_sigma_m_per_s(self) -> float:
        return self._pose.options.age_sigma_m_per_s

    @property
    def age_sigma_rad_per_s(self) -> float:
        return self._pose.options.age_sigma_rad_per_s

    @property
    def outlier_gate_sigma(self) -> float:
        return self._gate.k_sigma

    @property
    def gated_total(self) -> int:
        """Distinct edge observations the gate rejected as outliers (counted once each)."""
        return self._gate.rejected_total

    @property
    def too_fast_total(self) -> int:
        """Distinct edge observations the speed bound refused (counted once each)."""
        return self._gate.too_fast_total

    # --- edges --------------------------------------------------------------------------------------

    @property
    def edges(self) -> dict[EdgeKey, Edge]:
        """The edges by key (read-only: change them with :meth:`update_edge`)."""
        self._drop_stale()
        return self._store.edges

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
        edge = Edge(key, a, b, p, q, float(sigma_m), int(now_ns), int(capture_time_us), cov)
        view = (key[0], a, b)
        stale = self._stale
        refresh = stale is not None and stale[0] == view and stale[1] == capture_time_us and key in stale[2]
        if refresh:
            stale[2].remove(key)  # the same image's view of it: the edge is refreshed in its row
        else:
            self._drop_stale()
        replaced = self._store.edges.get(key)
        if replaced is not None:  # the key may have joined other entities: they lose that edge
            self._touched[replaced.a] = self._touched[replaced.b] = True
        self._store.put(edge, anchored=key[0] in self.anchor_sensors)
        self._touched[a] = self._touched[b] = True
        # A camera's newer image of an entity replaces its older views of it through other markers: the
        # joint solve reports an entity through one of its markers, which changes from image to image,
        # and the stale edge would otherwise be fused as new (without ageing) until it expires. They go
        # before anything else reads or changes the graph (:meth:`_drop_stale`): where the next updates
        # are the same image's views of them, they stay, refreshed.
        held = self._views.get(view)
        if held is None or capture_time_us > held[0]:
            older = [old for old in held[1] if old != key] if held is not None else []
            if older:
                self._stale = (view, int(capture_time_us), older)
            self._views[view] = (int(capture_time_us), [key])
        elif capture_time_us == held[0] and key not in held[1]:
            held[1].append(key)

    def _drop_stale(self) -> None:
        """Remove the older edges of the view last updated that its image has not refreshed (see
        :meth:`update_edge`), in the order it held them."""
        stale, self._stale = self._stale, None
        if stale is not None:
            for old in stale[2]:
                self._store.remove(old, displaced=True)

    def clear(self) -> None:
        """Forget every edge."""
        self._drop_stale()
        self._touched[[e.a for e in self._store.edges.values()]] = True
        self._touched[[e.b for e in self._store.edges.values()]] = True
        self._store.clear()
        self._views.clear()
        self._pose.motion.clear()
        self._pose.waiting.clear()

    def expire(self, now_ns: int) -> int:
        """Remove edges older than the timeout (age > timeout); returns how many were removed."""
        self._drop_stale()
        ends = self._store.expire(now_ns, self.edge_timeout_ns)
        if ends.size:
            self._touched[ends] = True
        return ends.size // 2

    def next_expiry_ns(self) -> int | None:
        """The first time at which an edge will have expired (its age exceeds the timeout), or None
        without edges: until then a new evaluation can only differ by the age of the edges."""
        self._drop_stale()
        return self._store.next_expiry_ns(self.edge_timeout_ns)

    def live_edges(self, now_ns: int) -> list[Edge]:
        """Edges whose age is at most the timeout (not removed: :meth:`expire` does that)."""
        self._drop_stale()
        return [e for e in self._store.edges.values() if now_ns - e.stamp_ns <= self.edge_timeout_ns]

    def is_superseded(self, key: EdgeKey, arrival_ns: int, capture_time_us: int) -> bool:
        """Whether an observation of edge ``key`` that arrived at ``arrival_ns`` (on the clock of
        :meth:`update_edge`'s ``now_ns``) from an image captured at ``capture_time_us`` would replace
        a newer one: the edge holds an observation that arrived later, or one of a later image (a
        datagram overtaken on the way). Such an observation is dropped, not inserted."""
        self._drop_stale()
        return self._store.superseded(key, arrival_ns, capture_time_us)

    # --- phases -------------------------------------------------------------------------------------

    def broad_phase(self, root: int | None = None) -> tuple[list[int], dict[int, int]]:
        """BFS over the current edges from ``root`` (world by default): the visiting order and each
        reached vertex's level."""
        self._drop_stale()
        store = self._store
        slots = store.live_slots()
        order, level = bfs(store.a[slots], store.b[slots], self._root(root), len(self.names))
        return order.tolist(), {int(v): int(level[v]) for v in order}

    def dijkstra_phase(self, root: int | None = None) -> tuple[list[int], dict[int, float]]:
        """Shortest paths over the current edges from ``root`` with each edge's variance (sigma^2)
        as its length: the visiting order and each reached vertex's distance."""
        self._drop_stale()
        store = self._store
        slots = store.live_slots()
        order, dist = dijkstra(store.a[slots], store.b[slots], store.sigma[slots], self._root(root), len(self.names))
        return order.tolist(), {int(v): float(dist[v]) for v in order}

    def forget_plans(self) -> None:
        """Forget the kept evaluation plans, as if the graph's shape had changed (for benchmarks:
        the results are the same, only the next evaluation's cost differs)."""
        self._planner.clear()

    def evaluate(self, now_ns: int, target: str | None = None, previous: GraphResult | None = None) -> GraphResult:
        """Expire old edges, then run the broad phase and the pose phase (eq. 2) from world.

        With ``target``, the pose phase computes only what ``target``'s pose depends on: every entity
        of a lower stage (level), and of its own stage only ``target`` (the node's own pose, when
        others can wait). Its pose is the one a full evaluation gives (tested); the result says
        ``complete=False``. Its ``poses`` hold the entities computed and, with ``previous`` (the
        result of this graph's last full evaluation, or one made from it like this one), every
        other entity's pose in ``previous`` (and its relative poses): ``current`` says whether those
        are what a full evaluation would give now, which holds when nothing they rest on has changed
        since the last full evaluation (BFS paths, no edge ageing, no edge changed but between
        ``target`` and world, ``target`` the parent of none; the consensus gate's memory is not
        considered: an entity whose candidates it left out may be judged anew once its last estimate
        is older than the edge timeout). A target with no path to world gets the full evaluation
        (relative poses included).

        With the paper's method (``path="bfs"``) a vertex's candidates come from every live edge to
        a parent exactly one level lower; edges within a level (cycles such as the paper's A-B) and
        towards higher levels are ignored. With ``path="dijkstra"`` the candidates come from every
        neighbour whose best chain to world has a smaller variance, weighted by the variance of the
        whole chain, so a long precise chain can outvote a short noisy one.

        With ``relative=True``, each group of entities that has no path to world is evaluated from
        its first entity (in world-file order), and its poses are reported relative to that entity.
        """
        self.expire(now_ns)
        slots = self._store.live_slots()
        world = self.index[WORLD]
        cands: dict[str, list[Candidate]] | None = {} if self.keep_candidates else None
        goal = self.index[target] if target is not None else None
        frame = self._evaluate_from(slots, world, now_ns, cands, goal)
        if frame.too_fast and self._restore(frame.too_fast, now_ns):
            # A newer observation refused as too fast had pushed out a view that may be the real one.
            slots = self._store.live_slots()
            cands = {} if self.keep_candidates else None
            frame = self._evaluate_from(slots, world, now_ns, cands, goal)
        reached = set(frame.order)
        if goal is not None and goal not in reached:
            goal = None  # _evaluate_from has evaluated everything: the relative poses follow
        unreached = [v for v in range(len(self.names)) if v not in reached]
        relative: dict[str, dict[str, EntityPose]] = {}
        gated = frame.gated
        if self.relative:  # with a reached target too: the gate's memory follows every evaluation
            relative, rel_gated = relative_groups(
                self.names, unreached, lambda root: self._evaluate_from(slots, root, now_ns)
            )
            gated += rel_gated
        order = tuple(self.names[v] for v in frame.order)
        poses, current = frame.poses, True
        if goal is None:
            self._touched[:] = False
            self._evaluated = True
        elif previous is None:
            current = False
        else:
            poses, relative, current = self._with_previous(order, goal, frame, previous)
        return GraphResult(
            poses=poses,
            order=order,
            levels={self.names[v]: lv for v, lv in frame.levels.items()},
            unreached=tuple(self.names[v] for v in unreached),
            n_edges=len(slots),
            relative=relative,
            candidates=cands or {},
            gated=gated,
            complete=goal is None,
            current=current,
        )

    # --- internals ----------------------------------------------------------------------------------

    def _root(self, root: int | None) -> int:
        return self.index[WORLD] if root is None else root

    def _restore(self, refused: tuple[EdgeKey, ...], now_ns: int) -> bool:
        """Put back what the refused observations displaced (:meth:`EdgeStore.restore`)."""
        back = False
        for key in refused:
            edge = self._store.edges.get(key)
            if edge is not None and self._store.restore(key, now_ns, self.edge_timeout_ns):
                back = True
                self._touched[edge.a] = self._touched[edge.b] = True
        return back

    def _evaluate_from(
        self,
        slots: NDArray[np.intp],
        root: int,
        now_ns: int,
        out: dict[str, list[Candidate]] | None = None,
        goal: int | None = None,
    ) -> FrameEvaluation:
        """The broad phase (kept plan or a new one) and the pose phase from ``root``."""
        plan = self._planner.plan(self._store, slots, root, goal)
        self._store.invert_new(plan.row[plan.direction == 1])  # only the edges walked backwards need it
        return self._pose.run(self._store, plan, root, now_ns, out, goal)

    def _with_previous(
        self, order: tuple[str, ...], goal: int, frame: FrameEvaluation, previous: GraphResult
    ) -> tuple[dict[str, EntityPose], dict[str, dict[str, EntityPose]], bool]:
        """A targeted evaluation's poses completed with ``previous``'s poses of the other entities,
        ``previous``'s relative poses, and whether those are still current (see :meth:`evaluate`)."""
        known, computed = previous.poses, frame.poses
        poses = {n: computed[n] if n in computed else known[n] for n in order if n in computed or n in known}
        others = self._touched.copy()
        others[[self.index[WORLD], goal]] = False
        options = self._pose.options
        current = (
            self._evaluated
            and options.path == "bfs"
            and not options.ageing
            and not others.any()
            and not frame.goal_is_parent
        )
        return poses, previous.relative, current
