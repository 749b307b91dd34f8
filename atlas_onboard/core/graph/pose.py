"""The pose phase (the paper's section 3.2, eq. 2 and 4-7): every vertex reached from a root gets the
weighted mean of its candidates, each candidate its parent's fused pose times an edge.

It runs a :class:`~atlas_onboard.core.graph.paths.Plan` stage by stage (a stage's parents all lie in
lower stages), each stage in a few batched array operations, in these steps: the edges' terms
(:func:`_edge_terms`, aged), the candidates (:func:`_compose`, eq. 2, with their covariance), the
gate (:meth:`PosePhase._gate`), and the fusion (:meth:`PosePhase._fuse`, eq. 4-7).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core import covariance, fusion, geometry
from atlas_onboard.core.graph.edges import EdgeKey, EdgeStore
from atlas_onboard.core.graph.gate import ConsensusGate, GateInput, PriorEstimate, Verdict
from atlas_onboard.core.graph.paths import Plan
from atlas_onboard.core.graph.result import Candidate, EntityPose
from atlas_onboard.core.graph.timing import MotionHistory, Parents, Sample


@dataclass(frozen=True, slots=True)
class PoseOptions:
    """How candidates are weighted and aged (see :class:`TransformGraph`)."""

    inverse_variance: bool = False
    path: str = "bfs"
    age_sigma_m_per_s: float = 0.0
    age_sigma_rad_per_s: float = 0.0
    # A parent that is not the root is taken at its child's capture time (:mod:`.timing`).
    align: bool = False
    # A candidate through such a parent whose position sigma (largest axis) exceeds this is left out
    # (0: no limit): a leader with no fresh view cannot place its follower.
    max_relayed_sigma_m: float = 0.0
    hold_us: int = 250_000  # how long a child with no usable candidate keeps its last pose (capture time)

    @property
    def ageing(self) -> bool:
        return self.age_sigma_m_per_s > 0.0 or self.age_sigma_rad_per_s > 0.0


@dataclass(slots=True)
class Vertices:
    """Every vertex's estimate so far, in the root's frame, indexed by vertex: position ``p`` (n, 3),
    orientation ``q`` (n, 4) xyzw, covariance ``cov`` (n, 6, 6), position ``sigma`` (n,) m, the
    capture time of its newest observation ``stamp_us`` (n,), its number of candidates ``count``,
    whether one of them is a direct view of the root by the node's own cameras ``own`` (n,)."""

    p: NDArray[np.float64]
    q: NDArray[np.float64]
    cov: NDArray[np.float64]
    sigma: NDArray[np.float64]
    stamp_us: NDArray[np.int64]
    count: NDArray[np.intp]
    own: NDArray[np.bool_]
    lost: NDArray[np.bool_]  # no candidate left (see PosePhase._compose_aligned): no pose

    @classmethod
    def at_root(cls, n: int) -> Vertices:
        """Identity everywhere, exact: the root's pose in its own frame (the rest is overwritten)."""
        q = np.zeros((n, 4))
        q[:, 3] = 1.0
        return cls(np.zeros((n, 3)), q, np.zeros((n, 6, 6)), np.zeros(n), np.zeros(n, dtype=np.int64),
                   np.zeros(n, dtype=np.intp), np.zeros(n, dtype=bool), np.zeros(n, dtype=bool))  # fmt: skip


@dataclass(slots=True)
class StageEdges:
    """Edges as walked (parent -> child), shapes (N, ...): edge ``row``, ``parent``, ``child``, the
    edge's ``p`` and ``q`` (xyzw), its ``sigma`` (m) and 6x6 ``cov``, both aged, and the
    ``capture_us`` of its image. Made once per evaluation for every candidate of the plan, then
    sliced by stage (:meth:`stage`: views, no copies)."""

    row: NDArray[np.intp]
    parent: NDArray[np.intp]
    child: NDArray[np.intp]
    p: NDArray[np.float64]
    q: NDArray[np.float64]
    sigma: NDArray[np.float64]
    cov: NDArray[np.float64]
    capture_us: NDArray[np.int64]

    def stage(self, sel: slice | NDArray[np.bool_]) -> StageEdges:
        """The edges at ``sel``: a stage's slice (views), or a mask (copies)."""
        return StageEdges(
            self.row[sel], self.parent[sel], self.child[sel], self.p[sel], self.q[sel], self.sigma[sel],
            self.cov[sel], self.capture_us[sel],
        )  # fmt: skip


