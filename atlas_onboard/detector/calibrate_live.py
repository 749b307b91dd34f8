"""``atlas-onboard calibrate --device``: calibration views captured from a live camera by themselves.

Headless: the user moves the ChArUco board (or the camera) and holds it still now and then; every
frame is checked and a view is kept when the board is found, sharp, still, and adds coverage:

- sharp: the edge width across the board's squares, ``contrast / max gradient`` (about 2.5 sigma of
  a Gaussian blur), at most ``max_edge_px``; independent of the board's size and lighting;
- still: the board's corners moved at most ``max_motion_px`` (median) since the previous frame, so
  that neither motion blur nor a rolling shutter bends the view;
- coverage: the view puts corners into a cell of an image grid that has none yet, shows the board
  at a tilt (direction and angle) or an apparent size not yet seen, or differs enough from every
  kept view in where the board is, how large and how tilted (``min_novelty``, the distance of the
  descriptors as in ROS camera_calibration). A view that adds nothing (a duplicate) is refused.

It stops at ``views`` kept views, or once the coverage is complete with at least ``min_views``,
at the end of a file, or on Ctrl-C; then it calibrates with what it kept (:func:`calibrate`).
"""

from __future__ import annotations

import enum
import math
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.detector.calibrate import MIN_CORNERS

GRID_COLS, GRID_ROWS = 6, 4
TILT_BINS_DEG = (15.0, 30.0)  # below 15 deg: facing; 15-30 and above 30 deg, in four directions each
SIZE_BINS = (0.35, 0.6)  # the board's extent over the image's shorter side: far, middle, near
MIN_CELL_CORNERS = 2  # corners a view must put into a cell to count it covered


class Refusal(enum.Enum):
    """Why a frame was not kept as a view."""

    NO_BOARD = "no board"
    BLURRED = "blurred"
    MOVING = "moving"
    NOTHING_NEW = "nothing new"


@dataclass(frozen=True)
class ViewQuality:
    """What a frame shows of the board: ``edge_px`` edge width (px), ``motion_px`` median corner
    motion since the previous frame (px, inf without one), ``cells`` grid cells with corners,
    ``pose_bins`` the (tilt, size) bins it falls in, ``descriptor`` (x, y, size, tilt x, tilt y): the
    corners' centre over the image's width and height, their extent over its shorter side, and the
    board normal's x and y components."""

    n_corners: int
    edge_px: float
    motion_px: float
    cells: frozenset[tuple[int, int]]
    pose_bins: frozenset[str]
    descriptor: tuple[float, float, float, float, float]


@dataclass
class Coverage:
    """Covered grid cells and pose bins so far."""

    cells: set[tuple[int, int]] = field(default_factory=set)
    pose_bins: set[str] = field(default_factory=set)

    @staticmethod
    def all_pose_bins() -> set[str]:
        bins = {f"size-{s}" for s in ("far", "middle", "near")} | {"tilt-facing"}
        return bins | {f"tilt-{d}-{a}" for d in ("left", "right", "up", "down") for a in ("15", "30")}

    def fraction_cells(self) -> float:
        return len(self.cells) / (GRID_COLS * GRID_ROWS)

    def fraction_poses(self) -> float:
        return len(self.pose_bins) / len(self.all_pose_bins())

    def complete(self) -> bool:
        return self.fraction_cells() >= 0.9 and self.fraction_poses() >= 0.75

    def text(self) -> str:
        return (
            f"cells {len(self.cells)}/{GRID_COLS * GRID_ROWS}, poses {len(self.pose_bins)}/{len(self.all_pose_bins())}"
        )

    def grid(self) -> str:
        """The image grid as text: '#' a covered cell, '.' an empty one."""
        rows = ["".join("#" if (c, r) in self.cells else "." for c in range(GRID_COLS)) for r in range(GRID_ROWS)]
        return "\n".join(rows)


