"""The sensor listener (the paper's section 3.1): MarkerData -> validated, EMA-filtered graph edges.

Pure: no I/O and no clock; the caller passes the arrival time. Every rejected observation is counted
by reason, and a rejected observation changes nothing (no edge, no filter state).

Planar ambiguity: an observation whose IPPE ratio exceeds ``ambiguity_threshold`` may carry the flipped
pose. If it carries the other solution too, the current estimates (:meth:`Listener.set_estimates`,
which the node calls after every evaluation) pick the consistent one by the rule of
:mod:`atlas_onboard.core.ambiguity`; if they cannot, a pair within the detection's covariance is used as
the two solutions' mixture (its covariance grown to cover both); any other, or one that carries no
other solution, is rejected and counted.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WorldConfig
from atlas_onboard.core import ambiguity, covariance, geometry
from atlas_onboard.core.edge_covariance import edge_covariances, inconsistent_sigma, positive_definite
from atlas_onboard.core.edge_filter import EdgeFilter, EdgeState
from atlas_onboard.core.graph import EdgeKey, EntityPose, TransformGraph
from atlas_onboard.core.markerdata import MarkerData, Rejection
from atlas_onboard.counters import Counters
from atlas_onboard.listener.ambiguity import AmbiguityResolver, Detections

_logger = logging.getLogger(__name__)

ESTIMATE_ATTITUDE_SIGMA_RAD = 0.05
"""Per-axis attitude error assumed for an entity's estimate when it resolves an ambiguity (about 3
degrees), grown by the motion the entity may have made since the estimate's capture (the graph's
MAX_RATE_RAD_S and MAX_SPEED_M_S times the age). The root of the estimates' frame (``world``) is
exact."""


@dataclass(frozen=True, slots=True)
class EdgeUpdate:
    """What an accepted observation became: the edge ``T_a_b`` after eq. 1 and the EMA of eq. 3."""

    key: EdgeKey
    observer: str
    observed: str
    p_a_b: NDArray[np.float64]
    q_a_b_xyzw: NDArray[np.float64]
    sigma_m: float
    cov_a_b: NDArray[np.float64] | None = None  # 6x6, core.covariance convention


class Listener:
    """Turns MarkerData into graph edges for one world file.

    ``T1`` (entity to sensor) and ``T3^-1`` (marker to entity) of eq. 1 are fixed by the world file,
    so they are precomputed as 4x4 matrices; per observation the work is two matrix products.
    """

    def __init__(
        self,
        world: WorldConfig,
        graph: TransformGraph,
        *,
        ambiguity_threshold: float = ambiguity.AMBIGUITY_THRESHOLD,
        attitude_sigma_rad: float = ESTIMATE_ATTITUDE_SIGMA_RAD,
        gate_r2: float = ambiguity.GATE_R2,
        min_likelihood_ratio: float = ambiguity.MIN_LIKELIHOOD_RATIO,
    ) -> None:
        """``ambiguity_threshold``: IPPE ratio above which an observation must be resolved (or is
        rejected); ``attitude_sigma_rad``, ``gate_r2``, ``min_likelihood_ratio``: the resolution rule's
        parameters (:mod:`atlas_onboard.core.ambiguity`)."""
        self.world = world
        self.graph = graph
        self.filter = EdgeFilter(world.fusion.ema_alpha, world.fusion.age_sigma_m_per_s, graph.edge_timeout_ns)
        self.ambiguity = AmbiguityResolver(
            world,
            threshold=ambiguity_threshold,
            attitude_sigma_rad=attitude_sigma_rad,
            gate_r2=gate_r2,
            min_likelihood_ratio=min_likelihood_ratio,
        )
        self._sensor = {s.id: (s.entity, s.T_entity_sensor.as_matrix()) for s in world.sensors.values()}
        self._marker = {m.id: (m.entity, m.T_entity_marker.inv().as_matrix()) for m in world.markers.values()}
        # The same rotations as quaternions: eq. 1's rotation is composed as a quaternion product.
        self._sensor_q = {s.id: s.T_entity_sensor.rotation.as_quat() for s in world.sensors.values()}
        self._marker_inv_q = {m.id: m.T_entity_marker.rotation.inv().as_quat() for m in world.markers.values()}
        self._marker_fwd = {m.id: m.T_entity_marker.as_matrix() for m in world.markers.values()}
        self._marker_cov: dict[int, NDArray[np.float64]] = {}  # markers placed by refinement, not the file
        self._ema: dict[EdgeKey, EdgeState] = {}  # each edge's filtered value, where the filter keeps one
        self.rejected = Counters()  # by reason (``rejected_<reason>``)
        self.counters = Counters()
        """Beyond rejections: ``ambiguity_resolved``, ``ambiguity_swapped`` (the other solution won),
        ``ambiguity_<verdict>`` for each one the estimates leave unresolved, ``ambiguity_covered`` for
        those of them used as the pair's mixture, and ``alt_ignored`` (an unusable other solution, see
        :class:`MarkerData`)."""
        self.accepted = 0

    def set_attitude(self, entity: str, up_at: Callable[[int], NDArray[np.float64] | None] | None) -> None:
        """The autopilot's gravity reference of ``entity`` (the node's own): ``up_at(capture_time_us)``
        is world up in the entity's body frame at that time, or None when no fresh attitude covers it.
        With it, a single tag's two solutions (observations between ``entity`` and the world carrying
        both) are chosen by the tilt they imply (:func:`atlas_onboard.core.attitude.choose_by_tilt`);
        one whose solutions both disagree with gravity is rejected (``attitude_mismatch``)."""
        self.ambiguity.set_attitude(entity, up_at)

    def set_marker_pose(self, marker_id: int, M_entity_marker: NDArray[np.float64], cov: NDArray[np.float64]) -> None:
        """Place a marker elsewhere than the world file does (live map refinement): ``M_entity_marker``
        its 4x4 pose in its entity, ``cov`` that pose's 6x6 covariance (dp in the entity frame, dtheta
        about the marker's axes), carried into every edge through it from now on."""
        M = np.asarray(M_entity_marker, dtype=float)
        T = geometry.pose_from_arrays(M[:3, 3], Rotation.from_matrix(M[:3, :3]).as_quat())
        entity = self._marker[marker_id][0]
        self._marker[marker_id] = (entity, T.inv().as_matrix())
        self._marker_inv_q[marker_id] = T.rotation.inv().as_quat()
        self._marker_fwd[marker_id] = T.as_matrix()
        self._marker_cov[marker_id] = np.asarray(cov, dtype=float)
        self.ambiguity.set_marker_pose(marker_id, T.as_matrix())

    def marker_pose(self, marker_id: int) -> NDArray[np.float64]:
        """The 4x4 pose of a marker in its entity that eq. 1 uses now (the world file's, or a refined one)."""
        return self._marker_fwd[marker_id].copy()

    def set_estimates(self, poses: Mapping[str, EntityPose]) -> None:
        """The current pose estimates (a graph evaluation's ``poses``), used to resolve ambiguity."""
        self.ambiguity.set_estimates(poses)

    def edge_from(self, md: MarkerData) -> EdgeUpdate | Rejection:
        """Eq. 1, T = T1 * T2 * T3^-1, without filtering (an ambiguous observation resolved with the
        current estimates); or the reason the observation is invalid. Counts nothing."""
        updates, _ = self._edges([md])
        return updates[0]

    def _edges(self, mds: list[MarkerData]) -> tuple[list[EdgeUpdate | Rejection], list[str]]:
        """Eq. 1 for many observations at once (one scipy call per step, not one per observation),
        and the names of the ambiguity counters to increment."""
        out: list[EdgeUpdate | Rejection] = []
        notes: list[str] = []
        valid = []
        for md in mds:
            reason = self._check(md)
            out.append(reason if reason is not None else md)  # type: ignore[arg-type]
            if reason is None:
                valid.append(md)
        C_sm = None  # the detection covariances as matrices, when every valid record has one
        if any(md.covariance for md in valid):
            valid, C_sm = positive_definite(valid, out)
            valid, C_sm = inconsistent_sigma(valid, out, C_sm, self.graph.anchor_sensors)
        if not valid:
            return out, notes
        T1 = np.array([self._sensor[md.sensor_id][1] for md in valid])
        T3_inv = np.array([self._marker[md.marker_id][1] for md in valid])
        q2 = np.array([md.q_sensor_marker_wxyz for md in valid])[:, [1, 2, 3, 0]]
        q2 /= np.sqrt(np.einsum("ij,ij->i", q2, q2))[:, None]
        R2 = geometry.quat_matrix(q2)
        p2 = np.array([md.p_sensor_marker_m for md in valid])
        unresolved, swapped = self.ambiguity.resolve(Detections(valid, R2, p2, q2, C_sm), notes)
        if any(valid[j].covariance for j in swapped):
            # The detector's covariance describes the solution it chose, not the other one (whose
            # tilt, and so whose spread, differs): a swapped record's edge gets the sigma model.
            valid = [replace(md, covariance=()) if j in swapped else md for j, md in enumerate(valid)]
            C_sm = None
        # eq. 1, T = T1 T2 T3^-1, its translation: p_a_b = R_a_s (p_s_m + R_s_m p_m_b) + p_a_s
        R_as = T1[:, :3, :3]
        chain = covariance.Chain(R_as, R2, p2, T3_inv)
        p_ab = T1[:, :3, 3] + (R_as @ chain.p_sb[:, :, None])[:, :, 0]
        q1 = np.array([self._sensor_q[md.sensor_id] for md in valid])
        q3_inv = np.array([self._marker_inv_q[md.marker_id] for md in valid])
        q_all = geometry.quat_multiply(geometry.quat_multiply(q1, q2), q3_inv)  # eq. 1's rotation
        cov = edge_covariances(valid, chain, C_sm)
        if self._marker_cov:
            placed = [j for j, md in enumerate(valid) if md.marker_id in self._marker_cov]
            if placed:  # T_a_b = T_a_m T_m_b: a refined marker's own uncertainty enters through T_m_b
                M_bm = np.array([self._marker_fwd[valid[j].marker_id] for j in placed])
                C_bm = np.array([self._marker_cov[valid[j].marker_id] for j in placed])
                C_mb = covariance.transform(covariance.inverse_jacobian(M_bm[:, :3, 3], M_bm[:, :3, :3]), C_bm)
                Je = np.tile(np.eye(6), (len(placed), 1, 1))
                Je[:, :3, :3] = R_as[placed] @ R2[placed]
                cov = cov.copy()
                cov[placed] += covariance.transform(Je, C_mb)
        j = 0
        for i, item in enumerate(out):
            if isinstance(item, MarkerData):
                if j in unresolved:
                    out[i] = unresolved[j]
                else:
                    observer, observed = self._sensor[item.sensor_id][0], self._marker[item.marker_id][0]
                    key = (item.sensor_id, item.marker_id)
                    out[i] = EdgeUpdate(key, observer, observed, p_ab[j], q_all[j], valid[j].sigma_m, cov[j])
                j += 1
        return out, notes

    def accept(self, md: MarkerData, now_ns: int) -> Rejection | None:
        """Validate, transform (eq. 1), filter (eq. 3) and insert into the graph; None when accepted."""
        return self.accept_many([(md, now_ns)])[0]

    def accept_many(self, items: list[tuple[MarkerData, int]]) -> list[Rejection | None]:
        """:meth:`accept` for a burst of observations, with eq. 1 computed for all of them at once
        (the node's hot path)."""
        results: list[Rejection | None] = []
        updates, notes = self._edges([md for md, _ in items])
        self.counters.update(notes)
        for (md, now_ns), update in zip(items, updates, strict=True):
            if isinstance(update, Rejection):
                self.rejected.inc(update)
                results.append(update)
            else:
                self._insert(md, update, now_ns)
                results.append(None)
        return results

    def _check(self, md: MarkerData) -> Rejection | None:
        reason = md.rejection()
        if reason is not None:
            return reason
        sensor = self._sensor.get(md.sensor_id)
        if sensor is None:
            return Rejection.UNKNOWN_SENSOR
        marker = self._marker.get(md.marker_id)
        if marker is None:
            return Rejection.UNKNOWN_MARKER
        if sensor[0] == marker[0]:
            return Rejection.OWN_MARKER
        return None

    def _insert(self, md: MarkerData, result: EdgeUpdate, now_ns: int) -> None:
        key = result.key
        state = self.filter.update(
            self._ema.get(key), result.p_a_b, result.q_a_b_xyzw, result.sigma_m, bool(md.covariance), now_ns
        )
        if self.filter.keeps_state:  # the filter's state is read only by the filter
            self._ema[key] = state
        p, q, sigma = state.p, state.q, state.sigma_m
        cov = result.cov_a_b
        if cov is not None and sigma != result.sigma_m:
            cov = cov * (sigma / result.sigma_m) ** 2
        self.graph.update_edge(
            key, result.observer, result.observed, p, q, sigma, now_ns, md.capture_time_us, cov_a_b=cov
        )
        self.accepted += 1

    def forget_expired(self, now_ns: int) -> None:
        """Drop filter state of edges older than the timeout (bounded memory when sensors go away)."""
        dead = [k for k, s in self._ema.items() if self.filter.expired(s, now_ns)]
        for k in dead:
            del self._ema[k]