@dataclass(slots=True)
class StageCandidates:
    """One stage's candidates (eq. 2), shapes (N, ...): edge ``row``, ``parent`` and ``child``; the
    edge parent -> child (``p_pc``, ``q_pc``, its sigma ``s_edge`` aged, its covariance ``c_edge``
    aged); the candidate in the root's frame (``p``, ``q``, sigma ``s`` along the chain, capture
    time ``capture_us`` of its newest part); the covariance's parts: ``Jp`` (None when the parent
    is the root) and ``edge_term`` (the edge's covariance carried into the root's frame)."""

    row: NDArray[np.intp]
    parent: NDArray[np.intp]
    child: NDArray[np.intp]
    p_pc: NDArray[np.float64]
    q_pc: NDArray[np.float64]
    s_edge: NDArray[np.float64]
    c_edge: NDArray[np.float64]
    p: NDArray[np.float64]
    q: NDArray[np.float64]
    s: NDArray[np.float64]
    capture_us: NDArray[np.int64]
    Jp: NDArray[np.float64] | None
    edge_term: NDArray[np.float64]
    # Per candidate, its parent's covariance when the parent was taken at the candidate's capture
    # time (:mod:`.timing`): then each candidate has its own parent term. None: the vertex's.
    c_parent: NDArray[np.float64] | None = None

    def covariance(self, cov_parent: NDArray[np.float64] | None) -> NDArray[np.float64]:
        """Each candidate's full 6x6 covariance, the parent's included (``cov_parent``: per vertex)."""
        if self.Jp is None:
            return self.edge_term
        if self.c_parent is not None:
            return covariance.transform(self.Jp, self.c_parent) + self.edge_term
        assert cov_parent is not None
        return covariance.transform(self.Jp, cov_parent[self.parent]) + self.edge_term

    def select(self, keep: NDArray[np.bool_]) -> StageCandidates:
        Jp = None if self.Jp is None else self.Jp[keep]
        c_parent = None if self.c_parent is None else self.c_parent[keep]
        return StageCandidates(
            self.row[keep], self.parent[keep], self.child[keep], self.p_pc[keep], self.q_pc[keep],
            self.s_edge[keep], self.c_edge[keep], self.p[keep], self.q[keep], self.s[keep],
            self.capture_us[keep], Jp, self.edge_term[keep], c_parent,
        )  # fmt: skip


@dataclass(frozen=True, slots=True)
class FrameEvaluation:
    """The pose phase from one root: the poses (in the root's frame), the visiting order and levels
    (vertex indices), how many candidates the gate left out, whether the goal (if any) is the
    parent of some candidate (then other entities' poses rest on it), and the edges whose
    observations the speed bound refused."""

    poses: dict[str, EntityPose]
    order: list[int]
    levels: dict[int, int]
    gated: int
    goal_is_parent: bool
    too_fast: tuple[EdgeKey, ...] = ()


