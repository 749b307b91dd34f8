"""``atlas-onboard calibrate``: camera intrinsics from views of a ChArUco board, written as the OpenCV
YAML the detector reads.

A ChArUco board (a chessboard with ArUco markers in its white squares) gives sub-pixel chessboard
corners that are identified even when the board is partly out of view. Take 15-40 views at different
distances and angles, covering the whole image; `atlas-onboard calibrate --board-image board.png`
writes a board to print. ``--device`` captures the views from a live camera by itself
(:mod:`atlas_onboard.detector.calibrate_live`).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from atlas_onboard.detector.calibration import Calibration, write_opencv
from atlas_onboard.detector.families import opencv_dictionary
from atlas_onboard.detector.sources import IMAGE_SUFFIXES
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


def _cmd(args: argparse.Namespace) -> int:
    b = board(args.squares_x, args.squares_y, args.square, args.marker, args.dictionary)
    if args.board_image:
        px_per_square = 200
        img = b.generateImage(
            (args.squares_x * px_per_square, args.squares_y * px_per_square), marginSize=px_per_square // 2
        )
        if not cv2.imwrite(str(args.board_image), img):
            raise AtlasError(f"--board-image: cannot write {args.board_image}")
        print(f"wrote {args.board_image}: print it so that one square measures {args.square * 1000:g} mm")
        return 0
    if (args.images is None) == (args.device is None) or args.out is None:
        raise AtlasError("calibrate: give --images DIR or --device SRC, and --out FILE (or --board-image FILE)")
    if args.device is not None:
        from atlas_onboard.detector.calibrate_live import capture_views

        images = capture_views(args, b)
    else:
        if not Path(args.images).is_dir():
            raise AtlasError(f"--images: {args.images} is not a directory")
        files = sorted(p for p in Path(args.images).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        images = [g for g in (cv2.imread(str(p), cv2.IMREAD_GRAYSCALE) for p in files) if g is not None]
    cal, rms, used = calibrate(images, b, args.fisheye)
    write_opencv(Path(args.out), cal)
    k = cal.K
    print(f"{used} of {len(images)} views used; RMS reprojection error {rms:.3f} px")
    print(f"fx {k[0, 0]:.2f} fy {k[1, 1]:.2f} cx {k[0, 2]:.2f} cy {k[1, 2]:.2f}")
    print(f"distortion {np.round(cal.dist, 5).tolist()}")
    print(f"wrote {args.out}")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = sub.add_parser("calibrate", help="camera calibration from views of a ChArUco board")
    p.add_argument("--images", type=Path, help="folder of views of the board")
    p.add_argument("--out", type=Path, help="calibration file to write (OpenCV YAML)")
    p.add_argument("--squares-x", type=int, default=7)
    p.add_argument("--squares-y", type=int, default=5)
    p.add_argument("--square", type=float, default=0.04, help="square side, metres (measure the print)")
    p.add_argument("--marker", type=float, default=0.03, help="marker side, metres")
    p.add_argument("--dictionary", default="DICT_4X4_50")
    p.add_argument("--fisheye", action="store_true", help="equidistant (fisheye) model")
    p.add_argument("--board-image", type=Path, help="write a board image to print, and stop")
    live = p.add_argument_group("live capture (--device): views kept by themselves, then calibrated")
    live.add_argument("--device", help="V4L2 index or path, stream URL or video file to capture views from")
    live.add_argument("--width", type=int, default=0, help="requested frame width, px (default: the device's)")
    live.add_argument("--height", type=int, default=0, help="requested frame height, px")
    live.add_argument("--fps", type=float, default=0.0, help="requested frame rate, Hz")
    live.add_argument("--fourcc", default="", help="V4L2 pixel format, e.g. MJPG")
    live.add_argument("--views", type=int, default=30, help="stop at this many views (default 30)")
    live.add_argument("--min-views", type=int, default=12, help="or at full coverage with this many (default 12)")
    live.add_argument("--max-edge-px", type=float, default=3.0, help="sharpness: widest edge kept, px (default 3)")
    live.add_argument("--max-motion-px", type=float, default=1.5, help="stillness: board motion per frame, px")
    live.add_argument("--save-views", type=Path, help="also write the kept views here (for --images later)")
    p.set_defaults(func=_cmd)
