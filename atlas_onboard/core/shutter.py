"""A camera that knows time: when each row was exposed, where a moving camera would have seen each corner
at its frame's stamp, and the corner covariance of what the motion leaves uncertain.

The stamp of a frame is the middle of the exposure of its middle row. A rolling shutter starts row r's
exposure ``readout * r / (H - 1)`` after row 0's (``top_down``; reversed for ``bottom_up``), so row r is
seen ``dt(r) = readout * (r - (H - 1) / 2) / (H - 1)`` after the stamp (a global shutter: 0).

The camera turns at ``omega`` (rad/s, camera frame, OpenCV axes) and moves at ``v`` (m/s, camera frame)
relative to what it sees, both constant over one frame (tens of milliseconds). A point seen at ``P(t)``
(camera frame at t) is at ``P(0) = exp([omega] t) P(t) + v t`` at the stamp: exact for constant omega and
v, since ``R(t) = R(0) exp([omega] t)`` and ``p(t) = p(0) + R(0) v t``.

Pure: numpy and scipy; times are passed in.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

_ZERO3 = np.zeros(3)


@dataclass(frozen=True, slots=True)
class RowClock:
    """When each row of a frame is seen, relative to the frame's stamp."""

    readout_s: float  # start of the first row's exposure to the start of the last row's (0: global shutter)
    height_px: int
    bottom_up: bool = False  # the last row is read first (a sensor mounted upside down)

    def dt_s(self, rows_px: NDArray[np.float64]) -> NDArray[np.float64]:
        """Seconds from the stamp to the mid-exposure of the (distorted, sub-pixel) rows ``rows_px``."""
        rows = np.asarray(rows_px, dtype=float)
        if self.readout_s <= 0.0 or self.height_px <= 1:
            return np.zeros_like(rows)
        half = (self.height_px - 1) / 2.0
        dt = self.readout_s * (rows - half) / (self.height_px - 1)
        return -dt if self.bottom_up else dt


@dataclass(frozen=True, slots=True)
class CameraMotion:
    """The camera's motion over one frame relative to the markers it sees, in the camera frame.

    ``omega`` (rad/s) and ``velocity`` (m/s) with their covariances. Known: the value is an estimate and
    the image is corrected by it (the covariance is its error). Not known: the image is left as it was and
    the value (with its covariance) says how large the motion may be: its second moment is the error.
    ``timing_sigma_s``: how far the stamp may be from the middle row's mid-exposure (latency calibration,
    clock, and the edge fit's place within a blurred edge: see :func:`timing_sigma_s`)."""

    omega: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    omega_cov: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))
    velocity: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    velocity_cov: NDArray[np.float64] = field(default_factory=lambda: np.zeros((3, 3)))
    omega_known: bool = False
    velocity_known: bool = False
    timing_sigma_s: float = 0.0

    def omega_used(self) -> NDArray[np.float64]:
        """The rate the image is corrected by (zero when not known)."""
        return np.asarray(self.omega, float) if self.omega_known else _ZERO3

    def velocity_used(self) -> NDArray[np.float64]:
        """The velocity the image is corrected by (zero when not known)."""
        return np.asarray(self.velocity, float) if self.velocity_known else _ZERO3

    def omega_second_moment(self) -> NDArray[np.float64]:
        """E[omega omega^T]: how large the rate may be (the timing term's image motion)."""
        w = np.asarray(self.omega, float)
        return np.outer(w, w) + np.asarray(self.omega_cov, float)

    def velocity_second_moment(self) -> NDArray[np.float64]:
        v = np.asarray(self.velocity, float)
        return np.outer(v, v) + np.asarray(self.velocity_cov, float)

    def omega_error(self) -> NDArray[np.float64]:
        """Second moment of the rate left uncorrected: the estimate's covariance, or the whole rate's."""
        return np.asarray(self.omega_cov, float) if self.omega_known else self.omega_second_moment()

    def velocity_error(self) -> NDArray[np.float64]:
        return np.asarray(self.velocity_cov, float) if self.velocity_known else self.velocity_second_moment()


def timing_sigma_s(stamp_sigma_s: float, exposure_s: float) -> float:
    """The uncertainty of a corner's instant common to a frame: the stamp's (``stamp_sigma_s``) and where
    within a blurred edge its fit lands (uniform over the exposure: ``exposure / sqrt(12)``)."""
    return math.sqrt(stamp_sigma_s**2 + exposure_s**2 / 12.0)


