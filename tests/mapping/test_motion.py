"""A recording's rolling shutter in the map's input: corners moved to their frame's stamp by the rate of the
recorded attitudes (:mod:`atlas_onboard.mapping.motion`)."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.core.shutter import RowClock
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.pose import object_corners
from atlas_onboard.mapping.motion import correct_input
from atlas_onboard.mapping.observations import FrameInfo, Observations
from tests.mapping.synthetic import DIST, K

W, H = 640, 480
READOUT_S = 0.025
MOUNT = Rotation.from_euler("y", 90, degrees=True) * Rotation.from_euler("z", -90, degrees=True)  # camera ahead


def _project(P: np.ndarray) -> np.ndarray:
    px, _ = cv2.projectPoints(P.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, DIST)
    return px.reshape(-1, 2)


def test_recorded_attitudes_move_rolling_rows_to_the_stamp() -> None:
    """A camera turning at ~50 deg/s (its body's attitude recorded every frame) sees a tag row by row
    through a distorted lens: corrected, the corners are where a global shutter at the stamp sees them,
    to far below 0.05 px, where the shear was over a pixel."""
    w_body = np.radians([20.0, -30.0, 35.0])  # body FLU rate
    R_bc = MOUNT.as_matrix()
    w_cam = R_bc.T @ w_body
    clock = RowClock(READOUT_S, H)
    obs = Observations()
    obs.lenses.append(Calibration(W, H, K, DIST))
    mount = np.eye(4)
    mount[:3, :3] = R_bc
    obs.mountings.append(mount)
    R0 = Rotation.from_euler("z", 30, degrees=True)
    for k in range(3):
        t_us = 1_000_000 + k * 33_333
        R = R0 * Rotation.from_rotvec(w_body * (t_us - 1_000_000) * 1e-6)
        x, y, z, w = R.as_quat()
        obs.frames.append(FrameInfo(0, k, t_us, 0, (w, x, y, z)))
    centre = np.array([0.15, -0.1, 1.0])
    tag = Rotation.from_euler("xyz", [170, 10, 5], degrees=True).apply(object_corners(0.2)) + centre
    seen = []
    for P in tag:  # each corner at its own row's instant (exact iteration: the row depends on it)
        t = 0.0
        for _ in range(50):
            uv = _project(Rotation.from_rotvec(-w_cam * t).apply(P))[0]
            t_new = float(clock.dt_s(np.array([uv[1]]))[0])
            if abs(t_new - t) < 1e-12:
                break
            t = t_new
        seen.append(uv)
    obs.obs_frame.append(1)
    obs.obs_marker_id.append(3)
    obs.corners_px.append(np.array(seen))
    truth = _project(tag)
    assert np.abs(np.array(seen) - truth).max() > 1.0
    assert correct_input(obs, 0, clock) == 1
    assert np.abs(obs.corners_px[0] - truth).max() < 0.02
