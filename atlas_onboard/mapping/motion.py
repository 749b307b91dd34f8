"""A recording's rolling shutter in the map's input: each detection's corners moved to its frame's stamp
(:mod:`atlas_onboard.core.shutter`) by the camera's rate from the attitudes recorded with the frames around
it, before the adjustment sees them (the adjustment's camera has one pose per frame).

Only the turn is corrected: the map builder has no velocity of its own before it has solved, and over a
readout the turn moves the image far more than the travel does at mapping speeds. Inputs without attitudes
(videos, image folders, recordings without an autopilot) keep their corners, which the adjustment's robust
loss then weighs.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core.shutter import CameraMotion, RowClock, to_stamp
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.mapping.observations import Observations

MAX_SPAN_US = 150_000  # neighbouring frames further apart than this give no rate


def _wxyz(q: tuple[float, float, float, float]) -> Rotation:
    w, x, y, z = q
    return Rotation.from_quat([x, y, z, w])


def _rates(obs: Observations, source: int, R_body_camera: NDArray[np.float64]) -> dict[int, NDArray[np.float64]]:
    """Per frame (index into ``obs.frames``) of input ``source``: the camera's rate (rad/s, camera frame)
    from the attitudes of its neighbouring frames (a central difference; one-sided at the ends)."""
    frames = [(i, fr) for i, fr in enumerate(obs.frames) if fr.source == source and fr.q_level_body_wxyz is not None]
    out = {}
    for k, (i, _) in enumerate(frames):
        a = frames[max(k - 1, 0)][1]
        b = frames[min(k + 1, len(frames) - 1)][1]
        span = b.capture_time_us - a.capture_time_us
        if span <= 0 or span > MAX_SPAN_US or a.q_level_body_wxyz is None or b.q_level_body_wxyz is None:
            continue
        w_body = (_wxyz(a.q_level_body_wxyz).inv() * _wxyz(b.q_level_body_wxyz)).as_rotvec() / (span * 1e-6)
        out[i] = R_body_camera.T @ w_body
    return out


def _distort(x_norm: NDArray[np.float64], cal: Calibration) -> NDArray[np.float64]:
    pts = np.hstack([x_norm, np.ones((len(x_norm), 1))]).reshape(-1, 1, 3)
    zero = np.zeros(3)
    if cal.fisheye:
        px, _ = cv2.fisheye.projectPoints(pts, zero, zero, cal.K, cal.dist)
    else:
        px, _ = cv2.projectPoints(pts, zero, zero, cal.K, cal.dist)
    return px.reshape(-1, 2)


def _undistort_normalised(px: NDArray[np.float64], cal: Calibration) -> NDArray[np.float64]:
    pts = np.ascontiguousarray(px, dtype=np.float64).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    if cal.fisheye:
        return cv2.fisheye.undistortPoints(pts, cal.K, cal.dist, criteria=crit).reshape(-1, 2)
    return cv2.undistortPoints(pts, cal.K, cal.dist, criteria=crit).reshape(-1, 2)


def correct_input(obs: Observations, source: int, clock: RowClock) -> int:
    """The corners of input ``source`` moved to their frames' stamps by the recorded attitudes' rate
    (in place, distorted pixels as before); returns how many detections were corrected."""
    mount = obs.mountings[source]
    if clock.readout_s <= 0.0 or mount is None:
        return 0
    rates = _rates(obs, source, np.asarray(mount, dtype=float)[:3, :3])
    cal = obs.lenses[source]
    n = 0
    for j, f in enumerate(obs.obs_frame):
        w = rates.get(f)
        if w is None:
            continue
        px = np.asarray(obs.corners_px[j], dtype=float)
        x = _undistort_normalised(px, cal)
        x0 = to_stamp(x, np.ones(len(x)), clock.dt_s(px[:, 1]), CameraMotion(w, omega_known=True))
        obs.corners_px[j] = _distort(x0, cal)
        n += 1
    return n


def correct(obs: Observations) -> int:
    """:func:`correct_input` of every input with a rolling shutter (``obs.clocks``); how many detections."""
    return sum(correct_input(obs, s, clock) for s, clock in enumerate(obs.clocks) if clock is not None)
