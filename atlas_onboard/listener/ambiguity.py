"""The listener's resolution of planar ambiguity (:mod:`atlas_onboard.listener`): by the current
estimates (:mod:`atlas_onboard.core.ambiguity`) and, with the autopilot's attitude, by gravity.

:class:`AmbiguityResolver` owns what the decision needs (the world file's mountings, the latest
estimates, the attitude source, the rule's thresholds); the listener holds one and asks it."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, WorldConfig
from atlas_onboard.core import ambiguity, attitude
from atlas_onboard.core.ambiguity import Verdict
from atlas_onboard.core.edge_covariance import camera_spread, pose_matrices, rotation_sigma
from atlas_onboard.core.graph import MAX_RATE_RAD_S, MAX_SPEED_M_S, EntityPose
from atlas_onboard.core.markerdata import AltState, MarkerData, Rejection, matrix_to_upper, upper_to_matrix

TILT_RATE_RAD_S = 0.5  # how fast a quadrotor's tilt may change between two of its estimates (manoeuvres)


@dataclass(frozen=True, slots=True)
class PeerTilt:
    """Another entity's estimated attitude (``R_world_entity``) and its tilt sigma (rad)."""

    R_world_entity: NDArray[np.float64]
    sigma_rad: float


@dataclass(slots=True)
class Detections:
    """A batch of valid detections under resolution, changed in place: the records, their rotation
    matrices ``R_sm`` (N, 3, 3) and rotations ``q_sm_xyzw`` (N, 4) of T_sensor_marker, positions ``p_sm``
    (N, 3, m), and their detection covariances as matrices ``C_sm`` (N, 6, 6) when every record has one."""

    records: list[MarkerData]
    R_sm: NDArray[np.float64]
    p_sm: NDArray[np.float64]
    q_sm_xyzw: NDArray[np.float64]
    C_sm: NDArray[np.float64] | None = None


