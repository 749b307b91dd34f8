"""A camera's motion at each frame, and its corners moved to the frame's stamp (:mod:`atlas_onboard.core.shutter`).

The rate: the autopilot's (ATTITUDE's body rates), which corrects the image; without them, the camera's
recent own poses bound it (not corrected: a rate from poses a frame apart is too noisy to correct by,
but says how large the shear may be), else ``rate_bound_dps``.

The velocity: the autopilot's (LOCAL_POSITION_NED's, turned into the body's axes by its attitude:
:mod:`atlas_onboard.core.velocity`), which its IMU keeps through a gap in the markers, for a rolling shutter;
without it (or for a global shutter, whose only use of a velocity is the size of its timing term) a
straight-line fit through the camera's own poses of the last few frames, from the world markers it saw
(each frame's best single-marker pose), relative to what it sees: there in every mode (any ``filter``,
image folders, no autopilot), in the camera's thread at the frame's instant. A velocity error enters only
times a corner's readout offset (millimetres a second over milliseconds), where its covariance is carried.
A joint solve of several world markers measures the motion with the pose (:mod:`.joint_motion`), from these
priors.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform

from atlas_onboard.config import WORLD, CameraConfig, SensorConfig
from atlas_onboard.config.settings import READOUT_BOTTOM_UP
from atlas_onboard.core.ekf import MANOEUVRE_ACCEL_SIGMA
from atlas_onboard.core.markerdata import MarkerData, matrix_to_upper, upper_to_matrix
from atlas_onboard.core.shutter import (
    BodyRate,
    BodyVelocity,
    CameraMotion,
    RowClock,
    planar_depths_many,
    shear_covariance,
    squares_to_stamp,
    timing_pose_covariance,
    timing_sigma_s,
)
from atlas_onboard.detector import pose
from atlas_onboard.detector.pose import object_corners
from atlas_onboard.detector.records import TimedCorners
from atlas_onboard.detector.rotations import matrix_from_quat, rotvec_from_matrix
from atlas_onboard.worker import RateAt, VelocityAt

WINDOW_US = 150_000  # poses this recent fit the velocity (about five frames at 30 Hz)
STALE_US = 300_000  # poses older than this give no velocity (fewer than two in WINDOW_US: the newest two within it)
ANGULAR_ACCEL_SIGMA = 6.0  # rad/s^2 per axis: how far a drone's rate changes over the history's span
SPEED_BOUND_MPS = 1.0  # per axis, when the camera's poses do not give a velocity
MIN_SPAN_S = 0.01  # recent poses spanning less than this are not a camera's frames (unrelated images)
MAX_SPEED_MPS = 15.0  # a history implying more than this (or MAX_RATE_RAD_S) is a jump, not a motion
MAX_RATE_RAD_S = 15.0
DEAD_RECKONING_ACCEL_M_S2 = 0.05
"""Per axis: how fast an autopilot's velocity drifts while its EKF has no vision (its accelerometers' residual
bias and its tilt error times gravity): counted from the camera's newest world marker, after VISION_GRACE_US."""
VISION_GRACE_US = 200_000  # an EKF fuses vision this late without dead-reckoning between


@dataclass(frozen=True, slots=True)
class CorrectedCorners:
    """A square's corners moved to the stamp (undistorted pixels, (4, 2)), their (8, 8) covariance with
    the motion's, and the RMS corner noise of the motion's shear alone (px): what no rigid pose absorbs,
    so what may make squares seen together misfit (the timing's share moves them all alike)."""

    corners: NDArray[np.float64]
    covariance: NDArray[np.float64]
    shear_px: float


@dataclass(frozen=True, slots=True)
class SeenSquare:
    """A world marker as the frame found it, for the camera's own motion history: its corners in the
    (distorted) image, whose rows set their instants, and undistorted (not moved to the stamp), with
    their own noise (``sigma_px``, the (8, 8) ``covariance``), the undistortion's ``stretch`` and what
    :func:`pose.solve` needs besides. ``solved``: the detector's pose of the square from its corners as
    :meth:`CameraMotionModel.correct_all` gave them, which are these when the frame's motion moved nothing."""

    T_world_marker: RigidTransform
    corners_px: NDArray[np.float64]
    undistorted_px: NDArray[np.float64]
    sigma_px: float
    covariance: NDArray[np.float64] | None
    stretch: NDArray[np.float64] | None
    size_m: float
    model_sigma_px: float
    K: NDArray[np.float64]
    solved: pose.MarkerPose | None = None


@dataclass(frozen=True, slots=True)
class _Seen:
    t_us: int
    p_world_m: NDArray[np.float64]
    R_world_camera: NDArray[np.float64]  # (3, 3)
    sigma_p_m: float
    sigma_theta_rad: float


