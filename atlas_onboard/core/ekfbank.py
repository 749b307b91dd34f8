"""One pose EKF per entity, fed by the transform graph's candidates (``fusion.filter: ekf``).

After each graph evaluation the bank takes every candidate that comes from an edge it has not seen
yet (a new observation), in capture-time order, as a pose measurement with the candidate's 6x6
covariance (propagated along its chain). Each filter predicts with a constant-velocity model, so
an entity's pose is available between detections and for up to ``max_predict_s`` after the last
one, stamped with the time it is predicted for, with a velocity and an angular rate. Outliers are
gated by Mahalanobis distance inside each filter (counted).

Pure: times are passed in (microseconds on the capture clock, the wall clock of the swarm).
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core import covariance
from atlas_onboard.core.ekf import EkfSettings, PoseEkf
from atlas_onboard.core.graph import WORLD, Candidate, EdgeKey, EntityPose, GraphResult

_TWIST = [3, 4, 5, 9, 10, 11]  # velocity (world) and angular rate (body) in the error state


@dataclass
class EkfBank:
    """The filters of every entity (world excluded: it does not move)."""

    settings: EkfSettings = field(default_factory=EkfSettings)
    max_predict_s: float = 0.5
    filters: dict[str, PoseEkf] = field(default_factory=dict)
    outcomes: Counter[str] = field(default_factory=Counter)
    _fed: dict[tuple[str, EdgeKey], int] = field(default_factory=dict)
    _last: dict[str, EntityPose] = field(default_factory=dict)
    latency_us: float | None = None  # smoothed capture-to-filter delay of the measurements (unbounded)
    gap_factor: float = 1.5  # a gap: the last update is this many usual intervals old, and ...
    # ... at least this old. A prediction is worse than the filtered pose it follows, and the
    # autopilot wants a pose at most 0.2 s old on arrival: predictions start half-way there, which
    # leaves room for the measurements' latency.
    predict_after_s: float = 0.1
    # Through a gap the pose is predicted to the times the missed frames were due, at most this far
    # past the newest update (then held, not re-sent, until ``max_predict_s`` loses it). A constant-
    # velocity extrapolation of a quadrotor is good for a few frames only (docs/covariance.md), while
    # 0.2 s still bridges the autopilot's 200 ms freshness limit across gaps of 0.4 s.
    predict_horizon_s: float = 0.2
    _interval: dict[str, float] = field(default_factory=dict)  # smoothed update interval, s
    # When (``now_us`` of :meth:`update`) each filter's newest update arrived: a pose's age is how long
    # ago that was, not how old its capture stamp is. A replay or a detector that runs seconds late
    # delivers measurements that are old but new to the filter; they are published (stamped with
    # their capture time, the lateness reported by the node), never withheld for their age.
    _arrival_us: dict[str, int] = field(default_factory=dict)
    # How old each filter's newest update was when it arrived, and the least such age seen: a newest
    # update that arrived later than the promptest by more than ``predict_after_s`` comes from a
    # source running behind (a replay, a detector that cannot keep up). Its missing frames are not
    # a gap but still to come, stamped in sequence: the pose is not predicted past them (a
    # prediction stamped ahead would make every one of them too old to publish).
    _lag_us: dict[str, int] = field(default_factory=dict)
    _min_lag_us: dict[str, int] = field(default_factory=dict)
    # The smoothed wall-clock spacing of the updates' arrivals, s: a gap is a pause of the arrivals,
    # counted in their own spacing (a replay's frames stamped 1 ms apart but detected 45 ms apart
    # are not 45 missing frames each).
    _spacing: dict[str, float] = field(default_factory=dict)

    def update(self, result: GraphResult, now_us: int | None = None, only: str | None = None) -> None:
        """Feed the new candidates of one evaluation (world-frame poses only); ``now_us`` (capture
        clock) measures how old measurements are when they arrive. With ``only``, just the filters
        that entity's pose needs: its own and those of the entities its candidates rest on, and
        theirs (a node filters for its autopilot; the others' filters would be work for nothing)."""
        wanted = None if only is None else self._ancestry(result, only)
        # Parents before children (the evaluation's order): a child's candidate is composed with its
        # parent's filtered pose, updated first.
        for name in [n for n in result.order if n in result.candidates]:
            cands = result.candidates[name]
            if name == WORLD or name not in result.poses or (wanted is not None and name not in wanted):
                continue
            ekf = self.filters.get(name)
            if ekf is None:
                ekf = self.filters[name] = PoseEkf(replace(self.settings))
            self._last[name] = result.poses[name]
            fresh = [c for c in cands if self._fed.get((name, c.key)) != c.stamp_ns]
            before = ekf.t_update_s if ekf.initialized else None
            for c in sorted(fresh, key=lambda c: c.capture_time_us):
                self._fed[(name, c.key)] = c.stamp_ns
                if now_us is not None:
                    lag = float(max(now_us - c.capture_time_us, 0))
                    self.latency_us = lag if self.latency_us is None else 0.9 * self.latency_us + 0.1 * lag
                p_m, q, cov = self._measurement(c)
                outcome = ekf.update(c.capture_time_us / 1e6, p_m, q, 0.5 * (cov + cov.T))
                self.outcomes[outcome] += 1
            if now_us is not None and ekf.initialized and (before is None or ekf.t_update_s > before):
                last_arrival = self._arrival_us.get(name)
                if before is not None and last_arrival is not None:
                    spacing = min(max(now_us - last_arrival, 0) / 1e6, self.max_predict_s)
                    old_spacing = self._spacing.get(name)
                    self._spacing[name] = spacing if old_spacing is None else 0.9 * old_spacing + 0.1 * spacing
                self._arrival_us[name] = now_us
                lag = now_us - round(ekf.t_update_s * 1e6)
                self._lag_us[name] = lag
                self._min_lag_us[name] = min(self._min_lag_us.get(name, lag), lag)
            if before is not None and ekf.t_update_s > before:
                step = min(ekf.t_update_s - before, self.max_predict_s)
                old = self._interval.get(name)
                self._interval[name] = step if old is None else 0.9 * old + 0.1 * step
        # Forget edges no longer in the graph, so the bookkeeping stays bounded.
        live = {(n, c.key) for n, cands in result.candidates.items() for c in cands}
        for k in [k for k in self._fed if k not in live]:
            del self._fed[k]

    @staticmethod
    def _ancestry(result: GraphResult, name: str) -> set[str]:
        """``name`` and every entity its candidates are composed from, recursively."""
        found, todo = {name}, [name]
        while todo:
            for c in result.candidates.get(todo.pop(), ()):
                if c.parent is not None and c.parent not in found:
                    found.add(c.parent)
                    todo.append(c.parent)
        return found

    def _measurement(self, c: Candidate) -> tuple[NDArray[np.float64], Rotation, NDArray[np.float64]]:
        """A candidate as the filter takes it. One whose parent is an entity (not the root) is the
        parent's pose times the edge: composed with the parent's filter, not with the graph's fused
        pose of the parent. The graph's parent pose, fused from whatever edges are live (with the
        paper's method, stale ones counted as new), errs the same way frame after frame, and a filter
        fed it as fresh noise each frame grows sure of it: in the relay scenario the chain's drones
        had a position NEES of 150-170 and more error than without the filter. A candidate the graph
        composed with the parent taken at its own capture time (``aligned``) is taken as it is: its
        covariance carries that step, where the parent's filter holds its attitude and would swing
        the entity by the parent's turn over the lever arm."""
        parent = self.filters.get(c.parent) if c.parent is not None else None
        t_s = c.capture_time_us / 1e6
        if (
            parent is None
            or c.aligned  # the graph took the parent at this candidate's time: a measurement as it is
            or not parent.initialized
            or t_s - parent.t_update_s > self.max_predict_s  # the parent's filter has lapsed
            or c.p_pc is None
            or c.q_pc is None
            or c.edge_covariance is None
        ):
            return c.p_m, Rotation.from_quat(c.q_xyzw), c.covariance
        p_wp, q_wp, P_wp = parent.pose_at(t_s)
        R_wp = q_wp.as_matrix()
        q_pc = Rotation.from_quat(c.q_pc)
        Jp, Je = covariance.compose_jacobians(R_wp, c.p_pc, q_pc.as_matrix())
        cov = Jp @ P_wp @ Jp.T + Je @ c.edge_covariance @ Je.T
        return p_wp + R_wp @ c.p_pc, q_wp * q_pc, cov

    def pose(self, name: str, now_us: int) -> EntityPose | None:
        """The entity's filtered pose, or None when it has no estimate or its last update is older
        than ``max_predict_s`` (the pose is then lost, as without a filter).

        While detections flow the pose is the filter's at its newest measurement, stamped with that
        capture time: filtered, not extrapolated (a quadrotor's attitude jitters faster than a
        30 Hz camera can follow, so extrapolating between frames costs more than it gives). Once
        the last update is older than ``gap_factor`` usual intervals and ``predict_after_s``, the
        pose is predicted to the last frame time due by ``now_us`` (the newest update's capture time
        plus the time since it arrived), advancing by the usual interval up to ``predict_horizon_s``
        past the last update, then held. Either way the stamp is a capture-clock time of the usual
        age, so the autopilot's delay setting (EKF2_EV_DELAY, VISO_DELAY_MS) is the same with and
        without the filter; measurements that arrive late keep their age, and still go out.
        """
        ekf = self.filters.get(name)
        last = self._last.get(name)
        if ekf is None or last is None or not ekf.initialized:
            return None
        arrival = self._arrival_us.get(name)
        if arrival is not None:  # the capture-clock time that corresponds to now: the newest update's, aged
            t = ekf.t_update_s + max(now_us - arrival, 0) / 1e6
        else:
            t = (now_us - (self.latency_us or 0.0)) / 1e6
        if t - ekf.t_update_s > self.max_predict_s:
            return None
        interval = self._interval.get(name)
        behind = self._lag_us.get(name, 0) - self._min_lag_us.get(name, 0) > self.predict_after_s * 1e6
        spacing = self._spacing.get(name, interval)
        elapsed = t - ekf.t_update_s  # wall time since the newest update arrived
        if (
            interval is None
            or spacing is None
            or behind
            or elapsed <= max(self.gap_factor * spacing, self.predict_after_s)
            or not ekf.velocity_observed
        ):
            # Detections flow: the filtered pose at the newest one. Likewise in a gap that follows a
            # lone measurement after a reset: with no velocity observed, a prediction is that pose held,
            # stamped as if it were newer (off by the distance flown since); the autopilot's own
            # inertial prediction bridges the gap instead.
            t = ekf.t_update_s
        else:
            # A gap: predicted to the last frame time that was due (the stamps advance at the camera's
            # rate, not the caller's), no further than the horizon.
            k = min(math.floor(elapsed / max(spacing, interval)), math.floor(self.predict_horizon_s / interval + 1e-9))
            t = ekf.t_update_s + max(k, 0) * interval
        t = max(t, ekf.t_s)
        p, q, cov = ekf.pose_at(t)
        pos_sigma = float(np.sqrt(max(np.trace(cov[0:3, 0:3]) / 3.0, 0.0)))
        return replace(
            last,
            p_world_m=p,
            q_world_xyzw=q.as_quat(),
            sigma_m=pos_sigma,
            capture_time_us=round(t * 1e6),
            covariance=0.5 * (cov + cov.T),
            velocity_m_s=ekf.v.copy(),
            angular_rate_rad_s=ekf.w.copy() if ekf.settings.constant_rate else None,
            velocity_covariance=ekf.P[np.ix_(_TWIST, _TWIST)].copy(),
        )

    def poses(self, result: GraphResult, now_us: int, only: str | None = None) -> GraphResult:
        """``result`` with every filtered entity's pose replaced by its prediction at ``now_us``;
        entities whose filter has lapsed are removed (their pose is lost). With ``only``, just that
        entity's (the others as the graph gave them): a node's autopilot needs its own, and a
        prediction costs a filter copy and a few rotations (in a swarm's node, computing all six at
        every publish was a third of the node's time)."""
        if only == WORLD:
            return result
        if only is not None:
            out = {n: p for n, p in result.poses.items() if n != only}
            filtered = self.pose(only, now_us)
            if filtered is not None:
                out[only] = filtered
            return replace(result, poses=out)
        out = {}
        for name, graph_pose in result.poses.items():
            if name == WORLD:
                out[name] = graph_pose
                continue
            filtered = self.pose(name, now_us)
            if filtered is not None:
                out[name] = filtered
        # An entity out of the graph this instant (its edges expired) still has its prediction.
        for name in self.filters:
            if name not in out:
                filtered = self.pose(name, now_us)
                if filtered is not None:
                    out[name] = filtered
        return replace(result, poses=out)
