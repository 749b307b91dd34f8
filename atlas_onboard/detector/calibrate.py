"""``atlas-onboard calibrate``: camera intrinsics from views of a ChArUco board, written as the OpenCV
YAML the detector reads.

A ChArUco board (a chessboard with ArUco markers in its white squares) gives sub-pixel chessboard
corners that are identified even when the board is partly out of view. Take 15-40 views at different
distances and angles, covering the whole image; `atlas-onboard calibrate --board-image board.png`
writes a board to print. ``--device`` captures the views from a live camera by itself
(:mod:`atlas_onboard.detector.calibrate_live`).
"""

from __future__ import annotations

import cv2
import numpy as np

from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.families import opencv_dictionary
from atlas_onboard.errors import AtlasError

MIN_CORNERS = 8
MIN_VIEWS = 5


def board(squares_x: int, squares_y: int, square_m: float, marker_m: float, dictionary: str) -> cv2.aruco.CharucoBoard:
    if not 0 < marker_m < square_m:
        raise AtlasError(f"--marker: expected a marker smaller than the square ({square_m} m), got {marker_m}")
    return cv2.aruco.CharucoBoard((squares_x, squares_y), square_m, marker_m, opencv_dictionary(dictionary))


def calibrate(
    images: list[np.ndarray], b: cv2.aruco.CharucoBoard, fisheye: bool = False
) -> tuple[Calibration, float, int]:
    """Intrinsics from grey views of the board: (calibration, RMS reprojection error px, views used)."""
    detector = cv2.aruco.CharucoDetector(b)
    obj_pts, img_pts = [], []
    size = None
    for gray in images:
        if size is None:
            size = gray.shape[::-1]
        elif gray.shape[::-1] != size:
            raise AtlasError(f"calibrate: images of different sizes ({size} and {gray.shape[::-1]})")
        corners, ids, _, _ = detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            continue
        obj, img = b.matchImagePoints(corners, ids)
        obj_pts.append(obj.astype(np.float32))
        img_pts.append(img.astype(np.float32))
    if len(obj_pts) < MIN_VIEWS:
        raise AtlasError(f"calibrate: the board was found in {len(obj_pts)} views; need at least {MIN_VIEWS}")
    assert size is not None
    if fisheye:
        K, D = np.eye(3), np.zeros(4)
        flags = cv2.fisheye.CALIB_RECOMPUTE_EXTRINSIC | cv2.fisheye.CALIB_FIX_SKEW
        rms, K, D, _, _ = cv2.fisheye.calibrate(
            [o.reshape(-1, 1, 3) for o in obj_pts], [i.reshape(-1, 1, 2) for i in img_pts], size, K, D, flags=flags
        )
    else:
        rms, K, D, _, _ = cv2.calibrateCamera(obj_pts, img_pts, size, None, None)
    return (
        Calibration(size[0], size[1], np.asarray(K, float), np.asarray(D, float).ravel(), fisheye, float(rms)),
        float(rms),
        len(obj_pts),
    )
