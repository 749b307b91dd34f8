"""The candidates of the pose phase (the paper's eq. 2), stage by stage: the plan's edges as walked and aged
(:func:`edge_terms`), each candidate its parent's pose times an edge with its sigma and covariance
(:func:`compose`), and the sigma and covariance each is weighed (:func:`weigh_sigma`, eq. 6-7) and gated
(:func:`gate_covariance`) with. The records they pass: :class:`PoseOptions`, :class:`Vertices`,
:class:`StageEdges`, :class:`StageCandidates`. :mod:`.pose` runs the stages.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core import covariance, geometry
from atlas_onboard.core.graph.edges import EdgeStore
from atlas_onboard.core.graph.paths import Plan
from atlas_onboard.core.graph.timing import Parents


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


def edge_terms(store: EdgeStore, plan: Plan, options: PoseOptions) -> StageEdges:
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
            # are not stale, the child takes the parent at its own time (:meth:`.pose.PosePhase._compose_aligned`).
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


def compose(vx: Vertices, e: StageEdges, from_root: bool, aligned: Parents | None = None) -> StageCandidates:
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
