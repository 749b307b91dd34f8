"""The pose phase (the paper's section 3.2, eq. 2 and 4-7): every vertex reached from a root gets the
weighted mean of its candidates, each candidate its parent's fused pose times an edge.

It runs a :class:`~atlas_onboard.core.graph.paths.Plan` stage by stage (a stage's parents all lie in
lower stages), each stage in a few batched array operations, in these steps: the edges' terms
(:func:`~.candidates.edge_terms`, aged), the candidates (:func:`~.candidates.compose`, eq. 2, with
their covariance), the gate (:meth:`PosePhase._gate`), and the fusion (:meth:`PosePhase._fuse`, eq. 4-7).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core import covariance, fusion
from atlas_onboard.core.graph.candidates import (
    PoseOptions,
    StageCandidates,
    StageEdges,
    Vertices,
    compose,
    edge_terms,
    gate_covariance,
    weigh_sigma,
)
from atlas_onboard.core.graph.edges import EdgeKey, EdgeStore
from atlas_onboard.core.graph.gate import ConsensusGate, GateInput, PriorEstimate, Verdict
from atlas_onboard.core.graph.paths import Plan
from atlas_onboard.core.graph.result import Candidate, EntityPose
from atlas_onboard.core.graph.timing import MAX_WAIT_US, WAIT_US, MotionHistory, Sample, Waiting, WaitingViews


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
        self.waiting = WaitingViews()

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
        edges = edge_terms(store, plan, self.options)
        gated = 0
        self._too_fast: list[EdgeKey] = []
        for sel, runs, from_root in zip(plan.stages, plan.runs, plan.from_root, strict=True):
            stage = edges.stage(sel)
            if from_root or not self.options.align:
                cands = compose(vx, stage, from_root)
            else:
                cands = self._compose_aligned(vx, stage, root, store)
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
            self._fuse(vx, cands, runs, root, now_ns)
            if self.own_known:
                vx.own[runs[0].ids] = np.logical_or.reduceat(anchored, runs[0].starts)
        order, level = plan.order.tolist(), plan.level.tolist()
        levels = {v: level[v] for v in order}
        poses = self._poses(vx, plan, root, goal)
        return FrameEvaluation(poses, order, levels, gated, plan.goal_is_parent, tuple(self._too_fast))

    def _compose_aligned(self, vx: Vertices, e: StageEdges, root: int, store: EdgeStore) -> StageCandidates | None:
        """A stage's candidates with each parent taken at the candidate's capture time (:mod:`.timing`).
        Left out: those whose parent has no pose; those that wait for the parent's next pose (it will
        bracket their time: an interpolation, not an extrapolation); and those whose position sigma
        (largest axis) passes ``max_relayed_sigma_m``. A child left with none is placed from its oldest
        waiting view newer than its last pose that the parent's poses now bracket
        (:class:`.timing.WaitingViews`: one per evaluation, in capture order); else it keeps its last
        pose (its stamp unchanged: not sent again) for at most ``hold_us`` of capture time, then has none
        (lost). None when no candidate is left."""
        ok = ~vx.lost[e.parent]
        if not ok.all():
            vx.lost[np.setdiff1d(e.child[~ok], e.child[ok])] = True
            e = e.stage(ok)
            if len(e.child) == 0:
                return None
        parents = self.motion.parents(root, e.parent, e.capture_us, e.p, vx.p, vx.q, vx.cov, vx.stamp_us, self._age)
        c = compose(vx, e, False, parents)
        keep = ~parents.wait & self._within_limit(c)
        # A view the parent's poses cannot place yet (its next pose is due, or the extrapolation passes
        # the limit) waits for the parent's next pose, if that is not too far off; so does one that would
        # be extrapolated while an older view of its child waits (placing it would drop that one).
        for i in range(len(e.child)):
            newest, key = self.motion.newest(root, int(e.parent[i])), store.keys[int(e.row[i])]
            ahead = int(e.capture_us[i]) - (newest.t_us if newest is not None else int(e.capture_us[i]))
            wait_us = WAIT_US + self.motion.lag_us(root, int(e.parent[i]), int(e.capture_us[i]))
            if key is None or not 0 < ahead <= min(wait_us, MAX_WAIT_US):
                continue
            if keep[i]:
                last = self.motion.newest(root, int(e.child[i]))
                after = np.iinfo(np.int64).min if last is None else last.t_us
                keep[i] = not self.waiting.pending(root, int(e.child[i]), after, int(e.capture_us[i]))
            if not keep[i]:
                view = Waiting(int(e.row[i]), key, int(e.parent[i]), int(e.child[i]), e.p[i].copy(), e.q[i].copy(),
                               float(e.sigma[i]), e.cov[i].copy(), int(e.capture_us[i]))  # fmt: skip
                self.waiting.add(root, view)
        if keep.all():
            return c
        left = np.setdiff1d(c.child[~keep], c.child[keep]).tolist()
        late = self._place_waiting(vx, root, store, left, e.parent)
        placed = set() if late is None else set(late.child.tolist())
        for v in left:
            if v in placed:
                continue
            held = self.motion.newest(root, v)
            newest = int(c.capture_us[c.child == v].max())
            if held is not None and newest - held.t_us <= self.options.hold_us:
                vx.p[v], vx.q[v], vx.cov[v], vx.stamp_us[v] = held.p, held.q, held.cov, held.t_us
                vx.sigma[v] = float(np.sqrt(np.trace(held.cov[:3, :3]) / 3.0))
                vx.count[v] = 1
            else:
                vx.lost[v] = True
        now = c.select(keep) if keep.any() else None
        if late is None or now is None:
            return late if now is None else now
        both = _concat(now, late)
        return both.select(np.lexsort((both.parent, both.child)))

    @property
    def _age(self) -> tuple[float, float]:
        return (self.options.age_sigma_m_per_s, self.options.age_sigma_rad_per_s)

    def _within_limit(self, c: StageCandidates) -> NDArray[np.bool_]:
        """Whether each candidate's position sigma (largest axis) is within ``max_relayed_sigma_m``."""
        limit = self.options.max_relayed_sigma_m
        if limit <= 0.0:
            return np.ones(len(c.child), dtype=bool)
        return np.linalg.eigvalsh(c.covariance(None)[:, :3, :3])[:, -1] <= limit**2

    def _place_waiting(
        self, vx: Vertices, root: int, store: EdgeStore, children: list[int], parents: NDArray[np.intp]
    ) -> StageCandidates | None:
        """The candidates of ``children``'s oldest waiting views newer than each child's last pose that
        their parent's poses now bracket (interpolated), within the relayed limit; None if none."""
        bracketed = {}
        for v in set(parents.tolist()):
            newest = self.motion.newest(root, v)
            if newest is not None and not vx.lost[v]:
                bracketed[v] = newest.t_us
        views: list[Waiting] = []
        for v in children:
            held = self.motion.newest(root, v)
            after = np.iinfo(np.int64).min if held is None else held.t_us
            ready = self.waiting.ready(root, v, after, bracketed)
            views += [w for w in ready if store.keys[w.row] == w.key]
        if not views:
            return None
        e = StageEdges(
            np.array([w.row for w in views], dtype=np.intp), np.array([w.parent for w in views], dtype=np.intp),
            np.array([w.child for w in views], dtype=np.intp), np.array([w.p for w in views]),
            np.array([w.q for w in views]), np.array([w.sigma for w in views]), np.array([w.cov for w in views]),
            np.array([w.capture_us for w in views], dtype=np.int64),
        )  # fmt: skip
        at = self.motion.parents(root, e.parent, e.capture_us, e.p, vx.p, vx.q, vx.cov, vx.stamp_us, self._age)
        c = compose(vx, e, False, at)
        keep = ~at.wait & self._within_limit(c)
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
            for k, v in enumerate(ids.tolist()):
                att = float(np.sqrt(max(np.trace(vx.cov[v][3:, 3:]) / 3.0, 0.0)))
                pos = float(np.sqrt(max(np.trace(vx.cov[v][:3, :3]) / 3.0, 0.0)))
                prior = PriorEstimate(
                    vx.p[v].copy(), vx.q[v].copy(), float(vx.sigma[v]), att, now_ns, int(newest[k]), pos
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


def _concat(a: StageCandidates, b: StageCandidates) -> StageCandidates:
    """Two stages' candidates, a's then b's (both through parents taken at their times)."""
    assert a.Jp is not None and b.Jp is not None and a.c_parent is not None and b.c_parent is not None
    return StageCandidates(
        *(np.concatenate((x, y)) for x, y in zip(
            (a.row, a.parent, a.child, a.p_pc, a.q_pc, a.s_edge, a.c_edge, a.p, a.q, a.s, a.capture_us, a.Jp,
             a.edge_term, a.c_parent),
            (b.row, b.parent, b.child, b.p_pc, b.q_pc, b.s_edge, b.c_edge, b.p, b.q, b.s, b.capture_us, b.Jp,
             b.edge_term, b.c_parent),
            strict=True,
        ))
    )  # fmt: skip