def to_stamp(
    x_norm: NDArray[np.float64], depth_m: NDArray[np.float64], dt_s: NDArray[np.float64], motion: CameraMotion
) -> NDArray[np.float64]:
    """Normalised image points ``x_norm`` (N, 2) seen ``dt_s`` (N,) after the stamp at depths ``depth_m``
    (N,) moved to where the camera saw them at the stamp: ``P(0) = exp([omega] dt) P(dt) + v dt``, with
    the motion's known parts (the rotation is exact: a homography; the translation needs the depth)."""
    x = np.asarray(x_norm, dtype=float).reshape(-1, 2)
    dt = np.asarray(dt_s, dtype=float).reshape(-1)
    P = np.hstack([x, np.ones((len(x), 1))]) * np.asarray(depth_m, dtype=float).reshape(-1, 1)
    w, v = motion.omega_used(), motion.velocity_used()
    if np.any(w):
        P = Rotation.from_rotvec(dt[:, None] * w[None, :]).apply(P)
    P = P + dt[:, None] * v[None, :]
    return P[:, :2] / P[:, 2:]


def from_stamp(
    x_norm: NDArray[np.float64], depth_m: NDArray[np.float64], dt_s: NDArray[np.float64], motion: CameraMotion
) -> NDArray[np.float64]:
    """The inverse of :func:`to_stamp`: points at the stamp (depths at the stamp) moved to where the camera
    saw them ``dt_s`` later: ``P(dt) = exp(-[omega] dt) (P(0) - v dt)``."""
    x = np.asarray(x_norm, dtype=float).reshape(-1, 2)
    dt = np.asarray(dt_s, dtype=float).reshape(-1)
    P = np.hstack([x, np.ones((len(x), 1))]) * np.asarray(depth_m, dtype=float).reshape(-1, 1)
    w, v = motion.omega_used(), motion.velocity_used()
    P = P - dt[:, None] * v[None, :]
    if np.any(w):
        P = Rotation.from_rotvec(-dt[:, None] * w[None, :]).apply(P)
    return P[:, :2] / P[:, 2:]


