"""Ground-truth trajectories of simulated entities, as functions of time.

Quadrotors do not fly on rails: they tilt to accelerate and their controllers oscillate. A
:class:`Quadrotor` trajectory therefore takes a smooth path (a position function of time), adds the
oscillation and jitter of a real vehicle (sums of sinusoids with seeded phases), and derives roll and
pitch from the acceleration the path needs (the thrust must point along a + g). Everything is a pure,
vectorised function of time in seconds; poses are ENU/FLU, ``T_world_entity``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

G = 9.81
PathFn = Callable[[NDArray[np.float64]], NDArray[np.float64]]  # t (N,) -> p (N, 3)
YawFn = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]  # t, p -> yaw (N,) rad
RATE_STEP_S = 1e-4  # half the step of the attitude's central difference (body rates)


@dataclass(frozen=True)
class Oscillation:
    """The controller's oscillation and the vehicle's attitude jitter.

    Position oscillates by ``amplitude_m`` per axis at ``freq_hz`` (the AR.Drone 2 of the paper's test
    1 "was oscillating heavily"); the tilt this needs follows from the acceleration. Vibration and
    turbulence add ``jitter_deg`` of roll/pitch jitter at 3-8 Hz, too fast to move the vehicle much.
    """

    amplitude_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    freq_hz: float = 1.0
    jitter_deg: float = 0.0
    seed: int = 0

    def __call__(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        phase = np.random.default_rng(self.seed).uniform(0, 2 * np.pi, 3)
        return np.asarray(self.amplitude_m)[None, :] * np.sin(2 * np.pi * self.freq_hz * t[:, None] + phase[None, :])

    def attitude_jitter_rad(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """Roll and pitch jitter (N, 2): a few incommensurate sinusoids (deterministic, smooth)."""
        out = np.zeros((len(t), 2))
        if self.jitter_deg <= 0:
            return out
        rng = np.random.default_rng(self.seed + 1)
        freqs, phases = rng.uniform(3.0, 8.0, (3, 2)), rng.uniform(0, 2 * np.pi, (3, 2))
        for k in range(3):
            out += np.sin(2 * np.pi * freqs[k][None, :] * t[:, None] + phases[k][None, :])
        return np.radians(self.jitter_deg) / 3 * out


@dataclass(frozen=True)
class Vibration:
    """The airframe's vibration as the camera feels it: ``amplitude_deg`` of roll and pitch and
    ``amplitude_m`` per axis of position at ``freq_hz`` (seeded phases). Unlike :class:`Oscillation`'s
    motion it needs no thrust: it is added to the pose, not flown (a mount shaking on its dampers)."""

    amplitude_deg: float = 0.0
    amplitude_m: float = 0.0
    freq_hz: float = 2.0
    seed: int = 0

    def offsets(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Position (N, 3) m and roll, pitch (N, 2) rad added at times ``t``."""
        phase = np.random.default_rng(self.seed).uniform(0, 2 * np.pi, 5)
        s = np.sin(2 * np.pi * self.freq_hz * t[:, None] + phase[None, :])
        return self.amplitude_m * s[:, :3], np.radians(self.amplitude_deg) * s[:, 3:]


