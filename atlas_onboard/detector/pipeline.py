"""Frame in, MarkerData out: find the configured markers, undistort their corners, solve their poses.

Speed beyond the library: on a textured floor the library spends most of its time on the texture. Each
frame searches the regions where the markers of the previous frame are predicted to be (at a decimation
that keeps each marker wide enough), then the regions of strong black-white contrast elsewhere at full
resolution (cells whose darkest pixel is a small share of their brightest, as black ink beside white
paper is in any light; texture searched in vain is left alone for a few frames unless its contrast rises),
within a budget of pixels; for markers of weak contrast, a whole-image search at decimate 3 and one tile
of a full-resolution grid, every (other) frame while hunting and now and then while tracking: the recall
of decimate 1 at a fraction of its cost.

Trust: a marker whose corners touch the image border (or the border of the region it was found in) is
dropped (counted by reason), since its edges cannot be fitted; the corners of the others are refitted
in undistorted pixels (:func:`refine.refine_corners_undistorted`), which also measures their noise.
Markers of one entity that do not fit together are found by leaving each out in turn: the rest give the
entity's pose, and the one that disagrees is counted, logged and announced (:meth:`Detector.take_status`).
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.linalg import block_diag
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import SensorConfig, WorldConfig
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.markerdata import MarkerData, matrix_to_upper
from atlas_onboard.core.worldcheck import MovedMarker, MovedMarkerCheck
from atlas_onboard.detector import pose
from atlas_onboard.detector.backends import Detection, MarkerFinder
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.families import family
from atlas_onboard.detector.refine import refine_corners_undistorted

_logger = logging.getLogger(__name__)

MAX_AMBIGUITY = 1.0
JOINT_MISFIT = 3.0  # a joint fit this many times worse than its worst single square is not used
"""Detections whose IPPE ratio (chosen over other solution's reprojection error) exceeds this are
dropped (counted ``ambiguous_dropped``). Above ``AMBIGUITY_THRESHOLD`` (0.5) the two planar solutions
fit almost equally well and the chosen one may be the mirror image (a "flip", tens of degrees off):
such detections are kept with both solutions (counted ``ambiguous``) for the listener to resolve with
the current estimates (:mod:`atlas_onboard.core.ambiguity`). 1.0 keeps them all."""
SCAN_EVERY = 4  # frames between whole-image searches while tracking
SMALL_SIDE_PX = 40.0  # markers smaller than this are re-searched at full resolution
ROI_MARGIN = 0.4  # a region is the marker's predicted box grown by this fraction of its size on each side
MAX_REGION_DECIMATE = 3.0  # the hunt's decimation and the largest of a tracked marker's region
TILES = (3, 3)  # the grid of full-resolution tiles searched one a frame (columns, rows)
CANDIDATE_AREA = 0.06  # the most of the image searched each frame at full resolution around strong contrast
QUIET_FRAMES = 4  # a candidate region in which nothing was found is not searched again for this many frames
CELL_PX = 8  # contrast is measured in cells of this many pixels
MIN_RATIO = 0.6  # a candidate cell's contrast is at least this share of its brightest pixel (ink on paper)
TILE_OVERLAP_PX = 1.5 * SMALL_SIDE_PX  # adjacent tiles share this much: a small marker and its quiet zone
BORDER_MARGIN_PX = 6.0  # corners closer than this to an image or region border: the edge fit's reach, and 3 px
STATUS_INTERVAL_US = 60_000_000  # at most one STATUSTEXT a minute about disagreeing markers
LOG_INTERVAL_US = 5_000_000
MIN_CONTRAST = 20  # grey levels: a cell with less is not a marker's black and white (refine.MIN_CONTRAST)


@dataclass(frozen=True)
class Disagreement:
    """A marker that does not fit with the other markers of its entity in one image: its offset is the
    distance between where its own square puts it and where the others place it (camera frame, m)."""

    entity: str
    marker_id: int
    offset_m: float
    capture_time_us: int


@dataclass
class FrameReport:
    """What the last frame gave: ids found, ids reported, and why the others were not (id -> reason)."""

    found: list[int] = field(default_factory=list)
    reported: list[int] = field(default_factory=list)
    dropped: dict[int, str] = field(default_factory=dict)

    def explain(self) -> str:
        """One line saying why nothing (or not everything) found was reported."""
        if not self.found:
            return "no tag found"
        ids = ", ".join(str(i) for i in self.found)
        why = "; ".join(f"marker {i}: {r}" for i, r in sorted(self.dropped.items()))
        n = len(self.found)
        head = f"{n} tag{'s' if n != 1 else ''} found (ids {ids})"
        if not self.reported:
            return f"{head}; none reported: {why}"
        return f"{head}; reported {', '.join(str(i) for i in self.reported)}" + (f"; not: {why}" if why else "")


@dataclass(frozen=True)
class _Single:
    """One marker's own solve: its pose, undistorted corners (4, 2), their undistortion Jacobian
    (:func:`pose.undistortion_jacobian`, None without distortion) and measured corner noise (px)."""

    pose: pose.MarkerPose
    corners: NDArray[np.float64]
    stretch: NDArray[np.float64] | None
    measured_px: float
    corner_cov: NDArray[np.float64] | None = None  # (8, 8), px^2: refine.RefinedCorners.covariance


@dataclass
class Detector:
    """The detector of one sensor."""

    sensor: SensorConfig
    world: WorldConfig
    calibration: Calibration
    decimate: float = 2.0  # 1: every frame searched whole at full resolution (no tracking)
    track: bool = True
    max_ambiguity: float = MAX_AMBIGUITY
    joint: bool = True
    counters: Counter[str] = field(default_factory=Counter)

    def __post_init__(self) -> None:
        others = [m for m in self.world.markers.values() if m.entity != self.sensor.entity]
        self.sizes = {m.id: m.size_m for m in others}
        self.entity_of = {m.id: m.entity for m in others}
        self.marker_pose = {m.id: m.T_entity_marker for m in others}
        wanted = {m.id: m.family for m in self.world.markers.values() if m.entity != self.sensor.entity}
        self.finder = MarkerFinder(wanted, self.decimate, extra=(MAX_REGION_DECIMATE,) if self.track else ())
        self._last: list[NDArray[np.float64]] = []  # regions (x0, y0, x1, y1, decimate) to search next
        self._corners: dict[int, NDArray[np.float64]] = {}  # the previous frame's markers' corners
        # Whole-image searches and tiles in a phase of their own for each sensor: the cameras of one
        # node do not all search at once (their frames come at the same instants).
        self._frame = self.sensor.id % SCAN_EVERY
        self._tile = self.sensor.id % (TILES[0] * TILES[1])
        self._quiet_until = np.zeros((0, 0), np.int64)  # per cell: the frame until which it is not a candidate
        self.report = FrameReport()
        self.disagreements: Counter[int] = Counter()  # marker id -> images in which it disagreed
        self._status: deque[str] = deque()
        self._last_status_us: int | None = None
        self._last_log_us: int | None = None
        # The live world-file check (issue 21): the joint solves' verdicts over many images.
        self.world_check = MovedMarkerCheck()
        self._offsets: dict[int, NDArray[np.float64]] = {}  # this image's disagreeing markers (entity frame)
        self._moved_log_us: dict[tuple[str, int], int] = {}
        self._moved_status_us: int | None = None
        self.moved: dict[tuple[str, int], MovedMarker] = {}  # reported so far, the latest verdict of each

    def find(self, gray: NDArray[np.uint8], R_prev_now: Rotation | None = None) -> list[Detection]:
        """Markers in the frame, tracked from the previous one.

        ``R_prev_now``: the camera's rotation since the previous frame (maps directions in the camera
        frame now into the camera frame then, OpenCV axes), e.g. from the autopilot's attitude; given,
        the previous markers are predicted where that rotation moves them instead of by their last
        image motion (a fast turn moves a marker far more than its past motion says).

        Every frame: the regions where the markers of the previous frame are predicted to be (moved on
        by their last motion in the image) are searched at a decimation that keeps each marker at least
        ``SMALL_SIDE_PX`` wide (the library fits the edges at full resolution whatever the decimation);
        then the regions of strong black-white contrast outside the markers found
        (:func:`_contrast_regions`: black ink on white paper, and the library spends most of its time on
        the texture elsewhere), at most ``CANDIDATE_AREA`` of the image's
        pixels (divided by each region's decimation squared). For markers of weak contrast: the whole
        image at ``MAX_REGION_DECIMATE`` (large markers), every frame while hunting and every
        ``SCAN_EVERY`` frames while tracking, and the next tile of a ``TILES`` grid at full resolution
        (small ones), every other frame while hunting and every ``SCAN_EVERY`` frames while tracking.
        Without ``track`` (or with ``decimate`` 1), the whole image at full resolution.
        """
        if not self.track or self.decimate <= 1.0:
            return self.finder.find(gray, 1.0)
        h, w = gray.shape[:2]
        found: dict[int, Detection] = {}
        if R_prev_now is not None and self._corners:
            self._last = [_box(self._rotated(c, R_prev_now)) for c in self._corners.values()]
        hunting = not self._last
        k = self._frame
        if not hunting:
            self._roi_search(gray, self._last, found)
        if hunting or k % SCAN_EVERY == 0:
            new = []
            for d in self.finder.find(gray, MAX_REGION_DECIMATE):
                if d.marker_id not in found:
                    found[d.marker_id] = d
                    new.append(_box(d.corners_px))  # found again at the region's own decimation
            self._roi_search(gray, new, found)
            self.counters["scans"] += 1
        cells = (-(-h // CELL_PX), -(-w // CELL_PX))
        if self._quiet_until.shape != cells:
            self._quiet_until = np.zeros(cells, np.int64)
            self._quiet_level = np.zeros(cells, np.uint8)
        contrast, top = _cell_contrast(gray)
        # Texture searched lately is not searched again unless its contrast rose (a marker came in).
        quiet = (self._quiet_until > k) & (contrast <= self._quiet_level.astype(np.int16) + MIN_CONTRAST)
        taken = [np.concatenate([d.corners_px.min(axis=0), d.corners_px.max(axis=0)]) for d in found.values()]
        for region in _contrast_regions(contrast, top, taken, CANDIDATE_AREA * w * h, quiet):
            before = len(found)
            self._roi_search(gray, [region], found, only_new=True)
            self.counters["candidate_regions"] += 1
            if len(found) == before:
                x0, y0, x1, y1 = (max(int(v), 0) // CELL_PX for v in region[:4])
                self._quiet_until[y0 : y1 + 1, x0 : x1 + 1] = k + QUIET_FRAMES
                self._quiet_level[y0 : y1 + 1, x0 : x1 + 1] = contrast[y0 : y1 + 1, x0 : x1 + 1]
        if k % SCAN_EVERY == SCAN_EVERY // 2 or (hunting and k % 2 == 1):
            self._roi_search(gray, [self._next_tile(w, h)], found, only_new=True)
        self.counters["hunts" if hunting else "tracked_frames"] += 1
        self._frame += 1
        # Where each marker will be: moved on by its last motion in the image (constant velocity).
        previous = self._corners
        self._corners = {i: d.corners_px for i, d in found.items()}
        self._last = [_box(2 * c - previous[i] if i in previous else c) for i, c in self._corners.items()]
        return list(found.values())

    def _rotated(self, corners_px: NDArray[np.float64], R_prev_now: Rotation) -> NDArray[np.float64]:
        """Where corners (N, 2) of the previous image are seen now after the camera turned by
        ``R_prev_now`` (far points: a turn moves them alike whatever their depth)."""
        cal = self.calibration
        ideal = pose.undistort(corners_px, cal.K, cal.dist, cal.fisheye)
        rays_prev = np.column_stack([ideal, np.ones(len(ideal))]) @ np.linalg.inv(cal.K).T
        rays_now = R_prev_now.inv().apply(rays_prev)
        if np.any(rays_now[:, 2] <= 1e-3):  # turned out of view: nothing to predict from
            return corners_px
        pts = rays_now.reshape(-1, 1, 3)
        zero = np.zeros(3)
        if cal.fisheye:
            out, _ = cv2.fisheye.projectPoints(pts, zero, zero, cal.K, cal.dist)
        else:
            out, _ = cv2.projectPoints(pts, zero, zero, cal.K, cal.dist)
        return out.reshape(-1, 2)

    @property
    def tracking(self) -> bool:
        """Whether markers of the previous frame are tracked (False: the next frame is a hunt)."""
        return bool(self._last)

    def _next_tile(self, w: int, h: int) -> NDArray[np.float64]:
        """The next tile of the grid, grown so that every small marker (the decimated search finds
        the others) lies wholly inside one tile."""
        cols, rows = TILES
        k = self._tile % (cols * rows)
        self._tile += 1
        tx, ty = k % cols, k // cols
        m = TILE_OVERLAP_PX / 2
        return np.array(
            [tx * w // cols - m, ty * h // rows - m, (tx + 1) * w // cols + m, (ty + 1) * h // rows + m], float
        )

    def _checked(
        self, found: list[Detection], shape: tuple[int, ...], region: tuple[int, int, int, int]
    ) -> list[Detection]:
        """``found`` in a ``region`` (x0, y0, x1, y1) of the image without the detections whose corners
        touch a border of the region inside the image: the marker may be cut there (counted; it is found
        again when the whole image is searched)."""
        h, w = shape[:2]
        x0, y0, x1, y1 = region
        m = BORDER_MARGIN_PX
        out = []
        for d in found:
            lo, hi = d.corners_px.min(axis=0), d.corners_px.max(axis=0)
            if (
                (x0 > 0 and lo[0] < x0 + m)
                or (y0 > 0 and lo[1] < y0 + m)
                or (x1 < w and hi[0] > x1 - 1 - m)
                or (y1 < h and hi[1] > y1 - 1 - m)
            ):
                self.counters["dropped_region_border"] += 1
                continue
            out.append(d)
        return out

    def _roi_search(
        self,
        gray: NDArray[np.uint8],
        boxes: list[NDArray[np.float64]],
        found: dict[int, Detection],
        only_new: bool = False,
    ) -> None:
        """Search each region (boxes (x0, y0, x1, y1[, decimate]), merged where they overlap)."""
        h, w = gray.shape[:2]
        for x0, y0, x1, y1, decimate in _merge(boxes, w, h):
            shifted = []
            for d in self.finder.find(np.ascontiguousarray(gray[y0:y1, x0:x1]), decimate):
                if only_new and d.marker_id in found:
                    continue
                c = d.corners_px + np.array([x0, y0], dtype=float)
                shifted.append(Detection(d.marker_id, d.family, c, d.decision_margin))
            for d in self._checked(shifted, gray.shape, (x0, y0, x1, y1)):
                found[d.marker_id] = d
                self.counters["roi_finds"] += 1

    def detect(
        self, gray: NDArray[np.uint8], capture_time_us: int, R_prev_now: Rotation | None = None
    ) -> list[MarkerData]:
        """MarkerData of the configured markers in ``gray`` (``R_prev_now``: see :meth:`find`).

        With ``joint`` (the default), the markers of one entity seen together are solved as one
        rigid pattern (every corner at once, far better conditioned than any single square) and
        reported as one observation of the first of them; a lone marker is solved on its own. Why
        found markers were not reported is in :attr:`report`.
        """
        h, w = gray.shape[:2]
        self.calibration.check_size(w, h, f"sensor {self.sensor.name}")
        self.report = FrameReport()
        cal = self.calibration
        K = cal.K
        singles: dict[int, _Single] = {}
        for d in self.find(gray, R_prev_now):
            self.report.found.append(d.marker_id)
            if _at_border(d.corners_px, w, h):
                # A marker cut by the border, or one whose corner is extrapolated or nearly outside: its
                # edges cannot be fitted, and such poses were off by many of their sigmas.
                self.counters["dropped_image_border"] += 1
                self.report.dropped[d.marker_id] = "at the image border"
                continue
            corners = pose.undistort(d.corners_px, K, cal.dist, cal.fisheye)
            refined = refine_corners_undistorted(gray, corners, K, cal.dist, cal.fisheye)
            if refined is None:
                # The library's corners are straight-line fits in the distorted image: where the edge fit
                # fails (near the image's edge, under strong distortion or blur) they were off by many
                # times the corner noise, a wrong pose with a small sigma (issue 19). Not used.
                self.counters["refine_failed"] += 1
                self.report.dropped[d.marker_id] = "corner refinement failed"
                continue
            corners, measured_px, corner_cov = refined.corners, refined.sigma_px, refined.covariance
            stretch = pose.undistortion_jacobian(d.corners_px, K, cal.dist, cal.fisheye)
            size_m = self.sizes[d.marker_id]
            mp = pose.solve(corners, size_m, K, self._sigma_px(d.family), stretch, measured_px, corner_cov)
            if mp is None:
                self.counters["pnp_failed"] += 1
                self.report.dropped[d.marker_id] = "no pose"
                continue
            singles[d.marker_id] = _Single(mp, corners, stretch, measured_px, corner_cov)
        self.report.found.sort()
        out = []
        groups: dict[str, list[int]] = {}
        for mid in sorted(singles):
            groups.setdefault(self.entity_of[mid], []).append(mid)
        for entity, ids in groups.items():
            if self.joint and len(ids) > 1:
                self._offsets = {}
                md, used = self._robust_joint(entity, ids, singles, capture_time_us)
                if len(ids) >= 3 and used is not None:  # one that does not fit can be singled out
                    self._check_world(entity, ids, capture_time_us)
                if md is not None:
                    out.append(md)
                    self.report.reported += used
                    continue
                if used is None:  # the squares contradict each other: none of them is trusted in this image
                    continue
            for mid in ids:
                if (entity, mid) in self.moved:  # alone it would move the pose by its offset
                    self.counters["dropped_moved"] += 1
                    self.report.dropped[mid] = "reported moved (the world file disagrees with what is seen)"
                    continue
                mp = singles[mid].pose
                ambiguous = mp.ambiguity > AMBIGUITY_THRESHOLD
                if mp.ambiguity > self.max_ambiguity or (ambiguous and mp.p_alt_m is None):
                    # Too poor a fit, or nothing downstream could resolve it: drop it here.
                    self.counters["ambiguous_dropped"] += 1
                    self.report.dropped[mid] = "ambiguous"
                    continue
                self.counters["ambiguous"] += ambiguous
                alt = (mp.p_alt_m, mp.q_alt_xyzw) if mp.p_alt_m is not None and mp.q_alt_xyzw is not None else None
                out.append(self._markerdata(mid, mp.p_m, mp.q_xyzw, mp.sigma_m, mp.reprojection_error_px, mp.ambiguity,
                                            capture_time_us, alt, mp.covariance))  # fmt: skip
                self.report.reported.append(mid)
        self.counters["detections"] += len(out)
        return out

    def take_status(self) -> list[str]:
        """STATUSTEXT lines to send (at most one a minute), emptied by the call."""
        out = []
        while self._status:  # a deque: the camera thread appends while the node's thread takes
            out.append(self._status.popleft())
        return out

    def _sigma_px(self, family_name: str) -> float:
        return pose.SIGMA_PX_APRILTAG if family(family_name).is_apriltag else pose.SIGMA_PX_ARUCO

    def _robust_joint(
        self, entity: str, ids: list[int], singles: dict[int, _Single], capture_time_us: int
    ) -> tuple[MarkerData | None, list[int] | None]:
        """The entity's observation from the markers that fit together, and the ids used.

        When all of them do not fit (:meth:`_joint`), the marker whose removal fits the rest best is
        left out, again while they do not fit and at least two remain: a moved or mis-measured marker
        costs only itself. Two markers that disagree cannot say which of them moved: neither is used.
        Returns (None, ids) when the joint solve failed (the squares are then reported one by one),
        (None, None) when no subset of two or more fits.
        """
        md, misfit = self._joint(ids, singles, capture_time_us)
        if md is not None or not misfit:
            return md, ids
        used = list(ids)
        while len(used) > 2:
            trials = []
            for m in used:
                rest = [i for i in used if i != m]
                md_r, misfit_r, err = self._joint(rest, singles, capture_time_us, count=False, with_error=True)
                if md_r is not None or misfit_r:
                    trials.append((err, m, rest, md_r))
            if not trials:
                break
            _, m, used, md = min(trials, key=lambda t: t[0])
            offset = self._offset_m(m, used, singles)
            self._disagrees(entity, m, offset, capture_time_us)
            if md is not None:
                self.counters["joint"] += 1
                self.counters["joint_without_disagreeing"] += 1
                return md, used
        for m in used:
            self.report.dropped.setdefault(m, "joint misfit: the markers do not fit together as placed")
        if len(used) == 2:
            a, b = used
            offset = self._offset_m(b, [a], singles)
            self.report.dropped[a] = self.report.dropped[b] = (
                f"joint misfit, markers {a} and {b} disagree by {offset * 100:.1f} cm"
            )
            self._log_disagreement(entity, f"markers {a} and {b} disagree", offset, capture_time_us)
        return None, None

    def _offset(self, m: int, others: list[int], singles: dict[int, _Single]) -> NDArray[np.float64] | None:
        """(3,) where marker ``m``'s own square is minus where the joint pose of ``others`` puts it,
        in the entity's frame (m); None when the others cannot be solved."""
        sol = self._joint_solution(others, singles)
        if sol is None:
            return None
        T_cam_entity = RigidTransform.from_components(sol[1], Rotation.from_rotvec(sol[0]))
        predicted = (T_cam_entity * self.marker_pose[m]).translation
        return T_cam_entity.rotation.inv().apply(singles[m].pose.p_m - predicted)

    def _offset_m(self, m: int, others: list[int], singles: dict[int, _Single]) -> float:
        """How far marker ``m``'s own square is from where the joint pose of ``others`` puts it (m)."""
        offset = self._offset(m, others, singles)
        if offset is not None:
            self._offsets[m] = offset
        return math.nan if offset is None else float(np.linalg.norm(offset))

    def _check_world(self, entity: str, ids: list[int], capture_time_us: int) -> None:
        """Feed the image's verdict to the live check; say a marker that has moved (log at most once a
        minute per marker, a STATUSTEXT at most once a minute, ``markers_moved`` counts distinct markers)."""
        verdicts = self.world_check.add(capture_time_us, entity, ids, self._offsets)
        still = {m.marker_id for m in verdicts}
        for mid in ids:  # a marker put back (it fits again in most images) is used again
            if (entity, mid) in self.moved and mid not in still and mid not in self._offsets:
                if not self.world_check.disagrees(entity, mid):
                    del self.moved[(entity, mid)]
                    _logger.warning("sensor %s: %s marker %d fits the world file again", self.sensor.name, entity, mid)
        for moved in verdicts:
            key = (entity, moved.marker_id)
            if key not in self.moved:
                self.counters["markers_moved"] += 1
            self.moved[key] = moved
            dx, dy, dz = moved.offset_m
            last = self._moved_log_us.get(key)
            if last is None or capture_time_us - last >= STATUS_INTERVAL_US:
                self._moved_log_us[key] = capture_time_us
                _logger.warning(
                    "sensor %s: %s marker %d has moved: seen %.1f cm from its place in the world file"
                    " (%+.3f %+.3f %+.3f m) in %d of %d images; it is not used while it disagrees",
                    self.sensor.name, entity, moved.marker_id, moved.distance_m * 100, dx, dy, dz,
                    moved.disagreeing, moved.views,
                )  # fmt: skip
            if self._moved_status_us is None or capture_time_us - self._moved_status_us >= STATUS_INTERVAL_US:
                self._moved_status_us = capture_time_us
                self._status.append(
                    f"atlas: marker {moved.marker_id} moved {round(dx * 100):+d} {round(dy * 100):+d}"
                    f" {round(dz * 100):+d} cm"[:50]
                )

    def _disagrees(self, entity: str, m: int, offset_m: float, capture_time_us: int) -> None:
        self.counters["marker_disagrees"] += 1
        self.disagreements[m] += 1
        self.report.dropped[m] = f"joint misfit, marker {m} disagrees by {offset_m * 100:.1f} cm"
        self._log_disagreement(entity, f"marker {m} disagrees", offset_m, capture_time_us)

    def _log_disagreement(self, entity: str, what: str, offset_m: float, capture_time_us: int) -> None:
        text = f"{entity}: {what} by {offset_m * 100:.1f} cm"
        if self._last_log_us is None or abs(capture_time_us - self._last_log_us) >= LOG_INTERVAL_US:
            self._last_log_us = capture_time_us
            _logger.warning("sensor %s: %s with the world file (not used)", self.sensor.name, text)
        if self._last_status_us is None or abs(capture_time_us - self._last_status_us) >= STATUS_INTERVAL_US:
            self._last_status_us = capture_time_us
            self._status.append(f"atlas {text}"[:50])

    def _joint_solution(self, ids: list[int], singles: dict[int, _Single]) -> tuple | None:
        """rvec, tvec (T_camera_entity), RMS error and sigma of the joint solve of ``ids``, or None."""
        obj = np.vstack([self.marker_pose[m].apply(pose.object_corners(self.sizes[m])) for m in ids])
        img = np.vstack([singles[m].corners for m in ids])
        # Start from the least ambiguous single solution, moved to the entity frame.
        best = min(ids, key=lambda m: singles[m].pose.ambiguity if np.isfinite(singles[m].pose.ambiguity) else 1.0)
        mp = singles[best].pose
        T_cam_entity = (
            RigidTransform.from_components(mp.p_m, Rotation.from_quat(mp.q_xyzw)) * self.marker_pose[best].inv()
        )
        guess = (T_cam_entity.rotation.as_rotvec(), T_cam_entity.translation)
        fam = self.world.markers[ids[0]].family
        return pose.solve_joint(obj, img, self.calibration.K, self._sigma_px(fam), guess)

    def _joint(
        self,
        ids: list[int],
        singles: dict[int, _Single],
        capture_time_us: int,
        count: bool = True,
        with_error: bool = False,
    ) -> tuple:
        """The entity's observation from all its squares at once; (None, False) when the solve
        failed (the squares are then reported one by one), (None, True) when they do not fit together.
        ``with_error``: the joint RMS error relative to its limit as a third element."""
        anchor = ids[0]
        T_entity_anchor = self.marker_pose[anchor]
        fam = self.world.markers[anchor].family
        sol = self._joint_solution(ids, singles)
        if sol is None:
            self.counters["joint_failed"] += count
            return (None, False, math.inf) if with_error else (None, False)
        rvec, tvec, err, sigma = sol
        # Markers that do not fit together as the world file places them (a misplaced marker, a bad
        # corner, motion blur that moves each square differently) give a joint fit far worse than
        # each square's own: the joint pose is then wrong in a way no sigma describes.
        worst_single = max(singles[m].pose.reprojection_error_px for m in ids)
        limit = JOINT_MISFIT * max(worst_single, self._sigma_px(fam))
        if err > limit:
            self.counters["joint_misfit"] += count
            return (None, True, err / limit) if with_error else (None, True)
        T = RigidTransform.from_components(tvec, Rotation.from_rotvec(rvec)) * T_entity_anchor
        # The covariance of the anchor's pose: the same corners, in the anchor's frame.
        obj = np.vstack([self.marker_pose[m].apply(pose.object_corners(self.sizes[m])) for m in ids])
        obj_anchor = T_entity_anchor.inv().apply(obj)
        model_px = pose.corner_noise_px(self._sigma_px(fam), float(np.median([_side(singles[m].corners) for m in ids])))
        measured = [singles[m].measured_px for m in ids]
        sigma_px = math.hypot(max(measured), pose.CORNER_FLOOR_PX) if min(measured) > 0 else model_px
        stretches = [singles[m].stretch for m in ids]
        stretch = None if any(x is None for x in stretches) else np.concatenate(stretches)
        R = T.rotation.as_matrix()
        covs = [singles[m].corner_cov for m in ids]
        img = np.vstack([singles[m].corners for m in ids])
        if all(c is not None for c in covs):  # the squares' own corner covariances, one block each
            cov = pose.fitted_covariance(R, T.translation, obj_anchor, self.calibration.K, img, block_diag(*covs))
        else:
            cov = pose.pose_covariance(R, T.translation, obj_anchor, self.calibration.K, sigma_px, err, stretch)
        self.counters["joint"] += count
        md = self._markerdata(anchor, T.translation, T.rotation.as_quat(), sigma, err, 0.0, capture_time_us, None, cov)
        return (md, False, err / limit) if with_error else (md, False)

    def _markerdata(
        self,
        marker_id: int,
        p: NDArray[np.float64],
        q_xyzw: NDArray[np.float64],
        sigma: float,
        err: float,
        ambiguity: float,
        capture_time_us: int,
        alt: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
        covariance: NDArray[np.float64] | None = None,
    ) -> MarkerData:
        """``alt``: the other IPPE solution (p, q_xyzw), carried along for the listener; ``covariance``:
        the chosen solution's 6x6 (:func:`pose.pose_covariance`; None: the record carries none)."""
        x, y, z, w = q_xyzw
        if alt is None:
            p_alt, q_alt = (math.nan,) * 3, (math.nan,) * 4
        else:
            pa, (xa, ya, za, wa) = alt
            p_alt, q_alt = (float(pa[0]), float(pa[1]), float(pa[2])), (float(wa), float(xa), float(ya), float(za))
        return MarkerData(
            sensor_id=self.sensor.id,
            marker_id=marker_id,
            sigma_m=float(sigma),
            p_sensor_marker_m=(float(p[0]), float(p[1]), float(p[2])),
            q_sensor_marker_wxyz=(float(w), float(x), float(y), float(z)),
            capture_time_us=capture_time_us,
            reprojection_error_px=float(err),
            ambiguity_ratio=float(ambiguity),
            p_sensor_marker_alt_m=p_alt,  # type: ignore[arg-type]
            q_sensor_marker_alt_wxyz=q_alt,  # type: ignore[arg-type]
            covariance=matrix_to_upper(covariance) if covariance is not None else (),
        )


def _at_border(c: NDArray[np.float64], w: int, h: int) -> bool:
    """Whether any corner (c: (4, 2) pixels) lies within ``BORDER_MARGIN_PX`` of the image's border or outside."""
    lo, hi = c.min(axis=0), c.max(axis=0)
    m = BORDER_MARGIN_PX
    return bool(lo[0] < m or lo[1] < m or hi[0] > w - 1 - m or hi[1] > h - 1 - m)


def _side(c: NDArray[np.float64]) -> float:
    return float(np.mean(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)))