class PosePhase:
    """The pose phase of one graph: its vertex names, options and gate. ``own_known``: the graph knows
    which sensors are the node's own (then each pose says whether it rests on their views)."""

    def __init__(
        self, names: tuple[str, ...], options: PoseOptions, gate: ConsensusGate, own_known: bool = False
    ) -> None:
        self.names = names
        self.options = options
        self.gate = gate
        self.own_known = own_known
        self._too_fast: list[EdgeKey] = []  # this run's edges refused by the speed bound
        self.motion = MotionHistory()

    def run(
        self,
        store: EdgeStore,
        plan: Plan,
        root: int,
        now_ns: int,
        out: dict[str, list[Candidate]] | None = None,
        goal: int | None = None,
    ) -> FrameEvaluation:
        """Poses of every vertex of ``plan`` (made from ``root``, with ``goal`` if given), in
        ``root``'s frame. ``out`` collects each entity's candidates when given. With ``goal`` (if
        reached), only the vertices of lower stages and ``goal`` itself get a pose."""
        vx = Vertices.at_root(len(self.names))
        edges = _edge_terms(store, plan, self.options)
        gated = 0
        self._too_fast: list[EdgeKey] = []
        for sel, runs, from_root in zip(plan.stages, plan.runs, plan.from_root, strict=True):
            stage = edges.stage(sel)
            if from_root or not self.options.align:
                cands = _compose(vx, stage, from_root)
            else:
                cands = self._compose_aligned(vx, stage, root)
                if cands is None:
                    continue
                runs = covariance.runs_by_parent(cands.child, cands.parent)
            anchored = store.anchored[cands.row] & (cands.parent == root)
            keep = None
            if self.gate.enabled:
                keep = self._gate(store, cands, vx, root, now_ns, anchored)
                gated += int(keep.size - keep.sum())
            if out is not None:
                self._collect(out, store, cands, vx, root, keep)
            if keep is not None and not keep.all():
                self._hold_rejected(vx, cands.child, keep, root)
                cands = cands.select(keep)
                anchored = anchored[keep]
                if len(cands.child) == 0:
                    continue
                runs = covariance.runs_by_parent(cands.child, cands.parent)
            self._fuse(vx, cands, runs, root, now_ns, store.stamp[cands.row])
            if self.own_known:
                vx.own[runs[0].ids] = np.logical_or.reduceat(anchored, runs[0].starts)
        order, level = plan.order.tolist(), plan.level.tolist()
        levels = {v: level[v] for v in order}
        poses = self._poses(vx, plan, root, goal)
        return FrameEvaluation(poses, order, levels, gated, plan.goal_is_parent, tuple(self._too_fast))

    def _compose_aligned(self, vx: Vertices, e: StageEdges, root: int) -> StageCandidates | None:
        """A stage's candidates with each parent taken at the candidate's capture time (:mod:`.timing`).
        Left out: those whose parent has no pose, and those whose position sigma (largest axis)
        passes ``max_relayed_sigma_m``. A child left with none keeps its last pose (its stamp
        unchanged: not sent again) for at most ``hold_us`` of capture time, then has none (lost).
        None when no candidate is left."""
        ok = ~vx.lost[e.parent]
        if not ok.all():
            vx.lost[np.setdiff1d(e.child[~ok], e.child[ok])] = True
            e = e.stage(ok)
            if len(e.child) == 0:
                return None
        age = (self.options.age_sigma_m_per_s, self.options.age_sigma_rad_per_s)
        parents = self.motion.parents(root, e.parent, e.capture_us, e.p, vx.p, vx.q, vx.cov, vx.stamp_us, age)
        c = _compose(vx, e, False, parents)
        limit = self.options.max_relayed_sigma_m
        if limit <= 0.0:
            return c
        keep = np.linalg.eigvalsh(c.covariance(None)[:, :3, :3])[:, -1] <= limit**2
        if keep.all():
            return c
        for v in np.setdiff1d(c.child[~keep], c.child[keep]).tolist():
            held = self.motion.newest(root, v)
            newest = int(c.capture_us[c.child == v].max())
            if held is not None and newest - held.t_us <= self.options.hold_us:
                vx.p[v], vx.q[v], vx.cov[v], vx.stamp_us[v] = held.p, held.q, held.cov, held.t_us
                vx.sigma[v] = float(np.sqrt(np.trace(held.cov[:3, :3]) / 3.0))
                vx.count[v] = 1
            else:
                vx.lost[v] = True
        return c.select(keep) if keep.any() else None

    def _gate(
        self, store: EdgeStore, c: StageCandidates, vx: Vertices, root: int, now_ns: int, anchored: NDArray[np.bool_]
    ) -> NDArray[np.bool_]:
        """The gate's verdict on a stage's candidates; counts the rejected edge observations.
        ``anchored``: the own cameras' direct views of the root's markers (through another entity, a
        candidate also rests on that entity's estimate: a peer's work)."""
        s_weigh = c.s_edge if anchored.all() else weigh_sigma(self.options, c, vx)  # (unused when all are own)
        cov = gate_covariance(c, vx, s_weigh, anchored, self.options.path == "dijkstra")
        gate_in = GateInput(c.child, c.p, c.q, cov, c.capture_us, anchored, store.stamp[c.row])
        verdict: Verdict = self.gate.verdict(root, now_ns, gate_in)
        for fast in (False, True):
            out = c.row[~verdict.keep & (verdict.too_fast == fast)].tolist()
            self.gate.count([store.keys[slot] for slot in out], [int(store.stamp[slot]) for slot in out], fast)
        self._too_fast += [key for slot in c.row[verdict.too_fast].tolist() if (key := store.keys[slot]) is not None]
        return verdict.keep

    def _collect(
        self,
        out: dict[str, list[Candidate]],
        store: EdgeStore,
        c: StageCandidates,
        vx: Vertices,
        root: int,
        keep: NDArray[np.bool_] | None,
    ) -> None:
        """Each kept candidate as a :class:`Candidate`, for a filter that fuses them itself."""
        names = self.names
        c_full = c.covariance(vx.cov)
        for i in range(len(c.child)) if keep is None else np.flatnonzero(keep):
            slot = int(c.row[i])
            via = None if c.parent[i] == root else names[c.parent[i]]
            out.setdefault(names[c.child[i]], []).append(
                Candidate(
                    names[c.child[i]], store.keys[slot], int(store.stamp[slot]),
                    int(c.capture_us[i]), c.p[i], c.q[i], c_full[i],
                    via, c.p_pc[i], c.q_pc[i], c.c_edge[i], c.c_parent is not None,
                )
            )  # fmt: skip

    def _hold_rejected(self, vx: Vertices, child: NDArray[np.intp], keep: NDArray[np.bool_], root: int) -> None:
        """A child whose every candidate was gated keeps its last estimate (not re-sent: same stamp)."""
        for v in set(child[~keep].tolist()) - set(child[keep].tolist()):
            prior = self.gate.priors[(root, v)]
            vx.p[v], vx.q[v], vx.sigma[v] = prior.p_m, prior.q_xyzw, prior.sigma_m
            vx.cov[v] = covariance.diagonal(prior.sigma_m, prior.sigma_att_rad)
            vx.stamp_us[v] = prior.capture_time_us
            vx.own[v] = False

    def _fuse(
        self,
        vx: Vertices,
        c: StageCandidates,
        runs: tuple[fusion.Runs, fusion.Runs],
        root: int,
        now_ns: int,
        arrival_ns: NDArray[np.int64],
    ) -> None:
        """eq. 4-7 per child, vectorised: w_i = sigma_min / sigma_i (squared for inverse variance).
        The paper weighs by the sensor's sigma; Dijkstra weighs by the whole chain's."""
        kids, pairs = runs
        s_weigh = weigh_sigma(self.options, c, vx)
        weights = np.repeat(np.minimum.reduceat(s_weigh, kids.starts), kids.sizes) / s_weigh
        if self.options.inverse_variance:
            weights = weights**2
        ids = kids.ids
        vx.p[ids], vx.q[ids], vx.sigma[ids] = fusion.fuse_runs(kids, c.p, c.q, c.s, weights)
        if c.c_parent is None:
            vx.cov[ids] = covariance.fuse_runs(kids, pairs, weights, c.Jp, vx.cov, c.edge_term)
        else:
            # Parents taken at their candidates' times: a pair's candidates share one parent error
            # (to first order, their mean covariance; one image's views of a parent share it exactly).
            per_pair = np.diff(np.append(pairs.starts, len(c.child)))
            c_pairs = np.add.reduceat(c.c_parent, pairs.starts) / per_pair[:, None, None]
            own = fusion.Runs(pairs.starts, np.arange(len(pairs.starts)), pairs.sizes)
            vx.cov[ids] = covariance.fuse_runs(kids, own, weights, c.Jp, c_pairs, c.edge_term)
        vx.count[ids] = kids.sizes
        newest = np.maximum.reduceat(c.capture_us, kids.starts)
        vx.stamp_us[ids] = newest
        if self.options.align:
            for k, v in enumerate(ids.tolist()):
                self.motion.add(root, v, Sample(int(newest[k]), vx.p[v].copy(), vx.q[v].copy(), vx.cov[v].copy()))
        if self.gate.enabled:
            accepted = np.maximum.reduceat(arrival_ns, kids.starts).tolist()
            for k, v in enumerate(ids.tolist()):
                att = float(np.sqrt(max(np.trace(vx.cov[v][3:, 3:]) / 3.0, 0.0)))
                pos = float(np.sqrt(max(np.trace(vx.cov[v][:3, :3]) / 3.0, 0.0)))
                prior = PriorEstimate(
                    vx.p[v].copy(), vx.q[v].copy(), float(vx.sigma[v]), att, now_ns, int(newest[k]), pos,
                    int(accepted[k]),
                )  # fmt: skip
                self.gate.remember(root, v, prior)

    def _poses(self, vx: Vertices, plan: Plan, root: int, goal: int | None) -> dict[str, EntityPose]:
        """The :class:`EntityPose` of every vertex reached (with ``goal``: the lower stages and it)."""
        levels, counts, sigmas, stamps = plan.level.tolist(), vx.count.tolist(), vx.sigma.tolist(), vx.stamp_us.tolist()
        frame = self.names[root]
        poses = {}
        below = int(plan.stage_of[goal]) if goal is not None and plan.level[goal] >= 0 else None
        stages = plan.stage_of.tolist()
        for rank_v, v in enumerate(plan.order.tolist()):
            if (below is not None and v != goal and stages[v] >= below) or vx.lost[v]:
                continue
            name = self.names[v]
            poses[name] = EntityPose(
                name,
                vx.p[v],
                vx.q[v],
                levels[v],
                rank_v,
                counts[v],
                sigmas[v],
                stamps[v],
                frame,
                vx.cov[v],
                own_view=bool(vx.own[v]) if self.own_known else None,
            )
        return poses