def planar_depths(x_norm: NDArray[np.float64], obj_xy: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """Depths (m) of the corners of a planar object (``obj_xy``: (N, 2) in its plane, N >= 4) seen at the
    normalised points ``x_norm`` (N, 2): from the homography H = [r1 r2 t] / s, each depth s * h3 . [X Y 1]
    with s fixed by |r1| = |r2| = 1. None when degenerate or behind the camera."""
    x = np.asarray(x_norm, dtype=float).reshape(1, -1, 2)
    z = planar_depths_many(x, np.asarray(obj_xy, dtype=float).reshape(1, -1, 2))[0]
    return None if np.isnan(z).any() else z


def planar_depths_many(x_norm: NDArray[np.float64], obj_xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`planar_depths` of M objects at once (``x_norm``, ``obj_xy``: (M, N, 2)): (M, N), a row of NaN
    where that object's depths are degenerate or behind the camera."""
    x = np.asarray(x_norm, dtype=float)
    X = np.asarray(obj_xy, dtype=float)
    m, n = x.shape[:2]
    u, w, a, b = x[..., 0], x[..., 1], X[..., 0], X[..., 1]
    rows = np.zeros((m, n, 2, 9))
    rows[:, :, 0, 0], rows[:, :, 0, 1], rows[:, :, 0, 2] = a, b, 1.0
    rows[:, :, 1, 3], rows[:, :, 1, 4], rows[:, :, 1, 5] = a, b, 1.0
    rows[:, :, 0, 6], rows[:, :, 0, 7], rows[:, :, 0, 8] = -u * a, -u * b, -u
    rows[:, :, 1, 6], rows[:, :, 1, 7], rows[:, :, 1, 8] = -w * a, -w * b, -w
    rows = rows.reshape(m, 2 * n, 9)
    H = np.full((m, 3, 3), np.nan)
    try:
        H[:] = np.linalg.svd(rows)[2][:, -1].reshape(m, 3, 3)
    except np.linalg.LinAlgError:  # one object's system: solve each alone, the failed ones NaN
        for k in range(m):
            try:
                H[k] = np.linalg.svd(rows[k])[2][-1].reshape(3, 3)
            except np.linalg.LinAlgError:
                continue
    scale = np.array([2.0 / (np.linalg.norm(h[:, 0]) + np.linalg.norm(h[:, 1])) for h in H])
    z = scale[:, None] * (np.concatenate([X, np.ones((m, n, 1))], axis=2) @ H[:, 2, :, None])[..., 0]
    z = np.where(np.all(z < 0, axis=1, keepdims=True), -z, z)
    bad = ~np.all(np.isfinite(z), axis=1) | np.any(z <= 0, axis=1)
    z[bad] = np.nan
    return z


def square_to_stamp(
    x_norm: NDArray[np.float64], obj_xy: NDArray[np.float64], dt_s: NDArray[np.float64], motion: CameraMotion
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`to_stamp` of a planar object's corners (``obj_xy``: (N, 2) in its plane, its known size),
    with the depths the translation needs from the object's own homography, recomputed from the corrected
    corners (the sheared shape's depth error then enters only squared) and carried to each corner's
    instant. Returns the corrected points and their depths at their instants (1 where no depth is found)."""
    x = np.asarray(x_norm, dtype=float).reshape(1, -1, 2)
    x0, z = squares_to_stamp(x, np.asarray(obj_xy, dtype=float).reshape(1, -1, 2), np.reshape(dt_s, (1, -1)), motion)
    return x0[0], z[0]


def squares_to_stamp(
    x_norm: NDArray[np.float64], obj_xy: NDArray[np.float64], dt_s: NDArray[np.float64], motion: CameraMotion
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`square_to_stamp` of M objects at once (``x_norm``, ``obj_xy``: (M, N, 2); ``dt_s``: (M, N)):
    the corrected points (M, N, 2) and their depths (M, N), each object's as if corrected alone."""
    x = np.asarray(x_norm, dtype=float)
    X = np.asarray(obj_xy, dtype=float)
    dt = np.asarray(dt_s, dtype=float)
    shape = x.shape
    z = planar_depths_many(x, X)
    z[np.isnan(z).any(axis=1)] = 1.0
    v = motion.velocity_used()
    active = np.any(dt != 0.0, axis=1) if np.any(v) else np.zeros(len(x), dtype=bool)
    for _ in range(2):
        if not active.any():
            break
        x0 = to_stamp(x.reshape(-1, 2), z.reshape(-1), dt.reshape(-1), motion).reshape(shape)
        z0 = planar_depths_many(x0, X)
        active &= ~np.isnan(z0).any(axis=1)  # an object without depths keeps its last ones
        P0 = np.concatenate([x0, np.ones((*shape[:-1], 1))], axis=-1) * z0[..., None] - dt[..., None] * v
        turn = Rotation.from_rotvec(-dt.reshape(-1, 1) * motion.omega_used()[None, :])
        z = np.where(active[:, None], turn.apply(P0.reshape(-1, 3))[:, 2].reshape(dt.shape), z)
    return to_stamp(x.reshape(-1, 2), z.reshape(-1), dt.reshape(-1), motion).reshape(shape), z


def flow_jacobians(
    x_norm: NDArray[np.float64], depth_m: NDArray[np.float64], fx: float, fy: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per point, the pixel motion (N, 2, 3) for a small turn of the camera's view ``theta`` (rad: the
    point's direction rotated by exp([theta])) and for a small displacement ``d`` (m) of the point in the
    camera frame: ``A = f [[-xy, 1 + x^2, -y], [-(1 + y^2), xy, x]]``, ``B = f / z [[1, 0, -x], [0, 1, -y]]``."""
    x = np.asarray(x_norm, dtype=float).reshape(-1, 2)
    u, w = x[:, 0], x[:, 1]
    z = np.asarray(depth_m, dtype=float).reshape(-1)
    A = np.empty((len(x), 2, 3))
    A[:, 0] = np.stack([-u * w, 1.0 + u * u, -w], axis=1) * fx
    A[:, 1] = np.stack([-(1.0 + w * w), u * w, u], axis=1) * fy
    B = np.zeros((len(x), 2, 3))
    B[:, 0, 0], B[:, 0, 2] = fx / z, -fx * u / z
    B[:, 1, 1], B[:, 1, 2] = fy / z, -fy * w / z
    return A, B


def shear_covariance(
    x_norm: NDArray[np.float64],
    depth_m: NDArray[np.float64],
    dt_s: NDArray[np.float64],
    motion: CameraMotion,
    fx: float,
    fy: float,
) -> NDArray[np.float64]:
    """(2N, 2N) covariance (pixels^2, x0 y0 x1 y1 ...) of the points after :func:`to_stamp` from the
    rate's and velocity's error times each point's ``dt``: one error shears every point coherently (rank
    at most 6), differently by row, which no rigid pose absorbs. Points (..., N, 2) with depths and
    ``dt_s`` (..., N): one such matrix per object, (..., 2N, 2N)."""
    x = np.asarray(x_norm, dtype=float)
    lead, n = x.shape[:-2], x.shape[-2]
    A, B = flow_jacobians(x.reshape(-1, 2), np.reshape(depth_m, -1), fx, fy)
    dt = np.asarray(dt_s, dtype=float).reshape(-1, 1, 1)
    Ga, Gb = (dt * A).reshape((*lead, 2 * n, 3)), (dt * B).reshape((*lead, 2 * n, 3))
    C = Ga @ motion.omega_error() @ np.swapaxes(Ga, -1, -2) + Gb @ motion.velocity_error() @ np.swapaxes(Gb, -1, -2)
    return 0.5 * (C + np.swapaxes(C, -1, -2))


def timing_covariance(
    x_norm: NDArray[np.float64], depth_m: NDArray[np.float64], motion: CameraMotion, fx: float, fy: float
) -> NDArray[np.float64]:
    """(2N, 2N) covariance of the points from the frame's timing uncertainty: the image motion (its second
    moment) times ``timing_sigma_s``, common to every point of the frame (the view at another instant: a
    rigid pose change, rank at most 6)."""
    A, B = flow_jacobians(x_norm, depth_m, fx, fy)
    n = len(A)
    if motion.timing_sigma_s <= 0.0:
        return np.zeros((2 * n, 2 * n))
    Ha, Hb = A.reshape(2 * n, 3), B.reshape(2 * n, 3)
    C = motion.timing_sigma_s**2 * (
        Ha @ motion.omega_second_moment() @ Ha.T + Hb @ motion.velocity_second_moment() @ Hb.T
    )
    return 0.5 * (C + C.T)


def motion_covariance(
    x_norm: NDArray[np.float64],
    depth_m: NDArray[np.float64],
    dt_s: NDArray[np.float64],
    motion: CameraMotion,
    fx: float,
    fy: float,
) -> NDArray[np.float64]:
    """(2N, 2N) covariance of the points after :func:`to_stamp` from what the motion leaves uncertain,
    correlated across points: :func:`shear_covariance` plus :func:`timing_covariance` (the detector adds
    the latter's pose equivalent, :func:`timing_pose_covariance`, to each frame's poses instead)."""
    return shear_covariance(x_norm, depth_m, dt_s, motion, fx, fy) + timing_covariance(x_norm, depth_m, motion, fx, fy)


def timing_pose_covariance(
    p_sensor_marker_m: NDArray[np.float64], R_sensor_marker: NDArray[np.float64], motion: CameraMotion
) -> NDArray[np.float64]:
    """(6, 6) covariance, in ``[dp, dtheta]`` (:mod:`atlas_onboard.core.covariance`), of a marker's pose
    in the camera from the frame's timing uncertainty: the pose ``timing_sigma_s`` later is
    ``p - dt (omega x p + v)``, ``R exp(-dt R^T omega)``. The same shift for every marker of the frame, so
    it belongs to the frame's pose, not to the markers' agreement with each other."""
    if motion.timing_sigma_s <= 0.0:
        return np.zeros((6, 6))
    p = np.asarray(p_sensor_marker_m, dtype=float)
    L = np.zeros((6, 6))  # d[dp, dtheta] / d[omega, v] per unit of time
    L[:3, :3] = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])  # p x omega
    L[:3, 3:] = -np.eye(3)
    L[3:, :3] = -np.asarray(R_sensor_marker, dtype=float).T
    M = np.zeros((6, 6))
    M[:3, :3], M[3:, 3:] = motion.omega_second_moment(), motion.velocity_second_moment()
    C = motion.timing_sigma_s**2 * (L @ M @ L.T)
    return 0.5 * (C + C.T)


@dataclass(frozen=True, slots=True)
class BodyRate:
    """The autopilot's angular rate at a capture time: body FLU (rad/s) with its covariance (gyro noise,
    bias, and how far the rate may have changed between its sample and the capture)."""

    omega_flu: NDArray[np.float64]
    cov: NDArray[np.float64]


@dataclass(frozen=True, slots=True)
class BodyVelocity:
    """The autopilot's velocity of the body at a capture time, in its own FLU axes (m/s, (3,)), relative to
    its local frame (the world's markers), with its covariance (3, 3), m^2/s^2 (:mod:`.velocity`)."""

    velocity_flu: NDArray[np.float64]
    cov: NDArray[np.float64]


GYRO_SIGMA_RAD_S = 0.005
"""Per-axis error of an autopilot's filtered body rate: gyro noise after its filters and the residual bias
of a calibrated MEMS gyro (a few tenths of a degree a second)."""
RATE_CHANGE_RAD_S2 = 6.0
"""How fast a drone's body rate may change (rad/s^2 per axis): the rate sample's age times it is the error
of using the nearest sample."""


class RateHistory:
    """The autopilot's recent body rates (FLU, rad/s), by time (wall clock, us), appended by one thread
    and read by another (a deque's append and copy are atomic in CPython)."""

    def __init__(self, capacity: int = 256, max_age_us: int = 50_000) -> None:
        self._samples: deque[tuple[int, NDArray[np.float64]]] = deque(maxlen=capacity)
        self.max_age_us = max_age_us

    def add(self, time_us: int, omega_flu: NDArray[np.float64]) -> None:
        """A sample; out-of-order, repeated or non-finite ones are ignored."""
        w = np.asarray(omega_flu, dtype=float)
        if (self._samples and time_us <= self._samples[-1][0]) or not np.all(np.isfinite(w)):
            return
        self._samples.append((int(time_us), w))

    def rate_at(self, t_us: int) -> BodyRate | None:
        """The rate at ``t_us``: interpolated between the samples around it, or extrapolated along the
        line through the newest two within ``max_age_us`` of the newest (the node usually asks before the
        sample after a frame's stamp has come). Its covariance: how well such a line has predicted each
        of the recent samples from the two before it (:func:`prediction_sigma`: the gyro's noise and the
        rate's changing slope as they are now), grown with the distance beyond a sample spacing; with too
        few samples for that, the gyro's and :data:`RATE_CHANGE_RAD_S2` over the distance to a sample."""
        samples = list(self._samples)
        if not samples:
            return None
        times = [s[0] for s in samples]
        k = bisect.bisect_left(times, t_us)
        recent = samples[max(k - PREDICTION_SAMPLES - 2, 0) : k + 1]
        spread = prediction_sigma(recent)
        if 0 < k < len(samples) and times[k] - times[k - 1] <= 2 * self.max_age_us:
            (t0, w0), (t1, w1) = samples[k - 1], samples[k]
            f = (t_us - t0) / (t1 - t0)
            w = (1.0 - f) * w0 + f * w1
            if spread is not None:  # within a spacing of the samples on both sides: no worse than a prediction
                return BodyRate(w, max(spread[0], GYRO_SIGMA_RAD_S) ** 2 * np.eye(3))
            age_s = min(t_us - t0, t1 - t_us) * 1e-6
        else:
            t0, w = samples[min(k, len(samples) - 1)] if k < len(samples) else samples[-1]
            age_s = abs(t_us - t0) * 1e-6
            if age_s * 1e6 > self.max_age_us:
                return None
            if k == len(samples) and spread is not None and len(samples) >= 2:
                (ta, wa), (tb, wb) = samples[-2], samples[-1]
                if 0 < tb - ta <= 2 * self.max_age_us:
                    w = wb + (wb - wa) * (t_us - tb) / (tb - ta)
                    sigma, spacing_us = spread
                    sigma *= max(1.0, (t_us - tb) / spacing_us) ** 2
                    return BodyRate(w, max(sigma, GYRO_SIGMA_RAD_S) ** 2 * np.eye(3))
        sigma2 = GYRO_SIGMA_RAD_S**2 + (RATE_CHANGE_RAD_S2 * age_s) ** 2
        return BodyRate(w, sigma2 * np.eye(3))


PREDICTION_SAMPLES = 8  # the recent samples whose prediction errors say how well the rate is predicted now


def prediction_sigma(samples: list[tuple[int, NDArray[np.float64]]]) -> tuple[float, float] | None:
    """How far each sample (time us, rate) is from the line through the two before it, RMS (rad/s, the
    worst axis), and the samples' median spacing (us); None with fewer than three such predictions. The
    error of a line a spacing ahead, measured: the gyro's noise and how fast the rate's slope changes."""
    errors, spacings = [], []
    for (ta, wa), (tb, wb), (tc, wc) in zip(samples, samples[1:], samples[2:], strict=False):
        if tb <= ta or tc <= tb:
            continue
        errors.append(wc - (wb + (wb - wa) * (tc - tb) / (tb - ta)))
        spacings.append(tc - tb)
    if len(errors) < 3:
        return None
    return float(np.sqrt(np.mean(np.square(errors), axis=0)).max()), float(np.median(spacings))