@dataclass(frozen=True, slots=True)
class _History:
    """The camera's motion from its own recent poses (camera frame): rate and velocity with variances."""

    omega: NDArray[np.float64]
    omega_var: float
    velocity: NDArray[np.float64]
    velocity_var: float

    @staticmethod
    def of(recent: list[_Seen], t_us: int) -> _History | None:
        """From the poses of the last ``WINDOW_US`` before ``t_us``: None when too few, too close in time
        (frames of a camera, not unrelated images), stale, or implausible for a drone (a jump)."""
        if len(recent) < 2 or t_us - recent[-1].t_us > STALE_US:
            return None
        a, b = recent[0], recent[-1]
        span = (b.t_us - a.t_us) * 1e-6
        if span < MIN_SPAN_S:
            return None
        w = rotvec_from_matrix(a.R_world_camera.T @ b.R_world_camera) / span
        noise = 2.0 * max(a.sigma_theta_rad, b.sigma_theta_rad) ** 2 / span**2
        lag = (ANGULAR_ACCEL_SIGMA * ((t_us - a.t_us) * 1e-6 - span / 2.0)) ** 2
        t = np.array([(s.t_us - t_us) * 1e-6 for s in recent])
        p = np.array([s.p_world_m for s in recent])
        tc = t - t.mean()
        v_world = tc @ (p - p.mean(axis=0)) / float(tc @ tc)
        if np.linalg.norm(v_world) > MAX_SPEED_MPS or np.linalg.norm(w) > MAX_RATE_RAD_S:
            return None
        sigma_p = max(s.sigma_p_m for s in recent)
        v_var = sigma_p**2 / float(tc @ tc) + (MANOEUVRE_ACCEL_SIGMA * float(-t.mean())) ** 2
        R = recent[-1].R_world_camera
        return _History(w, noise + lag, R.T @ v_world, v_var)


def body_rate_at(rate_at: RateAt | None, t_us: int) -> BodyRate | None:
    """The autopilot's body rate at a capture (its gyros', ``rate_at``), or None without one. Attitudes
    alone give none to correct by: those after the stamp have not come when the frame is solved (the
    newest held makes a turning camera look still), and an attitude's noise differenced over a sample
    spacing (0.5 deg over 40 ms: 0.3 rad/s) is as large as the turn; the camera's own poses bound it."""
    return rate_at(t_us) if rate_at is not None else None


def body_velocity_at(velocity_at: VelocityAt | None, t_us: int) -> BodyVelocity | None:
    """The autopilot's velocity at a capture in the body's axes (``velocity_at``), or None without one."""
    return velocity_at(t_us) if velocity_at is not None else None