@dataclass(frozen=True)
class Static:
    """An entity that does not move (a tag on the floor, a parked drone)."""

    p_m: tuple[float, float, float]
    rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def pose(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        n = len(np.atleast_1d(t))
        q = Rotation.from_euler("ZYX", self.rpy_deg[::-1], degrees=True).as_quat()
        return np.tile(np.asarray(self.p_m, dtype=float), (n, 1)), np.tile(q, (n, 1))

    def velocity(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """World velocities (N, 3) m/s: none."""
        return np.zeros((len(np.atleast_1d(t)), 3))

    def body_rates(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """Angular velocities (N, 3) rad/s in the body frame: none."""
        return np.zeros((len(np.atleast_1d(t)), 3))


@dataclass(frozen=True)
class Quadrotor:
    """A multirotor following ``path`` with heading ``yaw``, tilting as its acceleration requires."""

    path: PathFn
    yaw: YawFn
    oscillation: Oscillation = field(default_factory=Oscillation)
    dt: float = 1e-3
    vibration: Vibration | None = None

    def position(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """Positions (N, 3) at times ``t`` (s), the vibration included."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        p = self._flown(t)
        return p if self.vibration is None else p + self.vibration.offsets(t)[0]

    def _flown(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """The position the vehicle flies (its attitude follows its acceleration): no vibration."""
        return self.path(t) + self.oscillation(t)

    def pose(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Positions (N, 3) and quaternions xyzw (N, 4) at times ``t`` (s)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        p = self._flown(t)
        acc = (self._flown(t + self.dt) - 2 * p + self._flown(t - self.dt)) / self.dt**2
        yaw = self.yaw(t, p)
        # Thrust direction (body z) must be along a + g; roll/pitch follow in the yawed frame.
        thrust = acc + np.array([0.0, 0.0, G])
        cy, sy = np.cos(yaw), np.sin(yaw)
        fwd = cy * thrust[:, 0] + sy * thrust[:, 1]
        left = -sy * thrust[:, 0] + cy * thrust[:, 1]
        pitch = np.arctan2(fwd, thrust[:, 2])  # FLU: +pitch dips the nose, accelerating forward
        roll = np.arctan2(-left, np.hypot(fwd, thrust[:, 2]))
        jitter = self.oscillation.attitude_jitter_rad(t)
        roll, pitch = roll + jitter[:, 0], pitch + jitter[:, 1]
        if self.vibration is not None:
            dp, d_rp = self.vibration.offsets(t)
            p, roll, pitch = p + dp, roll + d_rp[:, 0], pitch + d_rp[:, 1]
        q = Rotation.from_euler("ZYX", np.stack([yaw, pitch, roll], axis=1)).as_quat()
        return p, q

    def velocity(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """World velocities (N, 3) m/s at times ``t`` (s): central differences over ``dt``."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return (self.position(t + self.dt) - self.position(t - self.dt)) / (2 * self.dt)

    def body_rates(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        """Angular velocities (N, 3) rad/s in the body frame (FLU) at times ``t`` (s), what a gyro
        measures: the turn between the attitudes RATE_STEP_S before and after, over that time
        (a central difference of :meth:`pose`, exact to second order in the step)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        _, q0 = self.pose(t - RATE_STEP_S)
        _, q1 = self.pose(t + RATE_STEP_S)
        return (Rotation.from_quat(q0).inv() * Rotation.from_quat(q1)).as_rotvec() / (2 * RATE_STEP_S)


# A flight file: row 0 holds the number of rows written; each row after it is one state of the vehicle.
FLIGHT_COLUMNS = ("t_s", "x_m", "y_m", "z_m", "yaw_rad", "vx_m_s", "vy_m_s", "vz_m_s", "yaw_rate_rad_s")


def flight_table(path: Path, rows: int | None = None) -> np.memmap:
    """The flight file at ``path`` mapped into memory: created with room for ``rows`` states when given
    (its writer's), else opened read-only (every other process of the run)."""
    shape = None if rows is None else (rows + 1, len(FLIGHT_COLUMNS))
    if rows is not None:
        return np.memmap(path, dtype=np.float64, mode="w+", shape=shape)
    raw = np.memmap(path, dtype=np.float64, mode="r")
    return raw.reshape(-1, len(FLIGHT_COLUMNS))


@dataclass(frozen=True)
class Flown:
    """A vehicle flown closed loop by its simulated autopilot in a real-time run (a landing on what the
    node tells it, :mod:`atlas_onboard.sim.flight`): its states are read from the run's flight file,
    which the runner writes a little ahead of the wall clock, so every process sees the same truth at a
    frame's time. Level, at its heading; before the first state, at ``start_m``; past the last, carried
    on at its last velocity. ``path`` is None outside a run (:meth:`bound` gives the run's)."""

    start_m: tuple[float, float, float]
    start_yaw_deg: float = 0.0
    path: Path | None = None

    def bound(self, path: Path) -> Flown:
        return Flown(self.start_m, self.start_yaw_deg, path)

    def states(self) -> NDArray[np.float64]:
        """The states written so far, (N, 9) as :data:`FLIGHT_COLUMNS` (none outside a run)."""
        table = None if self.path is None else _flight_tables.get(self.path)
        if table is None:  # mapped once per process: it stays readable after the run removes its directory
            if self.path is None or not self.path.exists():
                return np.zeros((0, len(FLIGHT_COLUMNS)))
            table = _flight_tables[self.path] = flight_table(self.path)
        n = int(table[0, 0])
        return np.array(table[1 : n + 1])

    def _at(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        s = self.states()
        if not len(s):
            start = [0.0, *self.start_m, np.radians(self.start_yaw_deg), 0.0, 0.0, 0.0, 0.0]
            return np.tile(start, (len(t), 1))
        out = np.column_stack([t] + [np.interp(t, s[:, 0], s[:, k]) for k in range(1, s.shape[1])])
        past = t > s[-1, 0]
        if past.any():
            dt = (t[past] - s[-1, 0])[:, None]
            out[past, 1:4] = s[-1, 1:4] + s[-1, 5:8] * dt
            out[past, 4] = s[-1, 4] + s[-1, 8] * dt[:, 0]
        return out

    def pose(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        s = self._at(t)
        return s[:, 1:4], Rotation.from_euler("z", s[:, 4:5]).as_quat()

    def velocity(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        return self._at(t)[:, 5:8]

    def body_rates(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        s = self._at(t)
        return np.column_stack([np.zeros(len(s)), np.zeros(len(s)), s[:, 8]])


_flight_tables: dict[Path, np.memmap] = {}


def lissajous(
    center: tuple[float, float, float],
    amp: tuple[float, float, float],
    freq_hz: tuple[float, float, float],
    phase: tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> PathFn:
    """A smooth, bounded, 'arbitrary-looking' path: a 3-D Lissajous curve."""
    c, a, f, ph = (np.asarray(v, dtype=float) for v in (center, amp, freq_hz, phase))

    def path(t: NDArray[np.float64]) -> NDArray[np.float64]:
        return c[None, :] + a[None, :] * np.sin(2 * np.pi * f[None, :] * t[:, None] + ph[None, :])

    return path


def circle(center: tuple[float, float, float], radius_m: float, period_s: float, phase_rad: float = 0.0) -> PathFn:
    """A horizontal circle around ``center`` at its height, counter-clockwise seen from above."""
    c = np.asarray(center, dtype=float)

    def path(t: NDArray[np.float64]) -> NDArray[np.float64]:
        a = 2 * np.pi * t / period_s + phase_rad
        return np.stack([c[0] + radius_m * np.cos(a), c[1] + radius_m * np.sin(a), np.full_like(t, c[2])], axis=1)

    return path


def shuttle(start: tuple[float, float, float], end: tuple[float, float, float], period_s: float) -> PathFn:
    """Back and forth between two points with a smooth (cosine) speed profile."""
    s, e = np.asarray(start, dtype=float), np.asarray(end, dtype=float)

    def path(t: NDArray[np.float64]) -> NDArray[np.float64]:
        u = 0.5 - 0.5 * np.cos(2 * np.pi * t / period_s)
        return s[None, :] + u[:, None] * (e - s)[None, :]

    return path


def offset(path: PathFn, delta: tuple[float, float, float]) -> PathFn:
    """The same path shifted by ``delta`` (a follower in formation)."""
    d = np.asarray(delta, dtype=float)
    return lambda t: path(t) + d[None, :]


def constant_yaw(yaw_deg: float) -> YawFn:
    y = np.radians(yaw_deg)
    return lambda t, p: np.full(len(t), y)


def slow_yaw(yaw0_deg: float, amplitude_deg: float, period_s: float) -> YawFn:
    y0, a = np.radians(yaw0_deg), np.radians(amplitude_deg)
    return lambda t, p: y0 + a * np.sin(2 * np.pi * t / period_s)


def face_point(target: tuple[float, float]) -> YawFn:
    """Heading that keeps the nose (and a front camera) pointed at ``target`` (x, y)."""
    tx, ty = target
    return lambda t, p: np.arctan2(ty - p[:, 1], tx - p[:, 0])


def behind(
    path: PathFn,
    yaw: YawFn,
    distance_m: tuple[float, float, float],
    bearing_deg: tuple[float, float],
    dz_m: float = 0.0,
) -> PathFn:
    """A follower behind a leader (``path`` with heading ``yaw``): at ``d0 + d1 sin(2 pi t / T)`` m for
    ``distance_m`` (d0, d1, T), off the leader's back by ``a sin(2 pi t / T)`` deg for ``bearing_deg``
    (a, T), ``dz_m`` lower or higher."""
    d0, d1, d_period = distance_m
    amp, b_period = np.radians(bearing_deg[0]), bearing_deg[1]

    def follower(t: NDArray[np.float64]) -> NDArray[np.float64]:
        d = d0 + d1 * np.sin(2 * np.pi * t / d_period)
        p = path(t)
        psi = yaw(t, p) + amp * np.sin(2 * np.pi * t / b_period)
        return p + np.stack([-d * np.cos(psi), -d * np.sin(psi), np.full_like(t, dz_m)], axis=1)

    return follower


def face_path(path: PathFn) -> YawFn:
    """Heading that keeps the nose pointed at where ``path`` is at the same time (yaw following another drone)."""

    def yaw(t: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
        q = path(t)
        return np.arctan2(q[:, 1] - p[:, 1], q[:, 0] - p[:, 0])

    return yaw


def driving(start_m: tuple[float, float, float], velocity_m_s: tuple[float, float, float]) -> Quadrotor:
    """A ground vehicle driving straight at constant speed, heading along its motion (no acceleration:
    the trajectory model keeps it level)."""
    p0, v = np.asarray(start_m, dtype=float), np.asarray(velocity_m_s, dtype=float)
    return Quadrotor(lambda t: p0 + np.asarray(t, dtype=float)[:, None] * v,
                     constant_yaw(float(np.degrees(np.arctan2(v[1], v[0])))))  # fmt: skip
