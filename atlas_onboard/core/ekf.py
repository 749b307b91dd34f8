"""An error-state EKF per entity: the paper's last item of future work.

State: position p and velocity v in the world frame, the body orientation as a nominal quaternion
with a 3-vector error state in the body frame, and the body angular rate w. Motion model: constant
velocity and constant angular rate, driven by white acceleration and angular-acceleration noise.
Measurements: a full pose (position and orientation) with a 6x6 covariance, stamped with the image's
capture time. Each update is gated by its Mahalanobis distance, so one wrong pose cannot yank the
estimate. Time is passed in (seconds on the stamps' clock); nothing here reads a clock.

Error state x = [dp (3), dv (3), dtheta (3), dw (3)]; the true orientation is q_nom * Exp(dtheta).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

CHI2_6DOF_999 = 22.458  # chi-square, 6 degrees of freedom, 99.9 %: the default gate
CHI2_6DOF_99 = 16.812


@dataclass
class EkfSettings:
    """Process noise and gating.

    Attributes:
        accel_noise: white acceleration noise density, m/s^2 (a quadrotor's manoeuvres).
        angular_accel_noise: white angular-acceleration noise density, rad/s^2.
        gate_chi2: reject an update whose squared Mahalanobis distance exceeds this (6 dof).
        max_gap_s: beyond this without an update the filter is reset by the next measurement.
        max_lag_s: a measurement older than the filter's time by more than this is dropped as late.
        constant_rate: True: the attitude is predicted with the estimated body rate (constant angular
            rate); False: it is held (a random walk driven by ``angular_rate_noise``, rad/s/sqrt(Hz)),
            the rate state stays zero. A quadrotor's attitude jitters at several hertz, faster than a
            30 Hz camera can follow: extrapolating a rate estimated from it does more harm than good.
        angular_rate_noise: the random walk's rate noise density (with ``constant_rate`` False).
    """

    accel_noise: float = 1.0
    angular_accel_noise: float = 2.0
    gate_chi2: float = CHI2_6DOF_999
    max_gap_s: float = 1.0
    max_lag_s: float = 0.1
    constant_rate: bool = True
    angular_rate_noise: float = 1.0


@dataclass
class PoseEkf:
    """The filter of one entity. ``initialized`` is False until the first accepted measurement."""

    settings: EkfSettings = field(default_factory=EkfSettings)
    p: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    v: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    q: Rotation = field(default_factory=Rotation.identity)
    w: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    P: NDArray[np.float64] = field(default_factory=lambda: np.eye(12))
    t_s: float = 0.0
    initialized: bool = False
    t_update_s: float = 0.0
    accepted: int = 0
    gated: int = 0
    late: int = 0
    resets: int = 0
    last_nis: float = float("nan")

    def reset(self, t_s: float, p: NDArray[np.float64], q: Rotation, R: NDArray[np.float64]) -> None:
        """Start from a measurement: its pose and covariance, zero velocity with a wide prior."""
        self.p, self.q = np.array(p, dtype=float), q
        self.v, self.w = np.zeros(3), np.zeros(3)
        self.P = np.zeros((12, 12))
        self.P[0:3, 0:3] = R[0:3, 0:3]
        self.P[6:9, 6:9] = R[3:6, 3:6]
        self.P[3:6, 3:6] = np.eye(3) * 1.0**2  # up to ~1 m/s unknown
        self.P[9:12, 9:12] = np.eye(3) * (1.0**2 if self.settings.constant_rate else 0.0)  # ~1 rad/s unknown
        self.t_s = self.t_update_s = t_s
        self.initialized = True
        self.resets += 1

    def predict(self, t_s: float) -> None:
        """Propagate the state and covariance to time ``t_s`` (no-op backwards in time)."""
        dt = t_s - self.t_s
        if not self.initialized or dt <= 0.0:
            return
        # Nominal state: constant velocity, constant body rate.
        self.p = self.p + self.v * dt
        self.q = self.q * Rotation.from_rotvec(self.w * dt)
        # Error-state transition F (first order) and process noise Q (white acceleration inputs).
        F = np.eye(12)
        F[0:3, 3:6] = np.eye(3) * dt
        F[6:9, 6:9] = Rotation.from_rotvec(-self.w * dt).as_matrix()
        F[6:9, 9:12] = np.eye(3) * dt
        qa, qw = self.settings.accel_noise**2, self.settings.angular_accel_noise**2
        Q = np.zeros((12, 12))
        blocks = ((0, qa), (6, qw)) if self.settings.constant_rate else ((0, qa),)
        for i0, q_ in blocks:
            Q[i0 : i0 + 3, i0 : i0 + 3] = np.eye(3) * q_ * dt**3 / 3
            Q[i0 : i0 + 3, i0 + 3 : i0 + 6] = np.eye(3) * q_ * dt**2 / 2
            Q[i0 + 3 : i0 + 6, i0 : i0 + 3] = np.eye(3) * q_ * dt**2 / 2
            Q[i0 + 3 : i0 + 6, i0 + 3 : i0 + 6] = np.eye(3) * q_ * dt
        if not self.settings.constant_rate:
            # Attitude as a random walk: the rate state is pinned at zero with zero variance.
            F[6:9, 9:12] = 0.0
            Q[6:9, 6:9] = np.eye(3) * self.settings.angular_rate_noise**2 * dt
        self.P = F @ self.P @ F.T + Q
        self.t_s = t_s

    def innovation(
        self, p_meas: NDArray[np.float64], q_meas: Rotation
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Innovation y (6,) = [p_meas - p, Log(q^-1 q_meas)] and its Jacobian H (6, 12)."""
        y = np.concatenate([np.asarray(p_meas, dtype=float) - self.p, (self.q.inv() * q_meas).as_rotvec()])
        H = np.zeros((6, 12))
        H[0:3, 0:3] = np.eye(3)
        H[3:6, 6:9] = np.eye(3)
        return y, H

    def update(self, t_s: float, p_meas: NDArray[np.float64], q_meas: Rotation, R: NDArray[np.float64]) -> str:
        """Fuse a pose measurement taken at ``t_s`` with covariance ``R`` (6x6: position m^2, then
        orientation rad^2 in the body frame). Returns ``accepted``, ``reset``, ``gated`` or ``late``."""
        if not self.initialized or t_s - self.t_update_s > self.settings.max_gap_s:
            self.reset(t_s, p_meas, q_meas, R)
            return "reset"
        if t_s < self.t_s - self.settings.max_lag_s:
            self.late += 1
            return "late"
        # Predict a copy first: a gated measurement leaves the filter exactly as it was.
        saved = (self.p, self.v, self.q, self.w, self.P, self.t_s)
        self.predict(t_s)
        y, H = self.innovation(p_meas, q_meas)
        S = H @ self.P @ H.T + R
        try:
            S_inv_y = np.linalg.solve(S, y)
        except np.linalg.LinAlgError:
            S_inv_y = None
        nis = float(y @ S_inv_y) if S_inv_y is not None else float("inf")
        self.last_nis = nis
        if nis > self.settings.gate_chi2:
            self.p, self.v, self.q, self.w, self.P, self.t_s = saved
            self.gated += 1
            return "gated"
        K = np.linalg.solve(S, H @ self.P).T  # K = P H^T S^-1 (S symmetric)
        dx = K @ y
        self.p = self.p + dx[0:3]
        self.v = self.v + dx[3:6]
        self.q = self.q * Rotation.from_rotvec(dx[6:9])
        self.w = self.w + dx[9:12]
        # Joseph form keeps P symmetric and positive definite.
        I_KH = np.eye(12) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        self.t_update_s = max(self.t_update_s, t_s)
        self.accepted += 1
        return "accepted"

    def pose_at(self, t_s: float) -> tuple[NDArray[np.float64], Rotation, NDArray[np.float64]]:
        """Predicted position, orientation and 6x6 pose covariance at ``t_s``, without changing the filter."""
        dt = max(t_s - self.t_s, 0.0)
        p = self.p + self.v * dt
        q = self.q * Rotation.from_rotvec(self.w * dt)
        shadow = PoseEkf(
            self.settings, self.p.copy(), self.v.copy(), self.q, self.w.copy(), self.P.copy(), self.t_s, True
        )
        shadow.predict(t_s)
        cov = np.zeros((6, 6))
        cov[0:3, 0:3] = shadow.P[0:3, 0:3]
        cov[3:6, 3:6] = shadow.P[6:9, 6:9]
        cov[0:3, 3:6] = shadow.P[0:3, 6:9]
        cov[3:6, 0:3] = shadow.P[6:9, 0:3]
        return p, q, cov
