"""A multirotor landing on LANDING_TARGET as PX4's precland and ArduPilot's AC_PrecLand do, in outline.

It reads the message in the form each takes (PX4: MAV_FRAME_LOCAL_NED position; ArduPilot: the
MAV_FRAME_BODY_FRD vector, scaled by ``distance``, turned to NED by the vehicle's attitude and added to
its own position) and keeps its own estimate of the target:

- approach at its height until within ``accept_radius_m`` of the target (PX4 PLD_HACC_RAD), then
  descend at ``descent_m_s`` while centring over it (both keep correcting horizontally);
- ArduPilot with a moving target (PLND_OPTIONS bit 0) estimates the target's velocity (its Kalman
  filter) and feeds it forward; PX4 chases the position alone;
- a target not heard of for ``lost_timeout_s`` (PX4 PLD_BTOUT, ArduPilot's 2 s) aborts the descent:
  the vehicle climbs to ``search_alt_m`` over its last position until the target comes back.

The vehicle's true motion: its horizontal and vertical velocity follow the command with a first-order
lag ``tau_s``. Positions here are world ENU (the autopilot's NED local frame is the same world turned).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core import frames

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
NIS_GATE = 3.0  # AC_PrecLand: a measurement whose NIS reaches 3 is refused, unless 3 were refused in a row
NIS_MAX_REJECTED = 3
FOOTPRINT_M = 0.25  # half a rover's deck: a vehicle over it touches the deck, not the floor


class Phase(StrEnum):
    WAIT = "wait"  # no target yet: hover
    APPROACH = "approach"  # over the target at the current height
    DESCEND = "descend"
    CLIMB = "climb"  # the target was lost: abort and climb
    LANDED = "landed"


@dataclass(frozen=True)
class LanderSettings:
    form: str  # "px4" or "ardupilot": the message form it takes
    moving_target: bool = False  # ArduPilot PLND_OPTIONS bit 0: estimate and follow the target's velocity
    descent_m_s: float = 0.5  # ArduPilot LAND_SPEED 50 cm/s; PX4 MPC_LAND_SPEED 0.7 m/s
    climb_m_s: float = 0.5
    accept_radius_m: float = 0.2  # PX4 PLD_HACC_RAD's default
    lost_timeout_s: float = 1.0  # PX4 PLD_BTOUT as `params` writes it
    search_alt_m: float = 2.0  # PX4 PLD_SRCH_ALT as `params` writes it
    gain_per_s: float = 2.0  # horizontal position gain
    max_speed_m_s: float = 1.0
    tau_s: float = 0.2  # velocity response
    target_accel_m_s2: float = 0.5  # the moving target's acceleration noise in the target filter


@dataclass
class Lander:
    """The vehicle: true position ``p_m`` and velocity ``v_m_s`` (world ENU), heading ``yaw_rad``."""

    settings: LanderSettings
    p_m: NDArray[np.float64]
    yaw_rad: float = 0.0
    v_m_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    phase: Phase = Phase.WAIT
    target_m: NDArray[np.float64] | None = None  # the autopilot's estimate of the target (world ENU)
    target_v_m_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    last_target_s: float = -math.inf
    touchdown_m: NDArray[np.float64] | None = None  # where it landed (true)
    aborts: int = 0
    refused: int = 0  # messages in a form this autopilot does not take
    _P: NDArray[np.float64] = field(default_factory=lambda: np.eye(2))  # the target filter's covariance
    _rejected: int = 0  # measurements refused by the filter's gate in a row
    _tick_s: float | None = None  # the last tick's time (:meth:`tick`)

    @property
    def attitude(self) -> Rotation:
        """The body's attitude (world ENU / body FLU): level, at its heading."""
        return Rotation.from_euler("z", self.yaw_rad)

    def on_target(self, fields: dict[str, Any], t_s: float, own_position_m: NDArray[np.float64]) -> None:
        """A LANDING_TARGET's fields arriving at ``t_s``; ``own_position_m`` the vehicle's own estimate of
        its position (what its EKF has from vision), world ENU."""
        if fields.get("position_valid") != 1:
            self.refused += 1
            return
        if self.settings.form == "px4" and fields["frame"] == MAV_FRAME_LOCAL_NED:
            north, east, down = fields["x"], fields["y"], fields["z"]
            measured = np.array([east, north, -down], dtype=float)
        elif self.settings.form == "ardupilot" and fields["frame"] == MAV_FRAME_BODY_FRD and fields["distance"] > 0:
            v_frd = np.array([fields["x"], fields["y"], fields["z"]], dtype=float)
            unit = v_frd / np.linalg.norm(v_frd) * fields["distance"]
            measured = own_position_m + (self.attitude * frames.R_FLU_FRD).apply(unit)
        else:
            self.refused += 1
            return
        if self.target_m is None or t_s - self.last_target_s > self.settings.lost_timeout_s:
            self.target_m, self.target_v_m_s = measured, np.zeros(3)
            self._P = np.array([[_meas_var(measured - own_position_m), 0.0], [0.0, 1.0]])
        elif not self.settings.moving_target:
            self.target_m = measured  # a static target: the measurement as it comes
        else:
            self._kalman(measured, t_s - self.last_target_s, _meas_var(measured - own_position_m))
        self.last_target_s = t_s
        if self.phase in (Phase.WAIT, Phase.CLIMB):
            self.phase = Phase.APPROACH

    def _kalman(self, measured: NDArray[np.float64], dt: float, r: float) -> None:
        """ArduPilot's per-axis position-velocity Kalman filter of the target (one covariance for x and y)."""
        assert self.target_m is not None
        F = np.array([[1.0, dt], [0.0, 1.0]])
        q = self.settings.target_accel_m_s2**2
        Q = q * np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
        P = F @ self._P @ F.T + Q
        predicted = [F @ np.array([self.target_m[a], self.target_v_m_s[a]]) for a in range(2)]
        nis = max((measured[a] - predicted[a][0]) ** 2 / (P[0, 0] + r) for a in range(2))
        if nis >= NIS_GATE and self._rejected < NIS_MAX_REJECTED:  # AC_PrecLand's outlier gate
            self._rejected += 1
            return
        self._rejected = 0
        K = P[:, 0] / (P[0, 0] + r)
        for axis in range(2):
            x = F @ np.array([self.target_m[axis], self.target_v_m_s[axis]])
            x = x + K * (measured[axis] - x[0])
            self.target_m[axis], self.target_v_m_s[axis] = x
        self.target_m[2] = measured[2]
        self._P = P - np.outer(K, P[0, :])

    def tick(self, t_s: float, own_position_m: NDArray[np.float64], ground_z_m: float = 0.0) -> None:
        """:meth:`step` to ``t_s`` from the previous tick (a real-time loop; the first tick only starts)."""
        if self._tick_s is not None and t_s > self._tick_s:
            self.step(t_s, t_s - self._tick_s, own_position_m, ground_z_m)
        self._tick_s = t_s

    def step(self, t_s: float, dt_s: float, own_position_m: NDArray[np.float64], ground_z_m: float) -> None:
        """Advance the true motion by ``dt_s`` to ``t_s``; ``ground_z_m`` the height of what is below (the
        pad's top where it is over the pad), touched when the vehicle's origin reaches it."""
        s = self.settings
        if self.phase is Phase.LANDED:
            return
        lost = self.target_m is not None and t_s - self.last_target_s > s.lost_timeout_s
        if lost and self.phase in (Phase.APPROACH, Phase.DESCEND):
            self.phase = Phase.CLIMB
            self.aborts += 1
        cmd = np.zeros(3)
        if self.target_m is not None and self.phase in (Phase.APPROACH, Phase.DESCEND):
            ff = self.target_v_m_s * (1.0 if s.moving_target else 0.0)
            ahead = self.target_m + ff * (t_s - self.last_target_s)
            error = (ahead - own_position_m)[:2]
            cmd[:2] = ff[:2] + s.gain_per_s * error
            speed = float(np.linalg.norm(cmd[:2]))
            if speed > s.max_speed_m_s:
                cmd[:2] *= s.max_speed_m_s / speed
            if self.phase is Phase.APPROACH and float(np.linalg.norm(error)) < s.accept_radius_m:
                self.phase = Phase.DESCEND
            if self.phase is Phase.DESCEND:
                cmd[2] = -s.descent_m_s
        elif self.phase is Phase.CLIMB:
            cmd[2] = s.climb_m_s if self.p_m[2] < s.search_alt_m else 0.0
        a = 1.0 - math.exp(-dt_s / s.tau_s)
        self.v_m_s = self.v_m_s + a * (cmd - self.v_m_s)
        self.p_m = self.p_m + self.v_m_s * dt_s
        if self.p_m[2] <= ground_z_m and self.phase is Phase.DESCEND:
            self.p_m[2] = ground_z_m
            self.v_m_s = np.zeros(3)
            self.phase = Phase.LANDED
            self.touchdown_m = self.p_m.copy()


def ground_below(p_m: NDArray[np.float64], deck_m: NDArray[np.float64]) -> float:
    """The height of what is below a vehicle at ``p_m``: the deck whose landing point is ``deck_m`` (a pad
    or a rover's top) within ``FOOTPRINT_M`` of it on both axes, else the floor (0)."""
    over = bool(np.all(np.abs(p_m[:2] - deck_m[:2]) < FOOTPRINT_M))
    return float(deck_m[2]) if over else 0.0


def _meas_var(relative_m: NDArray[np.float64]) -> float:
    """ArduPilot's horizontal measurement variance of a target ``relative_m`` away: (0.01 h + 0.02)^2 m^2
    (AC_PrecLand, at rest: its gyro term left out)."""
    return float((abs(relative_m[2]) * 0.01 + 0.02) ** 2)
