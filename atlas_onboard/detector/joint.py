"""The joint solve of the markers of one entity seen together: a marker that does not fit with the others
is left out. Its result (:class:`~atlas_onboard.detector.records.JointResult`) goes to the live check of the
world file (:mod:`atlas_onboard.detector.worldcheck`, which counts, logs and announces the verdicts). The
detector (:class:`atlas_onboard.detector.pipeline.Detector`) holds a :class:`JointSolve` and calls it."""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform

from atlas_onboard.config import WORLD, SensorConfig, WorldConfig
from atlas_onboard.core.shutter import CameraMotion
from atlas_onboard.detector import joint_covariance, joint_motion, pose
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.joint_motion import MovingPose
from atlas_onboard.detector.records import JointResult, LeftOut, SingleSolve, marker_data
from atlas_onboard.detector.rotations import matrix_from_quat, quat_from_matrix, rotvec_from_matrix
from atlas_onboard.detector.search import side

_logger = logging.getLogger(__name__)

JOINT_MISFIT = 3.0  # a joint fit this many times worse than its worst single square is not used


@dataclass(frozen=True)
class Disagreement:
    """A marker that does not fit with the other markers of its entity in one image: its offset is the
    distance between where its own square puts it and where the others place it (camera frame, m)."""

    entity: str
    marker_id: int
    offset_m: float
    capture_time_us: int