def _box(c: NDArray[np.float64]) -> NDArray[np.float64]:
    """The region (x0, y0, x1, y1, decimate) to search for a marker with corners ``c`` in the next
    frame: its box grown by ``ROI_MARGIN``, decimated while the marker stays ``SMALL_SIDE_PX`` wide
    (at most ``MAX_REGION_DECIMATE``)."""
    lo, hi = c.min(axis=0), c.max(axis=0)
    grow = (hi - lo) * ROI_MARGIN + 8
    decimate = float(min(max(math.floor(_side(c) / SMALL_SIDE_PX), 1), MAX_REGION_DECIMATE))
    return np.concatenate([lo - grow, hi + grow, [decimate]])


def _cell_contrast(gray: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Each ``CELL_PX`` cell's contrast (brightest minus darkest pixel) and brightest pixel, after a 2x2
    average (so that one noisy pixel does not count); each of shape (ceil(h / CELL_PX), ceil(w / CELL_PX))."""
    h, w = gray.shape[:2]
    cell = CELL_PX // 2
    small = cv2.resize(gray, (-(-w // 2), -(-h // 2)), interpolation=cv2.INTER_AREA)
    kernel = np.ones((cell, cell), np.uint8)
    top = cv2.dilate(small, kernel, anchor=(0, 0))[::cell, ::cell]
    bottom = cv2.erode(small, kernel, anchor=(0, 0))[::cell, ::cell]
    return cv2.subtract(top, bottom), top


def _contrast_regions(
    contrast: NDArray[np.uint8],
    top: NDArray[np.uint8],
    taken: list[NDArray[np.float64]],
    budget_px: float,
    quiet: NDArray[np.bool_] | None = None,
) -> list[NDArray[np.float64]]:
    """Regions (x0, y0, x1, y1, decimate) of the strongest black-white contrast outside the boxes
    ``taken`` (x0, y0, x1, y1: the markers found already) and the ``quiet`` cells, the strongest first,
    at most ``budget_px`` pixels (divided by the decimation squared) in all.

    ``contrast`` and ``top``: :func:`_cell_contrast`. Black ink reflects a tenth or less of what white
    paper does, whatever the light: a printed marker's outline crosses cells whose darkest pixel is at
    most ``1 - MIN_RATIO`` of their brightest; such cells (with at least ``MIN_CONTRAST``), with their
    neighbours, are joined into regions, strongest contrast first.
    """
    contrast = np.where(contrast >= MIN_RATIO * np.maximum(top, 1), contrast, 0).astype(np.uint8)
    for x0, y0, x1, y1, *_ in taken:  # markers found: their cells are not candidates
        x0, y0 = max(int(x0), 0) // CELL_PX, max(int(y0), 0) // CELL_PX
        contrast[y0 : -(-int(y1) // CELL_PX), x0 : -(-int(x1) // CELL_PX)] = 0
    if quiet is not None:  # searched lately and found to be texture
        contrast[quiet] = 0
    mask = (contrast >= MIN_CONTRAST).astype(np.uint8)
    mask = cv2.dilate(mask, np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    peaks = []
    for i in range(1, n):
        x, y, bw, bh = stats[i, :4]
        inside = labels[y : y + bh, x : x + bw] == i
        peaks.append((-int(contrast[y : y + bh, x : x + bw][inside].max()), i))
    out = []
    m = BORDER_MARGIN_PX
    for _, i in sorted(peaks):
        x, y, bw, bh = (int(v) * CELL_PX for v in stats[i, :4])
        # A wide region holds large markers (or clutter): searched decimated, as a tracked one would be.
        side = min(bw, bh) - 2 * CELL_PX  # the largest marker it can hold
        decimate = float(min(max(side // SMALL_SIDE_PX, 1), MAX_REGION_DECIMATE))
        cost = (bw + 2 * m) * (bh + 2 * m) / decimate**2
        if cost > budget_px:
            continue
        budget_px -= cost
        out.append(np.array([x - m, y - m, x + bw + m, y + bh + m, decimate]))
    return out


def _area(r: list[float]) -> float:
    return (r[2] - r[0]) * (r[3] - r[1])


def _merge(boxes: list[NDArray[np.float64]], w: int, h: int) -> list[tuple[int, int, int, int, float]]:
    """Clip boxes (x0, y0, x1, y1[, decimate]; 1 if not given) to the image and merge overlapping ones
    (so no marker is cut in two), a merged region at the smallest of its decimations."""
    rects = [
        [max(int(b[0]), 0), max(int(b[1]), 0), min(int(b[2]) + 1, w), min(int(b[3]) + 1, h), b[4] if len(b) > 4 else 1]
        for b in boxes
    ]
    rects = [r for r in rects if r[2] - r[0] >= 16 and r[3] - r[1] >= 16]
    merged: list[list[float]] = []
    for r in sorted(rects):
        for m in merged:
            union = (max(m[2], r[2]) - min(m[0], r[0])) * (max(m[3], r[3]) - min(m[1], r[1]))
            # Overlapping boxes are searched as one where that is cheaper than searching both (each
            # holds its own marker whole).
            if r[0] <= m[2] and r[2] >= m[0] and r[1] <= m[3] and r[3] >= m[1] and union <= _area(r) + _area(m):
                m[:] = [min(m[0], r[0]), min(m[1], r[1]), max(m[2], r[2]), max(m[3], r[3]), min(m[4], r[4])]
                break
        else:
            merged.append(r)
    return [(int(a), int(b), int(c), int(d), float(e)) for a, b, c, d, e in merged]