def edge_width_px(gray: NDArray[np.uint8], corners_px: NDArray[np.float64]) -> float:
    """Edge width (px) over the board's corners' hull: intensity range / 99th-percentile gradient.
    A sharp edge is about 1-1.5 px wide; a Gaussian blur of sigma s widens it to about 2.5 s."""
    hull = cv2.convexHull(corners_px.astype(np.float32)).astype(np.int32)
    x, y, w, h = cv2.boundingRect(hull)
    if w < 4 or h < 4:
        return math.inf
    roi = gray[y : y + h, x : x + w].astype(np.float32)
    mask = np.zeros(roi.shape, np.uint8)
    cv2.fillConvexPoly(mask, hull - np.array([x, y], np.int32), 1)
    gx = cv2.Sobel(roi, cv2.CV_32F, 1, 0, ksize=3, scale=1 / 8)
    gy = cv2.Sobel(roi, cv2.CV_32F, 0, 1, ksize=3, scale=1 / 8)
    inside = mask.astype(bool)
    if inside.sum() < 16:
        return math.inf
    grad = float(np.percentile(np.hypot(gx, gy)[inside], 99))
    lo, hi = np.percentile(roi[inside], (5, 95))
    return float(hi - lo) / grad if grad > 0 else math.inf


def board_normal(
    obj_xy_m: NDArray[np.float64], img_px: NDArray[np.float64], size: tuple[int, int]
) -> NDArray[np.float64]:
    """The board's unit normal in the camera frame (towards the camera), from its homography with a
    nominal camera (focal length = image width, centre at the middle): no calibration needed."""
    w, h = size
    K = np.array([[w, 0, w / 2], [0, w, h / 2], [0, 0, 1.0]])
    H, _ = cv2.findHomography(obj_xy_m.astype(np.float64), img_px.astype(np.float64))
    if H is None:
        return np.array([0.0, 0.0, -1.0])
    A = np.linalg.inv(K) @ H
    r1, r2 = A[:, 0], A[:, 1]
    normal = np.cross(r1 / np.linalg.norm(r1), r2 / np.linalg.norm(r2))
    normal /= np.linalg.norm(normal)
    return -normal if normal[2] > 0 else normal


def pose_bins(normal: NDArray[np.float64], img_px: NDArray[np.float64], size: tuple[int, int]) -> frozenset[str]:
    """The tilt (direction and angle) and apparent-size bins of a view."""
    w, h = size
    tilt = math.degrees(math.acos(min(1.0, abs(normal[2]))))
    bins = set()
    if tilt < TILT_BINS_DEG[0]:
        bins.add("tilt-facing")
    else:
        nx, ny = normal[0], normal[1]
        direction = ("right" if nx > 0 else "left") if abs(nx) >= abs(ny) else ("down" if ny > 0 else "up")
        bins.add(f"tilt-{direction}-{'30' if tilt >= TILT_BINS_DEG[1] else '15'}")
    extent = np.ptp(img_px, axis=0).max() / min(w, h)
    bins.add("size-" + ("far" if extent < SIZE_BINS[0] else "middle" if extent < SIZE_BINS[1] else "near"))
    return frozenset(bins)


