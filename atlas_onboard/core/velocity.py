"""The autopilot's velocity at a capture time: its estimate (``LOCAL_POSITION_NED``'s ``vx vy vz``, in its
local frame, here as level ENU) turned into the body frame by its attitude at the same instant, with the
covariance the rolling-shutter model carries (:mod:`atlas_onboard.core.shutter`).

Why it is a prior independent enough of a frame's corners: the autopilot's EKF fuses our earlier poses
with its accelerometers, so its velocity error is what its filter made of those poses' errors over the last
seconds, and of its IMU's; a frame's readout shear is measured from that frame's own corner noise, which
the velocity has not seen. Its errors are correlated from frame to frame, not with the frame.

Pure: numpy and scipy; times are passed in.
"""

from __future__ import annotations

import bisect
from collections import deque

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core.ekf import MANOEUVRE_ACCEL_SIGMA
from atlas_onboard.core.shutter import BodyVelocity

AUTOPILOT_VELOCITY_SIGMA_M_S = 0.05
"""Per-axis error of an autopilot's velocity estimate: a vision-aided EKF's velocity (a few cm/s), and what
its accelerometers' bias (a few cm/s^2) adds while it dead-reckons through a second without vision."""
MAX_GAP_US = 100_000
"""Samples further apart than this are not interpolated between; a sample older than this gives nothing."""


def level_enu_of_ned(vx: float, vy: float, vz: float) -> NDArray[np.float64] | None:
    """A velocity (m/s) in the autopilot's local NED frame as level ENU (east = y, north = x, up = -z); None
    when not all finite or all exactly zero (an autopilot that does not fill it: an estimate is never zero
    on three axes at once)."""
    v = (float(vx), float(vy), float(vz))
    if not all(np.isfinite(v)) or v == (0.0, 0.0, 0.0):
        return None
    return np.array([v[1], v[0], -v[2]])


class VelocityHistory:
    """The autopilot's recent velocities (level ENU of its own heading, m/s) by time (wall clock, us), appended
    by one thread and read by another (a deque's append and copy are atomic in CPython)."""

    def __init__(self, capacity: int = 128, max_gap_us: int = MAX_GAP_US) -> None:
        self._samples: deque[tuple[int, NDArray[np.float64]]] = deque(maxlen=capacity)
        self.max_gap_us = max_gap_us

    def add(self, time_us: int, v_level_enu: NDArray[np.float64]) -> None:
        """A sample; out-of-order, repeated or non-finite ones are ignored."""
        v = np.asarray(v_level_enu, dtype=float).reshape(3)
        if (self._samples and time_us <= self._samples[-1][0]) or not np.all(np.isfinite(v)):
            return
        self._samples.append((int(time_us), v))

    def latest_us(self) -> int | None:
        """Time of the newest sample, or None."""
        samples = self._samples
        return samples[-1][0] if samples else None

    def velocity_at(self, t_us: int, R_level_body: Rotation | None) -> BodyVelocity | None:
        """The body's velocity at ``t_us`` in its axes (``R_level_body``: the autopilot's attitude then, in the
        same level frame): interpolated between the samples around it, else the nearest within
        ``max_gap_us``. Its covariance: :data:`AUTOPILOT_VELOCITY_SIGMA_M_S` and a manoeuvre's acceleration
        over the time to the nearest sample, isotropic (so turned into any axes unchanged). None without an
        attitude or a sample near enough."""
        samples = list(self._samples)
        if R_level_body is None or not samples:
            return None
        times = [s[0] for s in samples]
        k = bisect.bisect_left(times, t_us)
        if 0 < k < len(samples) and times[k] - times[k - 1] <= self.max_gap_us:
            (t0, v0), (t1, v1) = samples[k - 1], samples[k]
            f = (t_us - t0) / (t1 - t0)
            v = (1.0 - f) * v0 + f * v1
            age_us = min(t_us - t0, t1 - t_us)
        else:
            candidates = [j for j in (k - 1, k) if 0 <= j < len(samples)]
            j = min(candidates, key=lambda i: abs(times[i] - t_us))
            age_us = abs(times[j] - t_us)
            if age_us > self.max_gap_us:
                return None
            v = samples[j][1]
        sigma2 = AUTOPILOT_VELOCITY_SIGMA_M_S**2 + (MANOEUVRE_ACCEL_SIGMA * age_us * 1e-6) ** 2
        return BodyVelocity(R_level_body.inv().apply(v), sigma2 * np.eye(3))
