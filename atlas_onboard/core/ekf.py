"""An error-state EKF per entity: the paper's last item of future work.

State: position p, velocity v and acceleration a in the world frame, the body orientation as a
nominal quaternion with a 3-vector error state in the body frame, and the body angular rate w.
Motion model: velocity driven by white acceleration noise plus, optionally, a manoeuvre acceleration
modelled as Singer's first-order Gauss-Markov process (a stationary random acceleration of a given
spread and correlation time: a craft's manoeuvres last a while and are bounded, so the error of a
prediction grows with the square of its horizon, as a real manoeuvre's does); constant angular rate
or a held attitude.
Measurements: a full pose (position and orientation) with a 6x6 covariance, stamped with the image's
capture time. Each update is gated by its Mahalanobis distance, so one wrong pose cannot yank the
estimate. Time is passed in (seconds on the stamps' clock); nothing here reads a clock.

Error state x = [dp (3), dv (3), dtheta (3), dw (3), da (3)]; the true orientation is
q_nom * Exp(dtheta).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

CHI2_6DOF_999 = 22.458  # chi-square, 6 degrees of freedom, 99.9 %: the default gate
CHI2_6DOF_99 = 16.812
N = 15  # error-state size
# A quadrotor's manoeuvres: tilting about 9 degrees accelerates it by about 1.5 m/s^2 (the simulated
# scenarios' drones: 0.4-1.5 m/s^2 RMS per axis), and a turn or a stop lasts about half a second. The
# node's filter considers them (Singer, not estimated): a prediction through a gap then carries the
# uncertainty of an acceleration that may have changed, growing with the square of the horizon as a
# real manoeuvre's error does, where white acceleration noise alone grows it with the power 1.5 and
# is overconfident at the end of a gap.
MANOEUVRE_ACCEL_SIGMA = 1.5  # m/s^2 per axis
MANOEUVRE_TIME_S = 0.5
# The tilt that acceleration needs (thrust along a + g), per axis; the heading is taken to swing as much.
MANOEUVRE_ATTITUDE_SIGMA_RAD = float(np.arctan(MANOEUVRE_ACCEL_SIGMA / 9.81))


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
        attitude_sigma_rad: with ``constant_rate`` False and this > 0, the held attitude's error grows
            as a stationary Gauss-Markov attitude's does (spread this, correlation time
            ``manoeuvre_time_s``): by ``2 sigma^2 (1 - exp(-dt / tau))`` over a prediction of dt, which
            a tilt that follows the manoeuvre acceleration has, instead of the random walk's.
        manoeuvre_accel_sigma: spread of the manoeuvre acceleration (Singer model), m/s^2 per axis; 0
            for the plain constant-velocity model (no acceleration state).
        manoeuvre_time_s: its correlation time, s (how long a manoeuvre's acceleration lasts).
        estimate_accel: True: the acceleration is estimated and extrapolated; False: it is only
            "considered" (Schmidt): never estimated, the mean predicted at constant velocity, but its
            uncertainty carried in the covariance. A quadrotor's acceleration follows its tilt, which
            jitters faster than a 30 Hz camera can follow (as its attitude rate does): extrapolating
            an estimate of it predicts worse than holding the velocity.
    """

    accel_noise: float = 1.0
    angular_accel_noise: float = 2.0
    gate_chi2: float = CHI2_6DOF_999
    max_gap_s: float = 1.0
    max_lag_s: float = 0.1
    constant_rate: bool = True
    angular_rate_noise: float = 1.0
    attitude_sigma_rad: float = 0.0
    manoeuvre_accel_sigma: float = 0.0
    manoeuvre_time_s: float = 0.5
    estimate_accel: bool = True