class AmbiguityResolver:
    """Decides which of an ambiguous observation's two solutions an edge is made of, that it is their
    mixture (two solutions too close to tell apart), or that it is refused.

    ``threshold``: IPPE ratio above which an observation must be resolved (or is rejected);
    ``attitude_sigma_rad``, ``gate_r2``, ``min_likelihood_ratio``: the resolution rule's parameters;
    ``cover_r2``: how close (in the detection's covariance) an undecided pair must be to be used as
    the two solutions' mixture instead of refused (:mod:`atlas_onboard.core.ambiguity`).
    """

    def __init__(
        self,
        world: WorldConfig,
        *,
        threshold: float,
        attitude_sigma_rad: float,
        gate_r2: float,
        min_likelihood_ratio: float,
        cover_r2: float = ambiguity.COVER_R2,
    ) -> None:
        self.threshold = threshold
        self.cover_r2 = cover_r2
        self.attitude_sigma_rad = attitude_sigma_rad
        self.gate_r2 = gate_r2
        self.min_likelihood_ratio = min_likelihood_ratio
        self._sensor_entity = {s.id: s.entity for s in world.sensors.values()}
        self._marker_entity = {m.id: m.entity for m in world.markers.values()}
        self._T_entity_sensor = {s.id: s.T_entity_sensor.as_matrix() for s in world.sensors.values()}
        self._T_sensor_entity = {s.id: s.T_entity_sensor.inv().as_matrix() for s in world.sensors.values()}
        self._T_entity_marker = {m.id: m.T_entity_marker.as_matrix() for m in world.markers.values()}
        self._estimates: dict[str, EntityPose] = {}
        self._up_at: Callable[[int], NDArray[np.float64] | None] | None = None
        self._up_entity: str | None = None

    def set_marker_pose(self, marker_id: int, M_entity_marker: NDArray[np.float64]) -> None:
        """A marker placed elsewhere than the world file (live refinement): predictions use it from now on."""
        self._T_entity_marker[marker_id] = np.asarray(M_entity_marker, dtype=float)

    def set_attitude(self, entity: str, up_at: Callable[[int], NDArray[np.float64] | None] | None) -> None:
        """The gravity reference of ``entity`` (see :meth:`atlas_onboard.listener.listener.Listener.set_attitude`)."""
        self._up_entity, self._up_at = (entity, up_at) if up_at is not None else (None, None)

    def set_estimates(self, poses: Mapping[str, EntityPose]) -> None:
        """The current pose estimates (a graph evaluation's ``poses``)."""
        self._estimates = dict(poses)

    def resolve(self, det: Detections, notes: list[str]) -> tuple[dict[int, Rejection], set[int]]:
        """Resolve the ambiguous observations among ``det`` in place, batched.

        Returns the rejections by index into ``det.records`` and the indices swapped to the other
        solution; appends counter names to ``notes``.
        """
        valid, p2, q2 = det.records, det.p_sm, det.q_sm_xyzw
        rejected: dict[int, Rejection] = {}
        swapped: set[int] = set()
        todo: list[tuple[int, EntityPose, EntityPose]] = []
        undecided: list[int] = []  # no prediction, or too close for it: covered when close, else refused
        by_tilt = self._by_tilt(det, notes, rejected, swapped) if self._up_at else set()
        for j, md in enumerate(valid):
            state = md.alt_state()
            if state is AltState.INVALID:
                notes.append("alt_ignored")
            if j in by_tilt or not md.ambiguity_ratio > self.threshold:  # nan (unknown) passes
                continue
            if state is not AltState.VALID:
                rejected[j] = Rejection.AMBIGUOUS
                continue
            est_a = self._estimates.get(self._sensor_entity[md.sensor_id])
            est_b = self._estimates.get(self._marker_entity[md.marker_id])
            if est_a is None or est_b is None or est_a.frame != est_b.frame:
                undecided.append(j)
                notes.append(f"ambiguity_{Verdict.NO_PREDICTION.value}")
                continue
            todo.append((j, est_a, est_b))
        if not todo:
            self._cover(det, undecided, notes, rejected)
            return rejected, swapped
        idx = [j for j, _, _ in todo]
        # Predicted T_sensor_marker = T1^-1 * T_frame_observer^-1 * T_frame_observed * T3 (eq. 1 backwards).
        W_a = pose_matrices(np.array([a.p_world_m for _, a, _ in todo]), np.array([a.q_world_xyzw for _, a, _ in todo]))
        W_b = pose_matrices(np.array([b.p_world_m for _, _, b in todo]), np.array([b.q_world_xyzw for _, _, b in todo]))
        T1_inv = np.array([self._T_sensor_entity[valid[j].sensor_id] for j in idx])
        T3 = np.array([self._T_entity_marker[valid[j].marker_id] for j in idx])
        pred = T1_inv @ np.linalg.inv(W_a) @ W_b @ T3
        p_a = p2[idx]
        p_b = np.array([valid[j].p_sensor_marker_alt_m for j in idx])
        q_b = np.array([valid[j].q_sensor_marker_alt_xyzw() for j in idx])

        # The estimates' frame root (world) is exact; every other entity has the assumed attitude error,
        # plus what it may have turned and moved between its estimate's capture and this observation's
        # (a stale estimate must not pick the flipped solution: it leaves the observation undecided).
        def motion(est: EntityPose, md: MarkerData) -> tuple[float, float]:
            if est.name == est.frame:
                return 0.0, 0.0
            age_s = max(md.capture_time_us - est.capture_time_us, 0) / 1e6
            return float(np.hypot(self.attitude_sigma_rad, MAX_RATE_RAD_S * age_s)), MAX_SPEED_M_S * age_s

        move_a = np.array([motion(a, valid[j]) for j, a, _ in todo])
        move_b = np.array([motion(b, valid[j]) for j, _, b in todo])
        sigma_rad, sigma_m = ambiguity.prediction_sigmas(
            np.linalg.norm(p_a, axis=1), np.array([valid[j].sigma_m for j in idx]),
            np.hypot([a.sigma_m for _, a, _ in todo], move_a[:, 1]),
            np.hypot([b.sigma_m for _, _, b in todo], move_b[:, 1]), move_a[:, 0], move_b[:, 0],
        )  # fmt: skip
        verdicts, _, _ = ambiguity.resolve_arrays(
            ambiguity.Poses(p_a, q2[idx]), ambiguity.Poses(p_b, q_b),
            ambiguity.Poses(pred[:, :3, 3], Rotation.from_matrix(pred[:, :3, :3]).as_quat()),
            sigma_rad, sigma_m, self.gate_r2, self.min_likelihood_ratio,
        )  # fmt: skip
        for j, verdict in zip(idx, verdicts, strict=True):
            if verdict is Verdict.ALT:
                alt = Rotation.from_quat(valid[j].q_sensor_marker_alt_xyzw())
                det.R_sm[j] = alt.as_matrix()
                q2[j] = alt.as_quat()
                p2[j] = valid[j].p_sensor_marker_alt_m
                swapped.add(j)
                notes.append("ambiguity_swapped")
            if verdict.decided:
                notes.append("ambiguity_resolved")
            else:
                notes.append(f"ambiguity_{verdict.value}")
                if verdict is Verdict.TOO_CLOSE:
                    undecided.append(j)
                else:  # both far: the prediction contradicts the view
                    rejected[j] = Rejection.AMBIGUITY_UNRESOLVED
        self._cover(det, undecided, notes, rejected)
        return rejected, swapped

    def _cover(self, det: Detections, undecided: list[int], notes: list[str], rejected: dict[int, Rejection]) -> None:
        """The undecided observations whose two solutions lie within their detection's covariance become
        the pair's mixture (:func:`atlas_onboard.core.ambiguity.cover`), in place: pose, covariance, and a
        sigma grown as its camera-position spread grew (``ambiguity_covered``). The others, and those
        without a covariance, are rejected."""
        valid, C_sm = det.records, det.C_sm
        idx = [j for j in undecided if C_sm is not None or valid[j].covariance]
        for j in set(undecided) - set(idx):
            rejected[j] = Rejection.AMBIGUITY_UNRESOLVED
        if not idx:
            return
        C = C_sm[idx] if C_sm is not None else upper_to_matrix(np.array([valid[j].covariance for j in idx]))
        primary = ambiguity.Poses(det.p_sm[idx], det.q_sm_xyzw[idx])
        alt = ambiguity.Poses(
            np.array([valid[j].p_sensor_marker_alt_m for j in idx]),
            np.array([valid[j].q_sensor_marker_alt_xyzw() for j in idx]),
        )
        mixed = ambiguity.cover(primary, alt, C, self.cover_r2)
        for k, j in enumerate(idx):
            if not mixed.close[k]:
                rejected[j] = Rejection.AMBIGUITY_UNRESOLVED
                continue
            md, R_old, p_old = valid[j], det.R_sm[j].copy(), det.p_sm[j].copy()
            det.q_sm_xyzw[j] = mixed.pose.q_xyzw[k]
            det.R_sm[j] = Rotation.from_quat(mixed.pose.q_xyzw[k]).as_matrix()
            det.p_sm[j] = mixed.pose.p_m[k]
            C_new = mixed.covariance[k]
            scale = camera_spread(det.p_sm[j], det.R_sm[j], C_new) / max(camera_spread(p_old, R_old, C[k]), 1e-300)
            valid[j] = replace(md, covariance=matrix_to_upper(C_new), sigma_m=md.sigma_m * math.sqrt(max(scale, 1.0)))
            if C_sm is not None:
                C_sm[j] = C_new
            notes.append("ambiguity_covered")

    def _by_tilt(
        self, det: Detections, notes: list[str], rejected: dict[int, Rejection], swapped: set[int]
    ) -> set[int]:
        """The MegaTag2 step: observations between the attitude's entity and the world that carry both
        solutions, decided by gravity (swapped in place, or rejected). Returns the indices decided.

        A kept solution of the own camera with a detection covariance is then updated with the
        autopilot's up vector (:func:`atlas_onboard.core.attitude.constrain_tilt`): its record gets
        the new covariance and a sigma scaled as its camera-position spread shrank, ``det.C_sm`` too."""
        valid, R2, p2, q2, C_sm = det.records, det.R_sm, det.p_sm, det.q_sm_xyzw, det.C_sm
        up_at, own = self._up_at, self._up_entity
        if up_at is None:
            return set()
        decided: set[int] = set()
        for j, md in enumerate(valid):
            observer, observed = self._sensor_entity[md.sensor_id], self._marker_entity[md.marker_id]
            # The own camera's view of another entity's marker: that entity's estimated attitude
            # stands in for the world's (its heading error turns no up vector; its tilt error counts).
            peer = self._peer_tilt(md, observer == own and observed not in (WORLD, own), observed)
            if peer is None and not (
                (observer == own and observed == WORLD) or (observer == WORLD and observed == own)
            ):
                continue
            if md.alt_state() is not AltState.VALID:
                continue
            up = up_at(md.capture_time_us)
            if up is None:
                notes.append("attitude_unavailable")
                continue
            R_alt = Rotation.from_quat(md.q_sensor_marker_alt_xyzw()).as_matrix()
            R_pair = np.stack([R2[j], R_alt])  # R_sensor_marker of both solutions
            M_es = self._T_entity_sensor[md.sensor_id][:3, :3]
            M_em = self._T_entity_marker[md.marker_id][:3, :3]
            if peer is not None:  # R_world_body = R_world_peer R_peer_marker R_sensor_marker^-1 R_body_sensor^-1
                R_wb = peer.R_world_entity @ M_em @ R_pair.transpose(0, 2, 1) @ M_es.T
            elif observer == own:  # R_world_body = R_world_marker R_sensor_marker^-1 R_body_sensor^-1
                R_wb = M_em @ R_pair.transpose(0, 2, 1) @ M_es.T
            else:  # a world camera sees the own marker: R_world_body = R_world_sensor R_sensor_marker R_body_marker^-1
                R_wb = M_es @ R_pair @ M_em.T
            rng = float(np.linalg.norm(p2[j]))
            obs_sigma = rotation_sigma(md, rng) if peer is None else math.hypot(rotation_sigma(md, rng), peer.sigma_rad)
            check = attitude.choose_by_tilt(Rotation.from_matrix(R_wb[0]), Rotation.from_matrix(R_wb[1]), up, obs_sigma)
            notes.append(f"attitude_{check.verdict.value}")
            if check.verdict is attitude.TiltVerdict.ALT:
                R2[j], q2[j] = R_alt, md.q_sensor_marker_alt_xyzw()
                p2[j] = md.p_sensor_marker_alt_m
                swapped.add(j)
            elif check.verdict is attitude.TiltVerdict.NEITHER:
                rejected[j] = Rejection.ATTITUDE_MISMATCH
            if check.verdict is not attitude.TiltVerdict.BOTH:
                decided.add(j)
            kept = check.verdict is attitude.TiltVerdict.PRIMARY or (
                check.verdict is attitude.TiltVerdict.BOTH and not md.ambiguity_ratio > self.threshold
            )
            if kept and observer == own and peer is None and md.covariance:
                C = C_sm[j] if C_sm is not None else upper_to_matrix(np.array([md.covariance]))[0]
                new = attitude.constrain_tilt(attitude.TagPose(p2[j], R2[j], C), M_es, M_em, up)
                scale = camera_spread(new.p_sensor_marker_m, new.R_sensor_marker, new.covariance) / max(
                    camera_spread(p2[j], R2[j], C), 1e-300
                )
                R2[j], p2[j] = new.R_sensor_marker, new.p_sensor_marker_m
                q2[j] = Rotation.from_matrix(new.R_sensor_marker).as_quat()
                valid[j] = replace(
                    md, covariance=matrix_to_upper(new.covariance), sigma_m=md.sigma_m * math.sqrt(min(scale, 1.0))
                )
                if C_sm is not None:
                    C_sm[j] = new.covariance
                notes.append("attitude_constrained")
        return decided

    def _peer_tilt(self, md: MarkerData, applies: bool, entity: str) -> PeerTilt | None:
        """The observed entity's estimated attitude for the tilt check of an own view of it (None when
        it does not apply or the entity has no world pose with a covariance), its tilt sigma grown by
        what it may have tilted since (a quadrotor's tilt follows its acceleration)."""
        est = self._estimates.get(entity) if applies else None
        if est is None or est.frame != WORLD or est.covariance is None:
            return None
        age_s = abs(md.capture_time_us - est.capture_time_us) / 1e6
        att = float(np.sqrt(max(np.linalg.eigvalsh(est.covariance[3:5, 3:5])[-1], 0.0)))
        return PeerTilt(Rotation.from_quat(est.q_world_xyzw).as_matrix(), math.hypot(att, TILT_RATE_RAD_S * age_s))