def entity_in_camera(
    p_cm: NDArray[np.float64], q_cm_xyzw: NDArray[np.float64], R_em: NDArray[np.float64], p_em: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """T_camera_entity = T_camera_marker T_entity_marker^-1 as a rotation vector and a translation, from a
    marker's pose in the camera (``p_cm``, quaternion ``q_cm_xyzw``) and in its entity (``R_em``, ``p_em``),
    in plain matrices (a scipy transform built for one pose costs more than the joint solve it starts)."""
    R_ce = matrix_from_quat(q_cm_xyzw) @ R_em.T
    return rotvec_from_matrix(R_ce), p_cm - R_ce @ p_em


@dataclass
class JointSolve:
    """The joint solve of one sensor's detector, held by :class:`~atlas_onboard.detector.pipeline.Detector`:
    the robust leave-one-out, the joint solution and its covariance, and the sensor's MarkerData records.

    ``sensor``, ``world``, ``calibration``: the detector's; ``marker_pose``: the pose of each marker it sees
    in its entity (``T_entity_marker``); ``sizes``: their sides (m); ``counters``: the detector's (shared).
    """

    sensor: SensorConfig
    world: WorldConfig
    calibration: Calibration
    marker_pose: Mapping[int, RigidTransform]
    sizes: Mapping[int, float]
    counters: Counter[str]
    motion: CameraMotion | None = field(default=None, init=False)
    """The frame's camera motion (:meth:`CameraMotionModel.at`), set by the detector before each frame's solves."""
    _corners: dict[int, NDArray[np.float64]] = field(default_factory=dict, init=False, repr=False)
    _frames: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]] = field(
        default_factory=dict, init=False, repr=False
    )

    def robust(self, ids: list[int], singles: dict[int, SingleSolve], capture_time_us: int) -> JointResult:
        """The entity's observation from the markers that fit together, and the ids used.

        When all of them do not fit (:meth:`solve`), the marker whose removal fits the rest best is
        left out, again while they do not fit and at least two remain: a moved or mis-measured marker
        costs only itself. Two markers that disagree cannot say which of them moved: neither is used
        (they are the result's ``misfit_pair``). The result's ``used`` is all ids when the joint solve
        failed (the squares are then reported one by one), None when no subset of two or more fits.
        """
        md, misfit = self.solve(ids, singles, capture_time_us)
        if md is not None or not misfit:
            return JointResult(md, ids)
        used = list(ids)
        left_out: list[LeftOut] = []
        while len(used) > 2:
            trials = []
            for m in used:
                rest = [i for i in used if i != m]
                md_r, misfit_r, err = self.solve(rest, singles, capture_time_us, count=False, with_error=True)
                if md_r is not None or misfit_r:
                    trials.append((err, m, rest, md_r))
            if not trials:
                break
            _, m, used, md = min(trials, key=lambda t: t[0])
            left_out.append(self._left_out(m, used, singles))
            if md is not None:
                self.counters["joint"] += 1
                self.counters["joint_without_disagreeing"] += 1
                return JointResult(md, used, left_out)
        if len(used) == 2:
            a, b = used
            return JointResult(None, None, left_out, [a, b], self._left_out(b, [a], singles))
        return JointResult(None, None, left_out, list(used))

    def offset(self, m: int, others: list[int], singles: dict[int, SingleSolve]) -> NDArray[np.float64] | None:
        """(3,) where marker ``m``'s own square is minus where the joint pose of ``others`` puts it,
        in the entity's frame (m); None when the others cannot be solved."""
        sol = self.solution(others, singles)
        if sol is None:
            return None
        R_ce = cv2.Rodrigues(np.asarray(sol[0], dtype=np.float64).reshape(3, 1))[0]
        predicted = sol[1] + R_ce @ self._frame_of(m)[1]
        return R_ce.T @ (singles[m].pose.p_m - predicted)

    def _left_out(self, m: int, others: list[int], singles: dict[int, SingleSolve]) -> LeftOut:
        """Marker ``m`` left out: how far its own square is from where the joint pose of ``others`` puts it."""
        offset = self.offset(m, others, singles)
        return LeftOut(m, offset, math.nan if offset is None else float(np.linalg.norm(offset)))

    def _corners_m(self, m: int) -> NDArray[np.float64]:
        """Marker ``m``'s corners (4, 3) in its entity's frame (m), kept (read-only)."""
        got = self._corners.get(m)
        if got is None:
            got = self.marker_pose[m].apply(pose.object_corners(self.sizes[m]))
            got.flags.writeable = False
            self._corners[m] = got
        return got

    def _frame_of(self, m: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Marker ``m``'s pose in its entity (``T_entity_marker``) as a rotation matrix and a translation, kept."""
        got = self._frames.get(m)
        if got is None:
            T = self.marker_pose[m]
            got = (T.rotation.as_matrix(), T.translation)
            self._frames[m] = got
        return got

    def solution(self, ids: list[int], singles: dict[int, SingleSolve]) -> tuple | None:
        """rvec, tvec (T_camera_entity), RMS error and sigma of the joint solve of ``ids``, or None."""
        obj = np.vstack([self._corners_m(m) for m in ids])
        img = np.vstack([singles[m].corners for m in ids])
        # Start from the least ambiguous single solution, moved to the entity frame:
        # T_camera_entity = T_camera_marker T_entity_marker^-1, in plain matrices.
        best = min(ids, key=lambda m: singles[m].pose.ambiguity if np.isfinite(singles[m].pose.ambiguity) else 1.0)
        mp = singles[best].pose
        guess = entity_in_camera(mp.p_m, mp.q_xyzw, *self._frame_of(best))
        fam = self.world.markers[ids[0]].family
        return pose.solve_joint(obj, img, self.calibration.K, pose.model_sigma_px(fam), guess)

    def solve(
        self,
        ids: list[int],
        singles: dict[int, SingleSolve],
        capture_time_us: int,
        count: bool = True,
        with_error: bool = False,
    ) -> tuple:
        """The entity's observation from all its squares at once; (None, False) when the solve
        failed (the squares are then reported one by one), (None, True) when they do not fit together.
        ``with_error``: the joint RMS error relative to its limit as a third element."""
        anchor = ids[0]
        model_sigma_px = pose.model_sigma_px(self.world.markers[anchor].family)
        sol = self.solution(ids, singles)
        if sol is None:
            self.counters["joint_failed"] += count
            return (None, False, math.inf) if with_error else (None, False)
        rvec, tvec, err, sigma = sol
        R_ea, p_ea = self._frame_of(anchor)
        R_ce = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64).reshape(3, 1))[0]
        R_ca, p_ca = R_ce @ R_ea, tvec + R_ce @ p_ea
        obj = np.vstack([self._corners_m(m) for m in ids])
        squares = [singles[m] for m in ids]
        moving = self._solve_moving(ids, squares, (obj - p_ea) @ R_ea, R_ca, p_ca)
        if moving is not None:  # the shear explained by the motion, not left in the residual
            R_ca, p_ca, err = moving.R, moving.p, moving.rms_px
        # Markers that do not fit together as the world file places them (a misplaced marker, a bad
        # corner, motion blur that moves each square differently) give a joint fit far worse than
        # each square's own: the joint pose is then wrong in a way no sigma describes.
        worst_single = max(singles[m].pose.reprojection_error_px for m in ids)
        # A moving camera's shear that its rates leave uncertain (detector.motion) widens the limit alike.
        limit = JOINT_MISFIT * max(worst_single, math.hypot(model_sigma_px, max(singles[m].motion_px for m in ids)))
        if err > limit:
            self.counters["joint_misfit"] += count
            return (None, True, err / limit) if with_error else (None, True)
        # The anchor's pose T_camera_entity T_entity_anchor, and its covariance: the same corners, in the
        # anchor's frame.
        fit = pose.CornerFit(R_ca, p_ca, (obj - p_ea) @ R_ea, self.calibration.K)
        if moving is not None:
            cov = moving.pose_covariance()
        elif all(s.corner_cov is not None for s in squares):
            cov = self._covariance(fit, squares)
        else:
            model_px = pose.corner_noise_px(model_sigma_px, float(np.median([side(s.corners) for s in squares])))
            measured = [s.measured_px for s in squares]
            sigma_px = max(measured) if min(measured) > 0 else model_px
            stretches = [s.stretch for s in squares]
            stretch = None if any(x is None for x in stretches) else np.concatenate(stretches)
            cov = pose.pose_covariance(fit, sigma_px, err, stretch)
        self.counters["joint"] += count
        q = quat_from_matrix(R_ca)
        md = marker_data(self.sensor.id, anchor, p_ca, q, sigma, err, 0.0, capture_time_us, None, cov)
        return (md, False, err / limit) if with_error else (md, False)

    def _solve_moving(
        self,
        ids: list[int],
        squares: list[SingleSolve],
        obj_anchor: NDArray[np.float64],
        R_ca: NDArray[np.float64],
        p_ca: NDArray[np.float64],
    ) -> MovingPose | None:
        """The anchor's pose with the camera's rate and velocity (:func:`joint_motion.solve_moving`) when a
        rolling shutter saw the world's markers while moving (their corners timed by their rows), from the
        joint solution of the corrected corners (``R_ca``, ``p_ca``); else None. Only the world's: another
        entity's markers move with it, which the camera's own motion prior does not describe."""
        timed = [s.timed for s in squares]
        if self.motion is None or any(t is None for t in timed) or self.world.markers[ids[0]].entity != WORLD:
            return None
        cal = self.calibration
        img = [t.corners for t in timed if t is not None]
        residuals = joint_covariance.lens_residual_covariances(img, cal.K, cal.dist, cal.fisheye)
        covs = [t.covariance + r for t, r in zip(timed, residuals, strict=True) if t is not None]
        dt = np.concatenate([t.dt_s for t in timed if t is not None])
        return joint_motion.solve_moving(obj_anchor, np.vstack(img), dt, covs, cal.K, self.motion, R_ca, p_ca)

    def _covariance(self, fit: pose.CornerFit, squares: list[SingleSolve]) -> NDArray[np.float64] | None:
        """The joint pose's 6x6 (``fit``: the anchor's pose and the squares' corners in its frame) from the
        squares' corners (:func:`joint_covariance.joint_covariance`), each square's block its edge fit's
        covariance plus the lens model's residual where it lies (:func:`joint_covariance.lens_residual_covariance`):
        the squares' relative places, on which the joint rotation rests, are only as good as the lens model
        between them."""
        cal = self.calibration
        residuals = joint_covariance.lens_residual_covariances(
            [s.corners for s in squares], cal.K, cal.dist, cal.fisheye
        )
        covs = [s.corner_cov + r for s, r in zip(squares, residuals, strict=True)]
        img = np.vstack([s.corners for s in squares])
        return joint_covariance.joint_covariance(fit, img, covs)
