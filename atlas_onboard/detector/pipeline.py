"""Frame in, MarkerData out: find the configured markers, undistort their corners, solve their poses.

Speed beyond the library: with nothing tracked, each frame searches the whole image at decimate 3 (nine
times fewer pixels) and one tile of a grid at full resolution (a different tile each time, so small
markers are found within a grid's worth of frames); the regions where markers were last seen are
searched every frame, at a decimation that keeps each marker wide enough, and the whole image and the
tiles now and then: the recall of decimate 1 after a few frames, at a fraction of its cost.

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

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import SensorConfig, WorldConfig
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.markerdata import MarkerData, matrix_to_upper
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
TILE_OVERLAP_PX = 1.5 * SMALL_SIDE_PX  # adjacent tiles share this much: a small marker and its quiet zone
BORDER_MARGIN_PX = 6.0  # corners closer than this to an image or region border: the edge fit's reach, and 3 px
STATUS_INTERVAL_US = 60_000_000  # at most one STATUSTEXT a minute about disagreeing markers
LOG_INTERVAL_US = 5_000_000


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


@dataclass
class Detector:
    """The detector of one sensor."""

    sensor: SensorConfig
    world: WorldConfig
    calibration: Calibration
    decimate: float = 2.0
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
        self.report = FrameReport()
        self.disagreements: Counter[int] = Counter()  # marker id -> images in which it disagreed
        self._status: deque[str] = deque()
        self._last_status_us: int | None = None
        self._last_log_us: int | None = None

    def find(self, gray: NDArray[np.uint8]) -> list[Detection]:
        """Markers in the frame, tracked from the previous one.

        Every frame, the regions where the markers of the previous frame are predicted to be (moved on
        by their last motion in the image) are searched, at a
        decimation that keeps the marker at least 1.5 ``SMALL_SIDE_PX`` wide (the library fits the
        edges at full resolution whatever the decimation). When nothing is tracked (hunting), every
        frame searches the whole image at ``MAX_REGION_DECIMATE`` (large markers) and the next tile of
        a ``TILES`` grid at full resolution (small ones, found within a grid's worth of frames); while
        tracking, the whole image is searched at ``decimate`` every ``SCAN_EVERY`` frames (and when
        every tracked marker is lost), and a tile every other frame.
        """
        if not self.track or self.decimate <= 1.0:
            return self.finder.find(gray, 1.0)
        h, w = gray.shape[:2]
        found: dict[int, Detection] = {}
        hunting = not self._last
        k = self._frame
        if hunting:
            decimate, tile = MAX_REGION_DECIMATE, True
        else:
            self._roi_search(gray, self._last, found)
            decimate = self.decimate if k % SCAN_EVERY == 0 or not found else 0.0
            tile = k % 2 == 1
        if decimate:
            new = []
            for d in self.finder.find(gray, decimate):
                if d.marker_id not in found:
                    found[d.marker_id] = d
                    new.append(_box(d.corners_px))  # found again at the region's own decimation
            self._roi_search(gray, new, found)
            self.counters["hunts" if hunting else "scans"] += 1
        if tile:
            self._roi_search(gray, [self._next_tile(w, h)], found, only_new=True)
        self._frame += 1
        # Where each marker will be: moved on by its last motion in the image (constant velocity).
        previous = self._corners
        self._corners = {i: d.corners_px for i, d in found.items()}
        self._last = [_box(2 * c - previous[i] if i in previous else c) for i, c in self._corners.items()]
        return list(found.values())

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

    def detect(self, gray: NDArray[np.uint8], capture_time_us: int) -> list[MarkerData]:
        """MarkerData of the configured markers in ``gray``.

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
        for d in self.find(gray):
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
            corners, measured_px = refined
            stretch = pose.undistortion_jacobian(d.corners_px, K, cal.dist, cal.fisheye)
            mp = pose.solve(corners, self.sizes[d.marker_id], K, self._sigma_px(d.family), stretch, measured_px)
            if mp is None:
                self.counters["pnp_failed"] += 1
                self.report.dropped[d.marker_id] = "no pose"
                continue
            singles[d.marker_id] = _Single(mp, corners, stretch, measured_px)
        self.report.found.sort()
        out = []
        groups: dict[str, list[int]] = {}
        for mid in sorted(singles):
            groups.setdefault(self.entity_of[mid], []).append(mid)
        for entity, ids in groups.items():
            if self.joint and len(ids) > 1:
                md, used = self._robust_joint(entity, ids, singles, capture_time_us)
                if md is not None:
                    out.append(md)
                    self.report.reported += used
                    continue
                if used is None:  # the squares contradict each other: none of them is trusted in this image
                    continue
            for mid in ids:
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

    def _offset_m(self, m: int, others: list[int], singles: dict[int, _Single]) -> float:
        """How far marker ``m``'s own square is from where the joint pose of ``others`` puts it (m)."""
        sol = self._joint_solution(others, singles)
        if sol is None:
            return math.nan
        T_cam_entity = RigidTransform.from_components(sol[1], Rotation.from_rotvec(sol[0]))
        predicted = (T_cam_entity * self.marker_pose[m]).translation
        return float(np.linalg.norm(singles[m].pose.p_m - predicted))

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
    decimate = float(min(max(math.floor(_side(c) / (1.5 * SMALL_SIDE_PX)), 1), MAX_REGION_DECIMATE))
    return np.concatenate([lo - grow, hi + grow, [decimate]])


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
            if r[0] <= m[2] and r[2] >= m[0] and r[1] <= m[3] and r[3] >= m[1]:
                m[:] = [min(m[0], r[0]), min(m[1], r[1]), max(m[2], r[2]), max(m[3], r[3]), min(m[4], r[4])]
                break
        else:
            merged.append(r)
    return [(int(a), int(b), int(c), int(d), float(e)) for a, b, c, d, e in merged]
