"""The autopilot's attitude as a reference for gravity: a short history, and which of a single tag's two
IPPE solutions agrees with it (the MegaTag2 idea: the flight controller knows which way is down far
better than a small, far or face-on tag does).

Only roll and pitch are used: the direction of world up seen in the body frame. The autopilot's yaw
may come from a compass or from our own poses, so it is never trusted here; up does not depend on it,
so the level frame's heading is irrelevant (the world file's z is up, internally ENU).

Times: samples are stamped on the node's wall clock (UNIX epoch, microseconds), the clock of capture
times (:class:`atlas_onboard.core.bootclock.BootClock` maps the autopilot's ``time_boot_ms`` to it).

Pure: numpy, scipy and the standard library; times are passed in.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.errors import GeometryError

UP = np.array([0.0, 0.0, 1.0])
MAX_GAP_US = 100_000
"""Samples further apart than this are not interpolated between; a capture further than half of it
from the nearest sample has no attitude (a stream that stopped, or a capture before the first)."""
HISTORY = 256
"""Samples kept (about 5 s at 50 Hz): enough for a capture that waited in the pipeline."""
AUTOPILOT_TILT_SIGMA_RAD = math.radians(1.5)
"""Per-axis error of the autopilot's roll and pitch as used here: its own (0.5-1 degree in flight,
accelerations bias a complementary or EKF attitude), the camera mount's calibration and the time
between the nearest samples."""
GATE_R2 = 13.82
"""chi-square(2) at 0.999: a solution agrees with the autopilot when its tilt error, squared over the
per-axis variance, is within this (the tilt error has two degrees of freedom: roll and pitch)."""
MIN_LIKELIHOOD_RATIO = 1000.0
"""The agreeing solution must be at least this many times as likely as the other under the same
Gaussian model; otherwise gravity cannot tell the two apart (their difference is mostly a turn about
the vertical, or the observation's own tilt is too uncertain)."""


class TiltVerdict(StrEnum):
    """Outcome of :func:`choose_by_tilt` (the value names the listener's counter)."""

    PRIMARY = "primary"  # the chosen solution agrees with gravity and the other does not
    ALT = "alt"  # the other solution agrees and the chosen one does not: it was the flip
    BOTH = "both"  # both agree: gravity cannot decide (the caller falls back on its other means)
    NEITHER = "neither"  # neither agrees: the detection (or the mount) is wrong; rejected


@dataclass(frozen=True, slots=True)
class TiltCheck:
    """A verdict with the tilt errors of both solutions (rad) and the sigma they were judged by."""

    verdict: TiltVerdict
    error_primary_rad: float
    error_alt_rad: float
    sigma_rad: float


def up_in_body(R_world_body: Rotation) -> NDArray[np.float64]:
    """World up (+z) expressed in the body frame, shape (3,) or (N, 3): what roll and pitch determine."""
    return R_world_body.inv().apply(UP)


def tilt_error_rad(R_world_body: Rotation, up_body: NDArray[np.float64]) -> NDArray[np.float64]:
    """Angle (rad) between the up that ``R_world_body`` implies and ``up_body`` (unit, body frame)."""
    implied = up_in_body(R_world_body)
    c = np.clip(np.sum(np.atleast_2d(implied) * np.atleast_2d(up_body), axis=-1), -1.0, 1.0)
    # atan2 of |cross| and dot keeps precision at small angles, where acos does not.
    s = np.linalg.norm(np.cross(np.atleast_2d(implied), np.atleast_2d(up_body)), axis=-1)
    return np.arctan2(s, c)


def choose_by_tilt(
    R_world_body_primary: Rotation,
    R_world_body_alt: Rotation,
    up_body: NDArray[np.float64],
    observation_sigma_rad: float,
    autopilot_sigma_rad: float = AUTOPILOT_TILT_SIGMA_RAD,
    gate_r2: float = GATE_R2,
    min_likelihood_ratio: float = MIN_LIKELIHOOD_RATIO,
) -> TiltCheck:
    """Which of a single tag's two solutions (each as the body attitude it implies in the world) agrees
    with the autopilot's up vector ``up_body`` (unit, body frame).

    A tilt error e is the angle between the two up vectors; the per-axis sigma it is judged by
    combines the autopilot's (``autopilot_sigma_rad``) and the observation's own attitude error about
    its solution (``observation_sigma_rad``, >= 0; not the spread between the two solutions). With
    r^2 = (e / sigma)^2, the nearer solution is chosen when ``r_near^2 <= gate_r2`` and
    ``r_far^2 - r_near^2 >= 2 ln(min_likelihood_ratio)``; both near but not decisively: BOTH; none near:
    NEITHER.
    """
    if not (observation_sigma_rad >= 0.0 and autopilot_sigma_rad > 0.0):
        raise GeometryError(
            f"expected sigmas >= 0 and > 0 rad, got {observation_sigma_rad!r} and {autopilot_sigma_rad!r}"
        )
    sigma = math.hypot(autopilot_sigma_rad, observation_sigma_rad)
    e_a = float(tilt_error_rad(R_world_body_primary, up_body)[0])
    e_b = float(tilt_error_rad(R_world_body_alt, up_body)[0])
    r2_a, r2_b = (e_a / sigma) ** 2, (e_b / sigma) ** 2
    near, far = min(r2_a, r2_b), max(r2_a, r2_b)
    if not near <= gate_r2:
        verdict = TiltVerdict.NEITHER
    elif far - near < 2.0 * math.log(min_likelihood_ratio):
        verdict = TiltVerdict.BOTH
    else:
        verdict = TiltVerdict.PRIMARY if r2_a <= r2_b else TiltVerdict.ALT
    return TiltCheck(verdict, e_a, e_b, sigma)


class AttitudeHistory:
    """The autopilot's recent attitudes (body FLU in a level ENU frame of arbitrary heading), by time,
    each with the body rate the autopilot sent with it when it sent one.

    Appended by one thread (the autopilot link's) and read by another (the node's loop): a deque's
    append and a copy of it are each atomic in CPython, so no lock is needed.
    """

    def __init__(self, capacity: int = HISTORY, max_gap_us: int = MAX_GAP_US) -> None:
        self._samples: deque[tuple[int, NDArray[np.float64], NDArray[np.float64] | None]] = deque(maxlen=capacity)
        self.max_gap_us = max_gap_us

    def add(self, time_us: int, R_level_body: Rotation, omega_flu: NDArray[np.float64] | None = None) -> None:
        """A sample at ``time_us`` (wall clock, us), with the body's angular rate (FLU, rad/s) at it if
        known; out-of-order, repeated or non-finite samples are ignored (a non-finite rate: no rate)."""
        if self._samples and time_us <= self._samples[-1][0]:
            return
        q = R_level_body.as_quat()
        if not np.all(np.isfinite(q)):
            return
        w = None if omega_flu is None else np.asarray(omega_flu, dtype=float)
        self._samples.append((int(time_us), q, w if w is not None and np.all(np.isfinite(w)) else None))

    def __len__(self) -> int:
        return len(self._samples)

    def latest_us(self) -> int | None:
        """Time of the newest sample, or None."""
        samples = self._samples
        return samples[-1][0] if samples else None

    def attitude_at(self, t_us: int) -> Rotation | None:
        """The attitude at ``t_us`` (wall clock, us).

        When the newest sample at or before ``t_us`` has a body rate and is at most ``max_gap_us``
        before it: that sample turned on by its rate to ``t_us`` (``R Exp(omega dt)``). The answer then
        does not depend on whether the sample after ``t_us`` has arrived yet, so a frame gets the same
        gravity however late it is processed. Otherwise: interpolated (slerp) between the samples around
        it when they are at most ``max_gap_us`` apart, the nearest sample when it is within half of that
        (before the first or after the last), else None."""
        samples = list(self._samples)
        if not samples:
            return None
        times = [s[0] for s in samples]
        k = int(np.searchsorted(times, t_us, side="right"))  # samples[k - 1]: the newest at or before t_us
        if k > 0 and samples[k - 1][2] is not None and t_us - times[k - 1] <= self.max_gap_us:
            t0, q0, w0 = samples[k - 1]
            return Rotation.from_quat(q0) * Rotation.from_rotvec(w0 * ((t_us - t0) * 1e-6))
        half = self.max_gap_us // 2
        if k == 0:
            return Rotation.from_quat(samples[0][1]) if times[0] - t_us <= half else None
        if k == len(samples):
            return Rotation.from_quat(samples[-1][1]) if t_us - times[-1] <= half else None
        (t0, q0, _), (t1, q1, _) = samples[k - 1], samples[k]
        if t1 - t0 > self.max_gap_us:
            if t_us - t0 <= half:
                return Rotation.from_quat(q0)
            return Rotation.from_quat(q1) if t1 - t_us <= half else None
        f = (t_us - t0) / (t1 - t0)
        R0 = Rotation.from_quat(q0)
        return R0 * Rotation.from_rotvec(f * (R0.inv() * Rotation.from_quat(q1)).as_rotvec())

    def up_at(self, t_us: int) -> NDArray[np.float64] | None:
        """World up in the body frame at ``t_us`` (see :meth:`attitude_at`), or None."""
        R = self.attitude_at(t_us)
        return None if R is None else up_in_body(R)


@dataclass(frozen=True, slots=True)
class TagPose:
    """A single tag's pose T_sensor_marker with its covariance: what :func:`constrain_tilt` updates."""

    p_sensor_marker_m: NDArray[np.float64]  # (3,)
    R_sensor_marker: NDArray[np.float64]  # (3, 3)
    covariance: NDArray[np.float64]  # (6, 6), core.covariance convention ([dp in sensor, dtheta about marker axes])


def _tangent_basis(u: NDArray[np.float64]) -> NDArray[np.float64]:
    """Two orthonormal rows perpendicular to the unit vector ``u``, shape (2, 3)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(u[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(u, a)
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1)])


def _tilt_update(
    C: NDArray[np.float64], H_rot: NDArray[np.float64], z: NDArray[np.float64], sigma_rad: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The Kalman update of a 6-state ``[dp, dtheta]`` (covariance ``C``) with a two-component tilt
    measurement ``z = H_rot dtheta + noise`` (per-axis ``sigma_rad``): the correction and the new
    covariance (Joseph form, symmetrised)."""
    H = np.zeros((2, 6))
    H[:, 3:] = H_rot
    S = H @ C @ H.T + sigma_rad**2 * np.eye(2)
    K = np.linalg.solve(S, H @ C).T  # C H^T S^-1 (S and C symmetric)
    I_KH = np.eye(6) - K @ H
    C_new = I_KH @ C @ I_KH.T + sigma_rad**2 * (K @ K.T)
    return K @ z, 0.5 * (C_new + C_new.T)


def _skew(v: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def constrain_tilt(
    tag: TagPose,
    R_body_sensor: NDArray[np.float64],
    R_world_marker: NDArray[np.float64],
    up_body: NDArray[np.float64],
    sigma_rad: float = AUTOPILOT_TILT_SIGMA_RAD,
) -> TagPose:
    """The MegaTag2 idea, as a Kalman update: a single tag's pose T_sensor_marker (position (3,) m,
    rotation (3, 3), 6x6 covariance in the core.covariance convention) updated with the autopilot's up
    vector ``up_body`` (unit, body frame; per-axis standard deviation ``sigma_rad``).

    The measurement is the up vector the pose implies, ``u = R_body_sensor R_sensor_marker m`` with ``m``
    world up in the marker frame; to first order ``u(dtheta) = u0 - R_bs R_sm [m]x dtheta``, observed
    in the plane perpendicular to ``u0`` (two components: roll and pitch). Position follows through the
    covariance's coupling of tilt and position (a single tag's camera position is range x tilt), and the
    covariance shrinks as the update says (Joseph form).
    """
    R_sm = np.asarray(tag.R_sensor_marker, dtype=float)
    m = np.asarray(R_world_marker, dtype=float).T @ UP
    u0 = np.asarray(R_body_sensor, dtype=float) @ R_sm @ m
    B = _tangent_basis(u0 / np.linalg.norm(u0))
    x, C_new = _tilt_update(
        np.asarray(tag.covariance, dtype=float),
        -B @ R_body_sensor @ R_sm @ _skew(m),
        B @ (np.asarray(up_body, dtype=float) - u0),
        sigma_rad,
    )
    R_new = R_sm @ Rotation.from_rotvec(x[3:]).as_matrix()
    return TagPose(np.asarray(tag.p_sensor_marker_m, dtype=float) + x[:3], R_new, C_new)


@dataclass(frozen=True, slots=True)
class BodyPose:
    """An entity's world pose with its covariance: what :func:`constrain_body_tilt` updates."""

    p_world_m: NDArray[np.float64]  # (3,)
    R_world_body: NDArray[np.float64]  # (3, 3)
    covariance: NDArray[np.float64]  # (6, 6), core.covariance convention ([dp in world, dtheta about body axes])


def constrain_body_tilt(
    pose: BodyPose, up_body: NDArray[np.float64], sigma_rad: float = AUTOPILOT_TILT_SIGMA_RAD
) -> BodyPose:
    """A fused world pose updated with the autopilot's up vector ``up_body`` (unit, body frame; per-axis
    ``sigma_rad``), as :func:`constrain_tilt` updates a single tag: for a pose that rests on no own view
    of the world (a follower placed through its leader's marker), whose tilt swings its position by the
    lever arm to that marker; the position follows through the covariance's coupling.

    The implied up is ``u = R_world_body^T z``; to first order ``u(dtheta) = u0 + [u0]x dtheta``."""
    R = np.asarray(pose.R_world_body, dtype=float)
    u0 = R.T @ UP
    B = _tangent_basis(u0)
    x, C_new = _tilt_update(
        np.asarray(pose.covariance, dtype=float), B @ _skew(u0), B @ (np.asarray(up_body, dtype=float) - u0), sigma_rad
    )
    return BodyPose(np.asarray(pose.p_world_m, dtype=float) + x[:3], R @ Rotation.from_rotvec(x[3:]).as_matrix(), C_new)


def camera_orientation(R_level_body: Rotation | None, R_body_sensor: Rotation) -> Rotation | None:
    """The camera's optical frame in the level frame (R_level_camera) from the autopilot's attitude
    (None: no attitude); the turn between two frames is ``then.inv() * now``, as :class:`CameraTurn`'s."""
    return None if R_level_body is None else R_level_body * R_body_sensor


class CameraTurn:
    """A camera's rotation between its consecutive frames from the autopilot's attitude at their capture
    times: where a turn will move the markers in the image (a fast yaw moves them far more than their
    last image motion says). ``R_body_sensor``: the camera's optical frame in the body (FLU) frame.

    Unlike the tilt check, the whole attitude is used, yaw too: over one frame period the autopilot's
    heading drifts by far less than the gyros' turn, whatever its absolute error."""

    def __init__(self, R_body_sensor: Rotation) -> None:
        self._R_body_sensor = R_body_sensor
        self._previous: Rotation | None = None

    def since_last(self, R_level_body: Rotation | None) -> Rotation | None:
        """The turn from the previous frame to this one (maps directions in the camera frame now into
        the camera frame then), given this frame's attitude (None: no attitude near its capture time);
        None when either frame has no attitude."""
        previous, self._previous = self._previous, R_level_body
        if previous is None or R_level_body is None:
            return None
        return self._R_body_sensor.inv() * previous.inv() * R_level_body * self._R_body_sensor
