"""Frame in, MarkerData out: find the configured markers, undistort their corners, solve their poses.

Speed beyond the library: markers are searched at ``decimate`` 2 (four times fewer pixels), and the
regions where markers were last seen, or are small, are searched again at full resolution, so the
detector keeps the recall of decimate 1 at close to the cost of decimate 2.
"""

from __future__ import annotations

import math
from collections import Counter
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

MAX_AMBIGUITY = 1.0
JOINT_MISFIT = 3.0  # a joint fit this many times worse than its worst single square is not used
"""Detections whose IPPE ratio (chosen over other solution's reprojection error) exceeds this are
dropped (counted ``ambiguous_dropped``). Above ``AMBIGUITY_THRESHOLD`` (0.5) the two planar solutions
fit almost equally well and the chosen one may be the mirror image (a "flip", tens of degrees off):
such detections are kept with both solutions (counted ``ambiguous``) for the listener to resolve with
the current estimates (:mod:`atlas_onboard.core.ambiguity`). 1.0 keeps them all."""
SCAN_EVERY = 4  # frames between whole-image searches (between them, only tracked regions)
SMALL_SIDE_PX = 40.0  # markers smaller than this are re-searched at full resolution
ROI_MARGIN = 0.6  # a region is the marker's box grown by this fraction of its size on each side


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
        self.finder = MarkerFinder(wanted, self.decimate)
        self._last: list[NDArray[np.float64]] = []  # boxes (x0, y0, x1, y1) of the previous frame's markers
        # Whole-image searches every SCAN_EVERY frames, in a phase of their own for each sensor: the
        # cameras of one node do not all search at once (their frames come at the same instants).
        self._frame = self.sensor.id % SCAN_EVERY

    def find(self, gray: NDArray[np.uint8]) -> list[Detection]:
        """Markers in the frame, tracked from the previous one.

        Every frame, the regions around the markers of the previous frame are searched at full
        resolution (as precise as decimate 1, on a fraction of the pixels). Every ``SCAN_EVERY``
        frames the whole image is searched at ``decimate`` and one tile of a 2x2 grid (in turn) at
        full resolution, so that new and small markers are found too; when nothing is tracked, the
        whole image is searched at full resolution.
        """
        if not self.track or self.decimate <= 1.0:
            return self.finder.find(gray, 1.0)
        h, w = gray.shape[:2]
        found: dict[int, Detection] = {}
        if not self._last:  # nothing tracked (start, or everything lost): one full-resolution search
            found = {d.marker_id: d for d in self.finder.find(gray, 1.0)}
            self._frame += 1
            self._last = [_box(d.corners_px) for d in found.values()]
            self.counters["full_searches"] += 1
            return list(found.values())
        self._roi_search(gray, self._last, found)
        if self._frame % SCAN_EVERY == 0 or not found:
            small = []
            for d in self.finder.find(gray, self.decimate):
                if d.marker_id not in found:
                    found[d.marker_id] = d
                    if _side(d.corners_px) < SMALL_SIDE_PX:
                        small.append(_box(d.corners_px))
            self._roi_search(gray, small, found)
            tile = (self._frame // SCAN_EVERY) % 4
            tx, ty = tile % 2, tile // 2
            mx, my = w // 8, h // 8  # tiles overlap so that no marker is cut on every tile
            box = np.array([tx * w // 2 - mx, ty * h // 2 - my, (tx + 1) * w // 2 + mx, (ty + 1) * h // 2 + my], float)
            self._roi_search(gray, [box], found, only_new=True)
            self.counters["scans"] += 1
        self._frame += 1
        self._last = [_box(d.corners_px) for d in found.values()]
        return list(found.values())

    def _roi_search(
        self,
        gray: NDArray[np.uint8],
        boxes: list[NDArray[np.float64]],
        found: dict[int, Detection],
        only_new: bool = False,
    ) -> None:
        h, w = gray.shape[:2]
        for x0, y0, x1, y1 in _merge(boxes, w, h):
            for d in self.finder.find(np.ascontiguousarray(gray[y0:y1, x0:x1]), 1.0):
                if only_new and d.marker_id in found:
                    continue
                c = d.corners_px + np.array([x0, y0], dtype=float)
                found[d.marker_id] = Detection(d.marker_id, d.family, c, d.decision_margin)
                self.counters["roi_finds"] += 1

    def detect(self, gray: NDArray[np.uint8], capture_time_us: int) -> list[MarkerData]:
        """MarkerData of the configured markers in ``gray``.

        With ``joint`` (the default), the markers of one entity seen together are solved as one
        rigid pattern (every corner at once, far better conditioned than any single square) and
        reported as one observation of the first of them; a lone marker is solved on its own.
        """
        h, w = gray.shape[:2]
        self.calibration.check_size(w, h, f"sensor {self.sensor.name}")
        K = self.calibration.K
        singles: dict[int, tuple[pose.MarkerPose, NDArray[np.float64]]] = {}
        for d in self.find(gray):
            corners = pose.undistort(d.corners_px, K, self.calibration.dist, self.calibration.fisheye)
            mp = pose.solve(corners, self.sizes[d.marker_id], K, self._sigma_px(d.family))
            if mp is None:
                self.counters["pnp_failed"] += 1
                continue
            singles[d.marker_id] = (mp, corners)
        out = []
        groups: dict[str, list[int]] = {}
        for mid in sorted(singles):
            groups.setdefault(self.entity_of[mid], []).append(mid)
        for ids in groups.values():
            if self.joint and len(ids) > 1:
                md, misfit = self._joint(ids, singles, capture_time_us)
                if md is not None:
                    out.append(md)
                    continue
                if misfit:  # the squares contradict each other: none of them is trusted in this image
                    continue
            for mid in ids:
                mp = singles[mid][0]
                ambiguous = mp.ambiguity > AMBIGUITY_THRESHOLD
                if mp.ambiguity > self.max_ambiguity or (ambiguous and mp.p_alt_m is None):
                    # Too poor a fit, or nothing downstream could resolve it: drop it here.
                    self.counters["ambiguous_dropped"] += 1
                    continue
                self.counters["ambiguous"] += ambiguous
                alt = (mp.p_alt_m, mp.q_alt_xyzw) if mp.p_alt_m is not None and mp.q_alt_xyzw is not None else None
                out.append(self._markerdata(mid, mp.p_m, mp.q_xyzw, mp.sigma_m, mp.reprojection_error_px, mp.ambiguity,
                                            capture_time_us, alt, mp.covariance))  # fmt: skip
        self.counters["detections"] += len(out)
        return out

    def _sigma_px(self, family_name: str) -> float:
        return pose.SIGMA_PX_APRILTAG if family(family_name).is_apriltag else pose.SIGMA_PX_ARUCO

    def _joint(self, ids: list[int], singles: dict, capture_time_us: int) -> tuple[MarkerData | None, bool]:
        """The entity's observation from all its squares at once; (None, False) when the solve
        failed (the squares are then reported one by one), (None, True) when they do not fit together."""
        anchor = ids[0]
        T_entity_anchor = self.marker_pose[anchor]
        obj = np.vstack([self.marker_pose[m].apply(pose.object_corners(self.sizes[m])) for m in ids])
        img = np.vstack([singles[m][1] for m in ids])
        # Start from the least ambiguous single solution, moved to the entity frame.
        best = min(ids, key=lambda m: singles[m][0].ambiguity if np.isfinite(singles[m][0].ambiguity) else 1.0)
        mp = singles[best][0]
        T_cam_entity = (
            RigidTransform.from_components(mp.p_m, Rotation.from_quat(mp.q_xyzw)) * self.marker_pose[best].inv()
        )
        guess = (T_cam_entity.rotation.as_rotvec(), T_cam_entity.translation)
        fam = self.world.markers[anchor].family
        sol = pose.solve_joint(obj, img, self.calibration.K, self._sigma_px(fam), guess)
        if sol is None:
            self.counters["joint_failed"] += 1
            return None, False
        rvec, tvec, err, sigma = sol
        # Markers that do not fit together as the world file places them (a misplaced marker, a bad
        # corner, motion blur that moves each square differently) give a joint fit far worse than
        # each square's own: the joint pose is then wrong in a way no sigma describes (a few degrees
        # of tilt on paper-test1), and a single square alone may be the flipped one. Nothing of the
        # entity is reported from this image (counted).
        worst_single = max(singles[m][0].reprojection_error_px for m in ids)
        if err > JOINT_MISFIT * max(worst_single, self._sigma_px(fam)):
            self.counters["joint_misfit"] += 1
            return None, True
        T = RigidTransform.from_components(tvec, Rotation.from_rotvec(rvec)) * T_entity_anchor
        # The covariance of the anchor's pose: the same corners, in the anchor's frame.
        obj_anchor = T_entity_anchor.inv().apply(obj)
        sigma_px = pose.corner_noise_px(self._sigma_px(fam), float(np.median([_side(singles[m][1]) for m in ids])))
        cov = pose.pose_covariance(T.rotation.as_matrix(), T.translation, obj_anchor, self.calibration.K, sigma_px, err)
        self.counters["joint"] += 1
        md = self._markerdata(anchor, T.translation, T.rotation.as_quat(), sigma, err, 0.0, capture_time_us, None, cov)
        return md, False

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


def _side(c: NDArray[np.float64]) -> float:
    return float(np.mean(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)))


def _box(c: NDArray[np.float64]) -> NDArray[np.float64]:
    lo, hi = c.min(axis=0), c.max(axis=0)
    grow = (hi - lo) * ROI_MARGIN + 8
    return np.concatenate([lo - grow, hi + grow])


def _merge(boxes: list[NDArray[np.float64]], w: int, h: int) -> list[tuple[int, int, int, int]]:
    """Clip boxes to the image and merge overlapping ones (so no marker is cut in two)."""
    rects = [[max(int(b[0]), 0), max(int(b[1]), 0), min(int(b[2]) + 1, w), min(int(b[3]) + 1, h)] for b in boxes]
    rects = [r for r in rects if r[2] - r[0] >= 16 and r[3] - r[1] >= 16]
    merged: list[list[int]] = []
    for r in sorted(rects):
        for m in merged:
            if r[0] <= m[2] and r[2] >= m[0] and r[1] <= m[3] and r[3] >= m[1]:
                m[:] = [min(m[0], r[0]), min(m[1], r[1]), max(m[2], r[2]), max(m[3], r[3])]
                break
        else:
            merged.append(r)
    return [(a, b, c, d) for a, b, c, d in merged]