@dataclass
class ViewSelector:
    """Decides frame by frame which views to keep (see the module's docstring)."""

    board: cv2.aruco.CharucoBoard
    max_edge_px: float = 3.0
    max_motion_px: float = 1.5
    min_novelty: float = 0.15
    kept: list[NDArray[np.uint8]] = field(default_factory=list)
    descriptors: list[tuple[float, ...]] = field(default_factory=list)
    coverage: Coverage = field(default_factory=Coverage)
    refused: Counter[Refusal] = field(default_factory=Counter)
    frames: int = 0
    _detector: cv2.aruco.CharucoDetector = field(init=False)
    _previous: dict[int, NDArray[np.float64]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._detector = cv2.aruco.CharucoDetector(self.board)

    def offer(self, gray: NDArray[np.uint8]) -> tuple[Refusal | None, ViewQuality | None]:
        """Look at one grey frame: (None, quality) if it was kept, else (why not, quality or None)."""
        self.frames += 1
        corners, ids, _, _ = self._detector.detectBoard(gray)
        if ids is None or len(ids) < MIN_CORNERS:
            self._previous = {}
            self.refused[Refusal.NO_BOARD] += 1
            return Refusal.NO_BOARD, None
        pts = corners.reshape(-1, 2).astype(np.float64)
        now = {int(i): p for i, p in zip(ids.ravel(), pts, strict=True)}
        common = [i for i in now if i in self._previous]
        motion = (
            float(np.median([np.linalg.norm(now[i] - self._previous[i]) for i in common]))
            if len(common) >= MIN_CORNERS
            else math.inf
        )
        self._previous = now
        h, w = gray.shape
        cells = Counter((min(int(x * GRID_COLS / w), GRID_COLS - 1), min(int(y * GRID_ROWS / h), GRID_ROWS - 1))
                        for x, y in pts)  # fmt: skip
        obj, img = self.board.matchImagePoints(corners, ids)
        normal = board_normal(obj.reshape(-1, 3)[:, :2], img.reshape(-1, 2), (w, h))
        centre = pts.mean(axis=0)
        extent = float(np.ptp(pts, axis=0).max() / min(w, h))
        q = ViewQuality(
            len(pts),
            edge_width_px(gray, pts),
            motion,
            frozenset(c for c, n in cells.items() if n >= MIN_CELL_CORNERS),
            pose_bins(normal, pts, (w, h)),
            (float(centre[0] / w), float(centre[1] / h), extent, float(normal[0]), float(normal[1])),
        )
        reason = None
        if q.edge_px > self.max_edge_px:
            reason = Refusal.BLURRED
        elif q.motion_px > self.max_motion_px:
            reason = Refusal.MOVING
        elif q.cells <= self.coverage.cells and q.pose_bins <= self.coverage.pose_bins and not self._novel(q):
            reason = Refusal.NOTHING_NEW
        if reason is not None:
            self.refused[reason] += 1
            return reason, q
        self.kept.append(gray.copy())
        self.descriptors.append(q.descriptor)
        self.coverage.cells |= q.cells
        self.coverage.pose_bins |= q.pose_bins
        return None, q

    def _novel(self, q: ViewQuality) -> bool:
        d = np.asarray(self.descriptors) - np.asarray(q.descriptor)
        return not self.descriptors or float(np.min(np.linalg.norm(d, axis=1))) >= self.min_novelty

    def refusals_text(self) -> str:
        return ", ".join(f"{r.value} {self.refused[r]}" for r in Refusal)


def collect_views(
    frames: Iterable[NDArray[np.uint8]],
    selector: ViewSelector,
    views: int = 30,
    min_views: int = 12,
    report: Callable[[str], None] = print,
    report_every: int = 100,
) -> ViewSelector:
    """Offer frames to ``selector`` until ``views`` are kept, or the coverage is complete with at
    least ``min_views``, or the frames end (a file, or a KeyboardInterrupt caught by the caller),
    reporting each kept view and every ``report_every`` frames the refusals so far."""
    for gray in frames:
        reason, q = selector.offer(gray)
        if reason is None and q is not None:
            report(
                f"view {len(selector.kept)} kept: {q.n_corners} corners, edge {q.edge_px:.1f} px,"
                f" {','.join(sorted(q.pose_bins))}; coverage {selector.coverage.text()}"
            )
            if len(selector.kept) >= views or (len(selector.kept) >= min_views and selector.coverage.complete()):
                break
        elif selector.frames % report_every == 0:
            report(f"{selector.frames} frames: refused {selector.refusals_text()}; coverage {selector.coverage.text()}")
    return selector