@dataclass
class PoseEkf:
    """The filter of one entity. ``initialized`` is False until the first accepted measurement."""

    settings: EkfSettings = field(default_factory=EkfSettings)
    p: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    v: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    q: Rotation = field(default_factory=Rotation.identity)
    w: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    P: NDArray[np.float64] = field(default_factory=lambda: np.eye(N))
    t_s: float = 0.0
    initialized: bool = False
    t_update_s: float = 0.0
    outcomes: Counter[str] = field(default_factory=Counter)  # of update(): accepted, reset, gated, late
    last_nis: float = float("nan")
    a: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    t_reset_s: float = 0.0  # capture time of the measurement that last reset the filter

    @property
    def velocity_observed(self) -> bool:
        """Whether a measurement later than the one that reset the filter has been fused: before that its
        velocity is only the reset's zero-mean prior, and a prediction would stamp a held pose as new."""
        return self.initialized and self.t_update_s > self.t_reset_s

    def reset(self, t_s: float, p: NDArray[np.float64], q: Rotation, R: NDArray[np.float64]) -> None:
        """Start from a measurement: its pose and covariance, zero velocity with a wide prior."""
        self.p, self.q = np.array(p, dtype=float), q
        self.v, self.w, self.a = np.zeros(3), np.zeros(3), np.zeros(3)
        self.P = np.zeros((N, N))
        self.P[0:3, 0:3] = R[0:3, 0:3]
        self.P[6:9, 6:9] = R[3:6, 3:6]
        self.P[3:6, 3:6] = np.eye(3) * 1.0**2  # up to ~1 m/s unknown
        self.P[9:12, 9:12] = np.eye(3) * (1.0**2 if self.settings.constant_rate else 0.0)  # ~1 rad/s unknown
        self.P[12:15, 12:15] = np.eye(3) * self.settings.manoeuvre_accel_sigma**2  # its stationary spread
        self.t_s = self.t_update_s = self.t_reset_s = t_s
        self.initialized = True
        self.outcomes["reset"] += 1

    def predict(self, t_s: float) -> None:
        """Propagate the state and covariance to time ``t_s`` (no-op backwards in time)."""
        dt = t_s - self.t_s
        if not self.initialized or dt <= 0.0:
            return
        # Translation, per axis [p, v, a]: its exact transition and process noise (Van Loan).
        Phi, Qt = _translation_model(self.settings, dt)
        self.p = self.p + Phi[0, 1] * self.v + Phi[0, 2] * self.a
        self.v = self.v + Phi[1, 2] * self.a
        self.a = Phi[2, 2] * self.a
        # Attitude: constant body rate (or held).
        self.q = self.q * Rotation.from_rotvec(self.w * dt)
        # Error-state transition F (first order for the attitude) and process noise Q.
        F = np.eye(N)
        Q = np.zeros((N, N))
        F[_TRANS_IX] = np.kron(Phi, _I3)
        Q[_TRANS_IX] = np.kron(Qt, _I3)
        F[6:9, 6:9] = Rotation.from_rotvec(-self.w * dt).as_matrix()
        F[6:9, 9:12] = np.eye(3) * dt
        if self.settings.constant_rate:
            qw = self.settings.angular_accel_noise**2
            Q[6:9, 6:9] = np.eye(3) * qw * dt**3 / 3
            Q[6:9, 9:12] = Q[9:12, 6:9] = np.eye(3) * qw * dt**2 / 2
            Q[9:12, 9:12] = np.eye(3) * qw * dt
        else:
            # Attitude as a random walk: the rate state is pinned at zero with zero variance.
            F[6:9, 9:12] = 0.0
            sigma, tau = self.settings.attitude_sigma_rad, self.settings.manoeuvre_time_s
            if sigma > 0.0:  # the increment of a Gauss-Markov attitude over dt (exact for one long step)
                Q[6:9, 6:9] = np.eye(3) * 2.0 * sigma**2 * -np.expm1(-dt / tau)
            else:
                Q[6:9, 6:9] = np.eye(3) * self.settings.angular_rate_noise**2 * dt
        self.P = F @ self.P @ F.T + Q
        self.t_s = t_s

    def innovation(
        self, p_meas: NDArray[np.float64], q_meas: Rotation
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Innovation y (6,) = [p_meas - p, Log(q^-1 q_meas)] and its Jacobian H (6, 15)."""
        y = np.concatenate([np.asarray(p_meas, dtype=float) - self.p, (self.q.inv() * q_meas).as_rotvec()])
        H = np.zeros((6, N))
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
            self.outcomes["late"] += 1
            return "late"
        # Predict a copy first: a gated measurement leaves the filter exactly as it was.
        saved = (self.p, self.v, self.q, self.w, self.a, self.P, self.t_s)
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
            self.p, self.v, self.q, self.w, self.a, self.P, self.t_s = saved
            self.outcomes["gated"] += 1
            return "gated"
        K = np.linalg.solve(S, H @ self.P).T  # K = P H^T S^-1 (S symmetric)
        if not self.settings.estimate_accel:
            K[12:15] = 0.0  # Schmidt: a considered state is not updated (Joseph form holds for any K)
        dx = K @ y
        self.p = self.p + dx[0:3]
        self.v = self.v + dx[3:6]
        self.q = self.q * Rotation.from_rotvec(dx[6:9])
        self.w = self.w + dx[9:12]
        self.a = self.a + dx[12:15]
        # Joseph form keeps P symmetric and positive definite.
        I_KH = np.eye(N) - K @ H
        self.P = I_KH @ self.P @ I_KH.T + K @ R @ K.T
        self.t_update_s = max(self.t_update_s, t_s)
        self.outcomes["accepted"] += 1
        return "accepted"

    def pose_at(self, t_s: float) -> tuple[NDArray[np.float64], Rotation, NDArray[np.float64]]:
        """Predicted position, orientation and 6x6 pose covariance at ``t_s``, without changing the filter."""
        shadow = PoseEkf(
            self.settings, self.p.copy(), self.v.copy(), self.q, self.w.copy(), self.P.copy(), self.t_s, True,
            a=self.a.copy(),
        )  # fmt: skip
        shadow.predict(t_s)
        cov = np.zeros((6, 6))
        cov[0:3, 0:3] = shadow.P[0:3, 0:3]
        cov[3:6, 3:6] = shadow.P[6:9, 6:9]
        cov[0:3, 3:6] = shadow.P[0:3, 6:9]
        cov[3:6, 0:3] = shadow.P[6:9, 0:3]
        return shadow.p, shadow.q, cov


_TRANS_IX = np.ix_(np.r_[0:6, 12:15], np.r_[0:6, 12:15])  # p, v and a in the error state
_I3 = np.eye(3)


def _translation_model(settings: EkfSettings, dt: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per axis, the transition Phi (3, 3) and process noise Q (3, 3) of [p, v, a] over ``dt`` (s):
    dp = v, dv = a + white acceleration (density ``accel_noise``), da = -a / tau + white noise of
    density sqrt(2 sigma^2 / tau) (Singer; stationary spread sigma = ``manoeuvre_accel_sigma``); with
    sigma 0 the acceleration stays zero. Phi in closed form; Q = int_0^dt Phi(u) Qc Phi(u)^T du by
    5-point Gauss-Legendre (exact for the polynomial part, to 1e-9 relative for the exponential)."""
    sigma, tau = settings.manoeuvre_accel_sigma, settings.manoeuvre_time_s
    u = 0.5 * dt * (_GL_X + 1.0)
    Phi_u = _singer_phi(u, sigma, tau)
    Qc = np.diag([0.0, settings.accel_noise**2, 2.0 * sigma**2 / tau if sigma > 0.0 else 0.0])
    Q = np.einsum("k,kij,jl,kml->im", 0.5 * dt * _GL_W, Phi_u, Qc, Phi_u)
    return _singer_phi(np.array([dt]), sigma, tau)[0], 0.5 * (Q + Q.T)


_GL_X, _GL_W = np.polynomial.legendre.leggauss(5)


def _singer_phi(u: NDArray[np.float64], sigma: float, tau: float) -> NDArray[np.float64]:
    """Transitions of [p, v, a] over the spans ``u`` (k,), shape (k, 3, 3)."""
    Phi = np.zeros((len(u), 3, 3))
    Phi[:, 0, 0] = Phi[:, 1, 1] = 1.0
    Phi[:, 0, 1] = u
    if sigma > 0.0:
        decay = np.exp(-u / tau)
        Phi[:, 0, 2] = tau**2 * (decay - 1.0 + u / tau)
        Phi[:, 1, 2] = tau * (1.0 - decay)
        Phi[:, 2, 2] = decay
    else:
        Phi[:, 2, 2] = 1.0
    return Phi