def weigh_sigma(options: PoseOptions, c: StageCandidates, vx: Vertices) -> NDArray[np.float64]:
    """The sigma each candidate is weighed by (eq. 6-7): the edge's (the paper), the whole chain's
    (Dijkstra), or with inverse variance its propagated covariance's position block."""
    dijkstra = options.path == "dijkstra"
    if not options.inverse_variance:
        return c.s if dijkstra else c.s_edge
    # Beyond the paper: weights from each candidate's propagated position variance (its covariance's
    # position block, the detector's own where it reported one, aged), so a fresh precise view
    # outweighs a stale or a poorly placed one whatever their sigma says.
    c_weigh = c.edge_term if c.Jp is None or not dijkstra else c.covariance(vx.cov)
    return np.sqrt(np.maximum(np.trace(c_weigh[:, :3, :3], axis1=1, axis2=2) / 3.0, 1e-30))


def gate_covariance(
    c: StageCandidates, vx: Vertices, s_weigh: NDArray[np.float64], anchored: NDArray[np.bool_], dijkstra: bool
) -> NDArray[np.float64]:
    """Each candidate's 6x6 covariance as the gate judges it: the one it is weighed with. Where the
    sigma it is weighed by (``s_weigh``) is smaller than the position spread of the part of its
    covariance that sigma describes (the edge's, or with Dijkstra the whole chain's), that part is
    shrunk by their ratio: a sender cannot claim a large covariance to pass the gate and a small sigma
    to weigh. The node's own direct views (``anchored``) are taken as they are."""
    full = c.covariance(vx.cov)
    if anchored.all():
        return full
    part = full if dijkstra or c.Jp is None else c.edge_term
    spread = np.sqrt(np.maximum(np.trace(part[:, :3, :3], axis1=1, axis2=2) / 3.0, 1e-30))
    f = np.where(anchored, 1.0, np.minimum(s_weigh / spread, 1.0))
    if (f >= 1.0).all():
        return full
    shrink = (f**2 - 1.0)[:, None, None] * part
    return full + shrink


