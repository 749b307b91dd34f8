"""The simulated autopilot's velocity estimate: what its EKF reports (LOCAL_POSITION_NED's ``vx vy vz``) of a
body's true velocity.

A vision-aided EKF's velocity is the true one a little late (the filter's output lags what its IMU felt),
plus an error that wanders slowly (a first-order Gauss-Markov process: what the filter made of the vision
poses' and the accelerometers' errors over the last second or so), and, while no vision pose comes, a drift:
its accelerometers' residual bias integrated (dead reckoning), which the filter pulls back once vision
returns. The local frame is the autopilot's own: its heading offset turns it about the vertical.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class EkfVelocityNoise:
    """An EKF velocity's errors, per axis: the wandering error's standard deviation (m/s) and correlation time
    (s), the output's lag behind the truth (s), the accelerometers' residual bias (m/s^2, drawn per run), the
    silence after which the filter dead-reckons (s), and how fast it pulls the drift back with vision (s)."""

    sigma_m_s: float = 0.03
    tau_s: float = 1.0
    lag_s: float = 0.01
    accel_bias_sigma: float = 0.03
    vision_timeout_s: float = 0.2
    recover_tau_s: float = 0.5


@dataclass(frozen=True, slots=True)
class LocalPosition:
    """One LOCAL_POSITION_NED: measured at ``t_s`` (wall clock), the position (NED, m) and velocity (NED, m/s)."""

    t_s: float
    xyz_m: tuple[float, float, float]
    v_ned_m_s: tuple[float, float, float]


class EkfVelocity:
    """Readings of one EKF's velocity in time order (``read``), from its own seeded random stream; measured
    ``delay_s`` before they are sent, in a local frame whose heading is the world's plus ``yaw_offset_deg``."""

    def __init__(self, noise: EkfVelocityNoise, seed: int, delay_s: float = 0.0, yaw_offset_deg: float = 0.0) -> None:
        self.noise = noise
        self.delay_s = delay_s
        self.yaw_offset_deg = yaw_offset_deg
        self._rng = np.random.default_rng(seed)
        self._wander = self._rng.normal(0.0, noise.sigma_m_s, 3)
        self._accel_bias = self._rng.normal(0.0, noise.accel_bias_sigma, 3)
        self._drift = np.zeros(3)
        self._last_s: float | None = None

    def read(self, t_s: float, true_velocity: NDArray[np.float64], vision_age_s: float | None) -> NDArray[np.float64]:
        """The estimate (3,) m/s at ``t_s`` of a body whose true velocity ``lag_s`` earlier was ``true_velocity``
        (3,), the newest vision pose ``vision_age_s`` old (None: none yet): the errors move on first."""
        n = self.noise
        dt = 0.0 if self._last_s is None else max(t_s - self._last_s, 0.0)
        self._last_s = t_s
        a = math.exp(-dt / n.tau_s)
        self._wander = a * self._wander + n.sigma_m_s * math.sqrt(1.0 - a * a) * self._rng.normal(0.0, 1.0, 3)
        if vision_age_s is None or vision_age_s > n.vision_timeout_s:
            self._drift = self._drift + self._accel_bias * dt
        else:
            self._drift = self._drift * math.exp(-dt / n.recover_tau_s)
        return np.asarray(true_velocity, dtype=float) + self._wander + self._drift

    def read_ned(
        self, t_s: float, true_world_enu: NDArray[np.float64], vision_age_s: float | None, yaw_offset_deg: float
    ) -> tuple[float, float, float]:
        """:meth:`read` of a true velocity in the world's ENU, as LOCAL_POSITION_NED carries it: in the
        autopilot's local NED, whose heading is the world's plus ``yaw_offset_deg`` (its ATTITUDE's)."""
        c, s = math.cos(math.radians(yaw_offset_deg)), math.sin(math.radians(yaw_offset_deg))
        v = np.asarray(true_world_enu, dtype=float)
        v = self.read(t_s, np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]]), vision_age_s)
        return (float(v[1]), float(v[0]), float(-v[2]))  # level ENU -> NED

    def local_position(
        self,
        now_s: float,
        last_vision: tuple[float, tuple[float, float, float]] | None,
        velocity: Callable[[float], NDArray[np.float64] | None] | None,
    ) -> LocalPosition | None:
        """The LOCAL_POSITION_NED to send at wall time ``now_s``: the last vision position received
        (``last_vision``: its arrival and NED position; an EKF on vision) and, with ``velocity`` (the true
        world ENU velocity at a wall time), the EKF's velocity measured ``delay_s`` earlier (else zeros, as
        an autopilot that does not fill it). None with neither."""
        t_s = now_s - (self.delay_s if velocity is not None else 0.0)
        true = velocity(t_s - self.noise.lag_s) if velocity is not None else None
        if last_vision is None and true is None:
            return None
        xyz = last_vision[1] if last_vision is not None else (0.0, 0.0, 0.0)
        if true is None:
            return LocalPosition(t_s, xyz, (0.0, 0.0, 0.0))
        age = None if last_vision is None else t_s - last_vision[0]
        return LocalPosition(t_s, xyz, self.read_ned(t_s, true, age, self.yaw_offset_deg))
