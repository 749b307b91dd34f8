"""The sensor listener (the paper's section 3.1): MarkerData -> validated, EMA-filtered graph edges.

Pure: no I/O and no clock; the caller passes the arrival time. Every rejected observation is counted
by reason, and a rejected observation changes nothing (no edge, no filter state).
"""

from __future__ import annotations

import logging
from collections import Counter
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import Weighting, WorldConfig
from atlas_onboard.core import covariance, fusion
from atlas_onboard.core.graph import EdgeKey, TransformGraph
from atlas_onboard.core.markerdata import MarkerData, Rejection

_logger = logging.getLogger(__name__)


@dataclass(slots=True)
class _EmaState:
    p: NDArray[np.float64]
    q: NDArray[np.float64]  # xyzw
    stamp_ns: int
    sigma_m: float


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


def make_graph(world: WorldConfig) -> TransformGraph:
    """The transform graph a world file describes: its entities and fusion settings."""
    f = world.fusion
    return TransformGraph(
        world.entity_names,
        round(f.edge_timeout_s * 1e9),
        inverse_variance=f.weighting is Weighting.INVERSE_VARIANCE,
        path=f.path,
        relative=f.relative_poses,
        age_sigma_m_per_s=f.age_sigma_m_per_s,
        outlier_gate_sigma=f.outlier_gate_sigma,
        keep_candidates=f.filter == "ekf",
    )


class Listener:
    """Turns MarkerData into graph edges for one world file.

    ``T1`` (entity to sensor) and ``T3^-1`` (marker to entity) of eq. 1 are fixed by the world file,
    so they are precomputed as 4x4 matrices; per observation the work is two matrix products.
    """

    def __init__(self, world: WorldConfig, graph: TransformGraph) -> None:
        self.world = world
        self.graph = graph
        self.alpha = world.fusion.ema_alpha
        self.age_sigma = world.fusion.age_sigma_m_per_s
        self.timeout_ns = graph.edge_timeout_ns
        self._sensor = {s.id: (s.entity, s.T_entity_sensor.as_matrix()) for s in world.sensors.values()}
        self._marker = {m.id: (m.entity, m.T_entity_marker.inv().as_matrix()) for m in world.markers.values()}
        self._ema: dict[EdgeKey, _EmaState] = {}
        self.rejected: Counter[Rejection] = Counter()
        self.accepted = 0

    def edge_from(self, md: MarkerData) -> EdgeUpdate | Rejection:
        """Eq. 1, T = T1 * T2 * T3^-1, without filtering; or the reason the observation is invalid."""
        updates = self._edges([md])
        return updates[0]

    def _edges(self, mds: list[MarkerData]) -> list[EdgeUpdate | Rejection]:
        """Eq. 1 for many observations at once (one scipy call per step, not one per observation)."""
        out: list[EdgeUpdate | Rejection] = []
        valid = []
        for md in mds:
            reason = self._check(md)
            out.append(reason if reason is not None else md)  # type: ignore[arg-type]
            if reason is None:
                valid.append(md)
        if not valid:
            return out
        T1 = np.array([self._sensor[md.sensor_id][1] for md in valid])
        T3_inv = np.array([self._marker[md.marker_id][1] for md in valid])
        T2 = np.tile(np.eye(4), (len(valid), 1, 1))
        T2[:, :3, :3] = Rotation.from_quat(np.array([md.q_sensor_marker_xyzw() for md in valid])).as_matrix()
        T2[:, :3, 3] = np.array([md.p_sensor_marker_m for md in valid])
        T = T1 @ T2 @ T3_inv  # eq. 1
        q_all = Rotation.from_matrix(T[:, :3, :3]).as_quat()
        cov = covariance.observation(T1, T2, T3_inv, np.array([md.sigma_m for md in valid]))
        j = 0
        for i, item in enumerate(out):
            if isinstance(item, MarkerData):
                observer, observed = self._sensor[item.sensor_id][0], self._marker[item.marker_id][0]
                key = (item.sensor_id, item.marker_id)
                out[i] = EdgeUpdate(key, observer, observed, T[j, :3, 3].copy(), q_all[j], item.sigma_m, cov[j])
                j += 1
        return out

    def accept(self, md: MarkerData, now_ns: int) -> Rejection | None:
        """Validate, transform (eq. 1), filter (eq. 3) and insert into the graph; None when accepted."""
        return self.accept_many([(md, now_ns)])[0]

    def accept_many(self, items: list[tuple[MarkerData, int]]) -> list[Rejection | None]:
        """:meth:`accept` for a burst of observations, with eq. 1 computed for all of them at once
        (the node's hot path)."""
        results: list[Rejection | None] = []
        for (md, now_ns), update in zip(items, self._edges([md for md, _ in items]), strict=True):
            if isinstance(update, Rejection):
                self.rejected[update] += 1
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
        state = self._ema.get(key)
        sigma = result.sigma_m
        if state is None or now_ns - state.stamp_ns > self.timeout_ns:
            # A new or expired edge starts the filter afresh: old information is not mixed in.
            p, q = result.p_a_b, result.q_a_b_xyzw
        elif self.age_sigma > 0.0:
            # Beyond the paper: a per-edge Kalman filter with a random walk of age_sigma m/s. The old
            # value's variance grows with its age; the blend weighs old and new by inverse variance,
            # so a blurred frame (large sigma) cannot overwrite a sharp one taken a moment before.
            age_s = (now_ns - state.stamp_ns) / 1e9
            var_old = state.sigma_m**2 + (age_s * self.age_sigma) ** 2
            var_new = sigma**2
            alpha = var_old / (var_old + var_new)
            p = fusion.ema_position(state.p, result.p_a_b, alpha)
            q = fusion.ema_quaternion(state.q, result.q_a_b_xyzw, alpha)
            sigma = float(np.sqrt(var_old * var_new / (var_old + var_new)))
        else:
            p = fusion.ema_position(state.p, result.p_a_b, self.alpha)  # eq. 3
            q = fusion.ema_quaternion(state.q, result.q_a_b_xyzw, self.alpha)
        self._ema[key] = _EmaState(p, q, now_ns, sigma)
        cov = None if result.cov_a_b is None else result.cov_a_b * (sigma / result.sigma_m) ** 2
        self.graph.update_edge(
            key, result.observer, result.observed, p, q, sigma, now_ns, md.capture_time_us, cov_a_b=cov
        )
        self.accepted += 1

    def forget_expired(self, now_ns: int) -> None:
        """Drop filter state of edges older than the timeout (bounded memory when sensors go away)."""
        dead = [k for k, s in self._ema.items() if now_ns - s.stamp_ns > self.timeout_ns]
        for k in dead:
            del self._ema[k]