class CameraMotionModel:
    """One camera's time model and motion: corners moved to the stamp, the motion's covariance added."""

    def __init__(
        self, camera: CameraConfig | None, T_body_sensor: RigidTransform, height_px: int, static: bool = False
    ) -> None:
        """``T_body_sensor``: the camera's mount on its body; ``static``: a camera fixed in the world (on the
        world entity), which does not move at all; the markers' own motion (a drone's) is not modelled."""
        cam = camera or CameraConfig()
        self.static = static
        self.clock = RowClock(cam.readout_ms * 1e-3, height_px, cam.readout_order == READOUT_BOTTOM_UP)
        self.timing_s = timing_sigma_s(cam.stamp_sigma_ms * 1e-3, cam.exposure_ms * 1e-3)
        self.rate_bound = math.radians(cam.rate_bound_dps)
        self.R_body_sensor = T_body_sensor.rotation
        self._M_sensor_body = self.R_body_sensor.inv().as_matrix()  # body axes into the camera's, made once
        self.p_body_sensor_m = np.asarray(T_body_sensor.translation, dtype=float)
        self._seen: deque[_Seen] = deque(maxlen=8)

    @staticmethod
    def of(sensor: SensorConfig, height_px: int) -> CameraMotionModel:
        """The model of ``sensor``'s camera on its mount; fixed when the sensor is the world's."""
        return CameraMotionModel(sensor.camera, sensor.T_entity_sensor, height_px, sensor.entity == WORLD)

    def at(self, t_us: int, rate: BodyRate | None, velocity: BodyVelocity | None = None) -> CameraMotion:
        """The camera's motion at the frame stamped ``t_us``, given the autopilot's rate and velocity (or None)."""
        if self.static:
            return CameraMotion(omega_known=True, velocity_known=True, timing_sigma_s=self.timing_s)
        past = [s for s in self._seen if 0 < t_us - s.t_us <= STALE_US]
        recent = [s for s in past if t_us - s.t_us <= WINDOW_US]
        if len(recent) < 2:  # frames missed or markers out of view: the newest two, their age in the covariance
            recent = past[-2:]
        history = _History.of(recent, t_us)
        if rate is not None:
            M = self._M_sensor_body
            w, w_cov, w_known = M @ np.asarray(rate.omega_flu, dtype=float), M @ rate.cov @ M.T, True
        elif history is not None:
            w, w_cov, w_known = history.omega, history.omega_var * np.eye(3), False
        else:
            w, w_cov, w_known = np.zeros(3), self.rate_bound**2 * np.eye(3), False
        v, v_cov, v_known = np.zeros(3), SPEED_BOUND_MPS**2 * np.eye(3), False
        if velocity is not None and self.clock.readout_s > 0.0:
            v, v_cov = self._camera_velocity(velocity, w, w_cov, w_known)
            v_known = True
            if self._seen:  # the autopilot has had no vision from this camera since its newest world marker
                blind_s = max(t_us - self._seen[-1].t_us - VISION_GRACE_US, 0) * 1e-6
                v_cov = v_cov + (DEAD_RECKONING_ACCEL_M_S2 * blind_s) ** 2 * np.eye(3)
        elif history is not None:
            v, v_cov, v_known = history.velocity, history.velocity_var * np.eye(3), True
        # The timing's image motion needs a motion estimate; with bounds alone (no rate, no recent poses:
        # the first frames, or unrelated images) it is left out rather than charged at the bounds.
        timing = self.timing_s if (rate is not None or v_known) else 0.0
        return CameraMotion(w, w_cov, v, v_cov, w_known, v_known, timing)

    def _camera_velocity(
        self, velocity: BodyVelocity, w: NDArray[np.float64], w_cov: NDArray[np.float64], w_known: bool
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The camera's velocity (camera axes, m/s) and its covariance from the body's: the body's plus its
        turn ``w`` (camera axes) swinging the mount's lever arm, ``w x p``; a rate not known (a bound) adds
        its second moment's swing to the covariance instead."""
        M = self._M_sensor_body
        p = M @ self.p_body_sensor_m  # the lever arm in the camera's axes
        P = np.array([[0.0, p[2], -p[1]], [-p[2], 0.0, p[0]], [p[1], -p[0], 0.0]])  # w x p = P w
        v, cov = M @ np.asarray(velocity.velocity_flu, dtype=float), M @ np.asarray(velocity.cov, dtype=float) @ M.T
        if w_known:
            return v + P @ w, cov + P @ w_cov @ P.T
        return v, cov + P @ (np.outer(w, w) + w_cov) @ P.T

    def moving(self, motion: CameraMotion) -> bool:
        """Whether ``motion`` moves a frame's corners: a rolling shutter on a camera in motion (else
        :meth:`correct_all` leaves them as they are)."""
        if self.clock.readout_s <= 0.0 or self.clock.height_px <= 1:
            return False
        parts = (motion.omega_used(), motion.velocity_used(), motion.omega_error(), motion.velocity_error())
        return any(np.any(m) for m in parts)

    def correct(
        self,
        motion: CameraMotion,
        corners_px: NDArray[np.float64],
        undistorted: NDArray[np.float64],
        corner_cov: NDArray[np.float64],
        K: NDArray[np.float64],
        size_m: float,
    ) -> CorrectedCorners:
        """A square's undistorted corners (4, 2) moved to the stamp, and their (8, 8) covariance with the
        motion's added. ``corners_px``: where they are in the (distorted) image, whose rows set their
        instants; the translation's depths are the square's own (:func:`square_to_stamp`)."""
        return self.correct_all(motion, [corners_px], [undistorted], [corner_cov], K, [size_m])[0]

    def correct_all(
        self,
        motion: CameraMotion,
        corners_px: Sequence[NDArray[np.float64]],
        undistorted: Sequence[NDArray[np.float64]],
        corner_cov: Sequence[NDArray[np.float64]],
        K: NDArray[np.float64],
        sizes_m: Sequence[float],
    ) -> list[CorrectedCorners]:
        """:meth:`correct` of a frame's squares at once, each as if corrected alone. A frame read at one
        instant (a global shutter), or a camera that does not move, has nothing to correct: no motion, no
        shear, the covariances as they are."""
        if not len(sizes_m):
            return []
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        c = np.array([cx, cy])
        f = np.array([fx, fy])
        x = (np.asarray(undistorted, dtype=float) - c) / f
        obj = np.array([object_corners(size)[:, :2] for size in sizes_m])
        if not self.moving(motion):
            # The corners as :func:`to_stamp` returns them unmoved (x z / z, rounding included): the same bits.
            z = planar_depths_many(x, obj)
            z[np.isnan(z).any(axis=1)] = 1.0
            moved = x * z[..., None] / z[..., None] * f + c
            return [CorrectedCorners(moved[k], np.array(cov, dtype=float), 0.0) for k, cov in enumerate(corner_cov)]
        dt = self.clock.dt_s(np.asarray(corners_px, dtype=float)[..., 1])
        x0, z = squares_to_stamp(x, obj, dt, motion)
        shear = shear_covariance(x0, z, dt, motion, fx, fy)
        cov = np.asarray(corner_cov, dtype=float) + shear
        moved = x0 * f + c
        shear_px = np.sqrt(np.trace(shear, axis1=1, axis2=2) / cov.shape[1])
        return [CorrectedCorners(moved[k], cov[k], float(shear_px[k])) for k in range(len(cov))]

    def timed(
        self,
        motion: CameraMotion,
        corners_px: Sequence[NDArray[np.float64]],
        undistorted: Sequence[tuple[NDArray[np.float64], NDArray[np.float64]]],
    ) -> list[TimedCorners | None]:
        """Each square's corners as seen (undistorted, with the edge fit's (8, 8) covariance: ``undistorted``),
        timed by their rows in the image (``corners_px``), when ``motion`` moves the frame's corners (else
        None each: nothing for a joint solve to fit the motion with)."""
        if not len(corners_px) or not self.moving(motion):
            return [None] * len(corners_px)
        dts = self.clock.dt_s(np.asarray(corners_px, dtype=float)[..., 1])
        return [
            TimedCorners(np.asarray(c, dtype=float), np.asarray(cov, dtype=float), dt)
            for (c, cov), dt in zip(undistorted, dts, strict=True)
        ]

    def with_timing(self, md: MarkerData, motion: CameraMotion) -> MarkerData:
        """``md`` with the frame's timing uncertainty in its covariance and sigma (:func:`timing_pose_covariance`):
        added to the frame's poses once checked, since it moves every marker alike."""
        if motion.timing_sigma_s <= 0.0 or not md.covariance:
            return md
        w, x, y, z = md.q_sensor_marker_wxyz
        R = matrix_from_quat(np.array([x, y, z, w]))
        C = upper_to_matrix(np.asarray(md.covariance)) + timing_pose_covariance(
            np.asarray(md.p_sensor_marker_m), R, motion
        )
        # The camera's position moves by its velocity over the timing error.
        extra = motion.timing_sigma_s**2 * float(np.linalg.eigvalsh(motion.velocity_second_moment())[-1])
        return replace(md, covariance=matrix_to_upper(C), sigma_m=math.sqrt(md.sigma_m**2 + extra))

    def observe(self, t_us: int, seen: list[SeenSquare], motion: CameraMotion | None = None) -> None:
        """The frame's world markers as found (corners not moved by this model): the best one's own pose
        gives the camera's pose at the instant its centre row was read, which joins the history. Where the
        frame's ``motion`` moved no corner, a square's ``solved`` pose is that pose, taken as it is.

        Open loop: a pose corrected by this model's velocity would carry that velocity's error into the
        next velocity fit (and a single square's pose moves far for a little shear), a loop that grows.
        Uncorrected, a square's pose is the camera's at its rows' mean instant, off only by the shear
        within the square, which changes slowly with the motion and the view (a slope hardly sees it)."""
        best = None
        unmoved = motion is not None and not self.moving(motion)
        for sq in seen:
            mp = sq.solved if unmoved and sq.solved is not None else None
            if mp is None:
                mp = pose.solve(
                    sq.undistorted_px, sq.size_m, sq.K, sq.model_sigma_px, sq.stretch, sq.sigma_px, sq.covariance
                )
            if mp is None or mp.covariance is None or (best is not None and mp.sigma_m >= best[1].sigma_m):
                continue
            best = (sq, mp)
        if best is None:
            return
        sq, mp = best
        dt = float(self.clock.dt_s(np.array([float(np.mean(np.asarray(sq.corners_px, dtype=float)[:, 1]))]))[0])
        T_wm = sq.T_world_marker.as_matrix()
        R_wc = T_wm[:3, :3] @ matrix_from_quat(mp.q_xyzw).T
        p_wc = T_wm[:3, 3] - R_wc @ mp.p_m
        sigma_theta = math.sqrt(max(float(np.linalg.eigvalsh(mp.covariance[3:, 3:]).max()), 0.0))
        self._seen.append(_Seen(t_us + round(dt * 1e6), p_wc, R_wc, mp.sigma_m, sigma_theta))
