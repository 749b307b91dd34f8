"""``atlas-onboard calibrate``: print a ChArUco board, capture views of it from a camera (kept by
themselves: sharp, still, adding coverage) or read them from a folder, and write the calibration."""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.config import CameraConfig
from atlas_onboard.detector.calibrate import MIN_VIEWS, board, calibrate
from atlas_onboard.detector.calibrate_live import Coverage, Refusal, ViewSelector, collect_views
from atlas_onboard.detector.calibration import write_opencv
from atlas_onboard.detector.sources import IMAGE_SUFFIXES, open_source
from atlas_onboard.errors import AtlasError


def capture_views(args: argparse.Namespace, board: cv2.aruco.CharucoBoard) -> list[NDArray[np.uint8]]:
    """The CLI's ``--device``: views kept from the camera until enough, its end or Ctrl-C, with the
    coverage printed as it goes and at the end; they are written to ``--save-views`` if given."""
    if args.views < MIN_VIEWS or not MIN_VIEWS <= args.min_views <= args.views:
        raise AtlasError(f"--views/--min-views: expected {MIN_VIEWS} <= min-views <= views, got {args.min_views}"
                         f" and {args.views}")  # fmt: skip
    camera = CameraConfig(
        source=str(args.device), width_px=args.width, height_px=args.height, fps=args.fps, fourcc=args.fourcc
    )
    source = open_source(camera, fast=True)
    selector = ViewSelector(board, max_edge_px=args.max_edge_px, max_motion_px=args.max_motion_px)
    print(f"capturing from {args.device}: hold the board still in many places, tilts and distances; Ctrl-C ends",
          flush=True)  # fmt: skip
    try:
        collect_views((f.gray for f in source.frames()), selector, args.views, args.min_views,
                      lambda line: print(line, flush=True))  # fmt: skip
    except KeyboardInterrupt:
        print("stopped (Ctrl-C)", flush=True)
    finally:
        source.close()
    print(f"{len(selector.kept)} views kept of {selector.frames} frames; refused {selector.refusals_text()}")
    print(f"coverage {selector.coverage.text()} (image cells, '#' covered):")
    print(selector.coverage.grid())
    missing = sorted(Coverage.all_pose_bins() - selector.coverage.pose_bins)
    if missing:
        print(f"poses not seen: {', '.join(missing)}")
    if not selector.kept and selector.refused[Refusal.BLURRED]:
        print(f"every view with the board was blurred: more light, focus, or a larger --max-edge-px"
              f" (now {args.max_edge_px:g})")  # fmt: skip
    if args.save_views is not None:
        try:
            args.save_views.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise AtlasError(f"--save-views: cannot create {args.save_views} ({exc.strerror})") from None
        for k, img in enumerate(selector.kept):
            if not cv2.imwrite(str(args.save_views / f"view-{k:03d}.png"), img):
                raise AtlasError(f"--save-views: cannot write {args.save_views}")
    return selector.kept


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