def _edge_terms(store: EdgeStore, plan: Plan, options: PoseOptions) -> StageEdges:
    """The plan's edges as walked (parent -> child), aged. An edge's information ages (the entities may have
    moved since its image was taken): with ``age_sigma_m_per_s`` > 0 an edge of age a (s) counts with sigma
    sqrt(sigma^2 + (a * age_sigma)^2), and its covariance grows likewise (the attitude's with
    ``age_sigma_rad_per_s``); 0: the paper's method, every live edge counts as new. The age is counted from
    the newest image of a live edge, on the capture clock: a pose is stamped with the capture time of its
    newest image (and a chain's with its newest link's), so a lag common to all (the link, the queue,
    this evaluation) ages nothing, while an edge older than the images it is combined with does."""
    row, direction = plan.row, plan.direction
    sigma_raw = store.sigma[row]
    sigma = sigma_raw
    c_edge = store.cov[direction, row]
    if options.ageing and len(row):
        capture = store.capture[row]
        if options.align:
            # Against the newest edge into the same entity: a parent's edges older than its child's
            # are not stale, the child takes the parent at its own time (_compose_aligned).
            newest = _newest_into(capture, plan.child)
        else:
            newest = store.capture[store.used].max()  # every live edge's: a partial evaluation ages as a full one
        age_s = np.maximum(newest - capture, 0) / 1e6
        if options.age_sigma_m_per_s > 0.0:
            sigma = np.hypot(sigma_raw, age_s * options.age_sigma_m_per_s)
        grow = (sigma**2 - sigma_raw**2).clip(0.0)
        c_edge[:, [0, 1, 2], [0, 1, 2]] += grow[:, None]
        turn = (age_s * options.age_sigma_rad_per_s) ** 2
        c_edge[:, [3, 4, 5], [3, 4, 5]] += turn[:, None]
    p, q = store.p[direction, row], store.q[direction, row]
    return StageEdges(row, plan.parent, plan.child, p, q, sigma, c_edge, store.capture[row])


def _compose(vx: Vertices, e: StageEdges, from_root: bool, aligned: Parents | None = None) -> StageCandidates:
    """eq. 2: each candidate is P_parent * T_parent_child, with its sigma and covariance. With
    ``aligned``, the parent's pose at the candidate's capture time (then the candidate is as new as
    its edge), else the parent's newest (the candidate as new as its newest part)."""
    row, parent, child, p_pc, q_pc, s_edge, c_edge, capture_us = (
        e.row, e.parent, e.child, e.p, e.q, e.sigma, e.cov, e.capture_us
    )  # fmt: skip
    t_cand = np.maximum(capture_us, vx.stamp_us[parent])  # a candidate is as new as its newest part
    if from_root:  # the root's pose is the identity, exactly, with no uncertainty
        return StageCandidates(row, parent, child, p_pc, q_pc, s_edge, c_edge, p_pc, q_pc, s_edge, t_cand, None, c_edge)
    if aligned is None:
        p_par, q_par, s_par, c_parent = vx.p[parent], vx.q[parent], vx.sigma[parent], None
    else:
        p_par, q_par, c_parent = aligned.p, aligned.q, aligned.cov
        s_par = np.where(
            aligned.moved, np.sqrt(np.trace(aligned.cov[:, :3, :3], axis1=1, axis2=2) / 3.0), vx.sigma[parent]
        )
        t_cand = np.where(aligned.moved, capture_us, t_cand)
    R_wp = geometry.quat_matrix(q_par)
    p_cand = p_par + (R_wp @ p_pc[:, :, None])[:, :, 0]
    q_cand = geometry.quat_multiply(q_par, q_pc)
    # The candidate's sigma carries its parent's: variances add along a chain.
    s_cand = np.sqrt(s_edge**2 + s_par**2)
    # Beyond the paper: the full 6x6 covariance along the chain (lever arms included).
    Jp, Je = covariance.compose_jacobians(R_wp, p_pc, geometry.quat_matrix(q_pc))
    edge_term = covariance.transform(Je, c_edge)
    return StageCandidates(
        row, parent, child, p_pc, q_pc, s_edge, c_edge, p_cand, q_cand, s_cand, t_cand, Jp, edge_term, c_parent
    )


def _newest_into(capture: NDArray[np.int64], child: NDArray[np.intp]) -> NDArray[np.int64]:
    """Per walked edge, the newest capture among the walked edges into its child (as in a full evaluation)."""
    newest = np.full(int(child.max()) + 1, np.iinfo(np.int64).min, dtype=np.int64)
    np.maximum.at(newest, child, capture)
    return newest[child]
