"""Frame in, MarkerData out: find the configured markers, undistort their corners, solve their poses.

Speed beyond the library: on a textured floor the library spends most of its time on the texture. Each
frame searches the regions where the markers of the previous frame are predicted to be (at a decimation
that keeps each marker wide enough), then the regions of strong black-white contrast elsewhere at full
resolution (cells whose darkest pixel is a small share of their brightest, as black ink beside white
paper is in any light; texture searched in vain is left alone for a few frames unless its contrast rises,
tags that are not ours for longer, followed with the camera's turn), within a budget of pixels; for markers
of weak contrast, a whole-image search at decimate 3 and one tile of a full-resolution grid, every (other)
frame while hunting and now and then while tracking: the recall of decimate 1 at a fraction of its cost.

Trust: a marker whose corners touch the image border (or the border of the region it was found in) is
dropped (counted by reason), since its edges cannot be fitted; the corners of the others are refitted
in undistorted pixels (:func:`refine.refine_corners_undistorted`), which also measures their noise.
Markers of one entity that do not fit together are found by leaving each out in turn: the rest give the
entity's pose, and the one that disagrees is counted, logged and announced (:meth:`Detector.take_status`).
Every pair seen together and every marker seen a frame after another (the camera cannot jump) is
evidence in a consistency graph over the markers (:mod:`atlas_onboard.core.consistency`): a
marker that disagrees with markers that agree among themselves is suspect, never used alone nor in a
joint solve, while the other member of a pair that disagrees is used. A moved or suspect world marker
whose place has been measured (:mod:`atlas_onboard.core.places`: where trusted markers' images put it, with its
covariance) is used alone at that place, the place's covariance carried into its pose. The world check
(:class:`atlas_onboard.detector.worldcheck.WorldCheck`) owns that state, its logs and STATUSTEXT.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, SensorConfig, WorldConfig
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.consistency import PairVerdict
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.refine.sampling import PerMarkerSchedule
from atlas_onboard.core.shutter import BodyRate, BodyVelocity
from atlas_onboard.core.worldcheck import MovedMarker
from atlas_onboard.detector import pose
from atlas_onboard.detector.backends import Detection, MarkerFinder
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.joint import JointSolve
from atlas_onboard.detector.marker_poses import solve_markers
from atlas_onboard.detector.motion import CameraMotionModel, SeenSquare
from atlas_onboard.detector.records import FrameReport, SingleSolve, marker_data
from atlas_onboard.detector.refine import refine_markers_undistorted
from atlas_onboard.detector.search import (
    MAX_REGION_DECIMATE,
    TILES,
    RegionSearch,
    at_border,
    box,
)
from atlas_onboard.detector.tracks import NO_TRACKS, SharedTracks
from atlas_onboard.detector.worldcheck import WorldCheck

MAX_AMBIGUITY = 1.0
"""Detections whose IPPE ratio (chosen over other solution's reprojection error) exceeds this are dropped
(counted ``ambiguous_dropped``). Above ``AMBIGUITY_THRESHOLD`` (0.5) the two planar solutions fit almost
equally well and the chosen one may be the mirror image (a "flip", tens of degrees off): such detections
are kept with both solutions (counted ``ambiguous``) for the listener to resolve (core/ambiguity.py)."""
SCAN_EVERY = 4  # frames between whole-image searches while tracking
CANDIDATE_AREA = 0.06  # the most of the image searched each frame at full resolution around strong contrast


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
    # Live map refinement's per-marker images (when due, an entity's 3+ markers each reported alone).
    per_marker: PerMarkerSchedule | None = None
    counters: Counter[str] = field(default_factory=Counter)

    def __post_init__(self) -> None:
        others = [m for m in self.world.markers.values() if m.entity != self.sensor.entity]
        self.sizes = {m.id: m.size_m for m in others}
        self.entity_of = {m.id: m.entity for m in others}
        self.marker_pose = {m.id: m.T_entity_marker for m in others}
        wanted = {m.id: m.family for m in self.world.markers.values() if m.entity != self.sensor.entity}
        self.finder = MarkerFinder(wanted, self.decimate, extra=(MAX_REGION_DECIMATE,) if self.track else ())
        self.tracks = NO_TRACKS  # the markers of the last frame searched, to predict them in the next
        self.shared: SharedTracks | None = None  # the camera's board, when its frames are dealt to workers
        # Whole-image searches and tiles in a phase of their own for each sensor: the cameras of one
        # node do not all search at once (their frames come at the same instants).
        self._frame = self.sensor.id % SCAN_EVERY
        self.search = RegionSearch(self.calibration, self.finder, self.counters, self.sensor.id % (TILES[0] * TILES[1]))
        self.report = FrameReport()
        # The joint solve of an entity's markers seen together, and the sensor's MarkerData records.
        self.joint_solve = JointSolve(
            self.sensor, self.world, self.calibration, self.marker_pose, self.sizes, self.counters
        )
        # The live world-file check: moved and suspect markers, measured places, what is said.
        world_markers = {m: T for m, T in self.marker_pose.items() if self.entity_of[m] == WORLD}
        self.world_check = WorldCheck(self.sensor, self.marker_pose, world_markers, self.counters, self.joint_solve)
        self.motion_model: CameraMotionModel | None = None  # made at the first frame (its height)

    @property
    def tracking(self) -> bool:
        """Whether markers of the previous frame are tracked (False: the next frame is a hunt)."""
        return bool(self.tracks.corners)

    def find(
        self,
        gray: NDArray[np.uint8],
        R_prev_now: Rotation | None = None,
        capture_time_us: int | None = None,
        attitude: Rotation | None = None,
    ) -> list[Detection]:
        """Markers in the frame, tracked from the previous one.

        ``R_prev_now``: the camera's rotation since the previous frame (maps directions in the camera
        frame now into the camera frame then, OpenCV axes), e.g. from the autopilot's attitude; given,
        the previous markers are predicted where that rotation moves them, plus the part of their last
        image motion that the previous turn did not explain (the drone's travel), instead of by their
        last image motion alone (a fast turn moves a marker far more than its past motion says).

        Every frame: the regions where the markers of the previous frame are predicted to be (moved on
        by their last motion in the image) are searched at a decimation that keeps each marker at least
        ``TRACKED_SIDE_PX`` wide (the library fits the edges at full resolution whatever the decimation);
        then the regions of strong black-white contrast outside the markers found
        (:func:`contrast_regions`: black ink on white paper, and the library spends most of its time on
        the texture elsewhere), at most ``CANDIDATE_AREA`` of the image's
        pixels (divided by each region's decimation squared). For markers of weak contrast: the whole
        image at ``MAX_REGION_DECIMATE`` (large markers), every frame while hunting and every
        ``SCAN_EVERY`` frames while tracking, and the next tile of a ``TILES`` grid at full resolution
        (small ones), every other frame while hunting and every ``SCAN_EVERY`` frames while tracking.
        Without ``track`` (or with ``decimate`` 1), the whole image at full resolution.

        ``capture_time_us``: the motion is scaled to the time since the previous frame searched;
        ``attitude``: the camera's orientation at the capture (R_level_camera), the turn since a frame
        of known orientation when ``R_prev_now`` is not given (a worker's, :mod:`.tracks`).
        """
        if not self.track or self.decimate <= 1.0:
            return self.finder.find(gray, 1.0)
        h, w = gray.shape[:2]
        found: dict[int, Detection] = {}
        base = self.tracks  # a newer frame searched by another worker of the camera, if any
        newer = None if self.shared is None or capture_time_us is None else self.shared.newer(base, capture_time_us)
        if R_prev_now is None:
            R_prev_now = base.turn_to(attitude)
        if newer is not None:
            self.counters["tracks_shared"] += 1
            base, R_base_now = newer, newer.turn_to(attitude)
        else:
            R_base_now = R_prev_now
        # The turn from the attitude, plus the motion (the drone's travel) that the last turn left over.
        self.search.predicted, turned = base.predicted(capture_time_us, R_base_now, self.search.rotated)
        hunting = not self.search.predicted
        k = self._frame
        if not hunting:
            self.search.track(gray, found)
        if hunting or k % SCAN_EVERY == 0:
            new = []
            for d in self.search.scan(gray, MAX_REGION_DECIMATE):
                if d.marker_id not in found:
                    found[d.marker_id] = d
                    new.append(box(d.corners_px))  # found again at the region's own decimation
            self.search.find_in(gray, new, found)
            self.counters["scans"] += 1
        self.search.candidates(gray, k, R_prev_now, found, CANDIDATE_AREA * w * h)
        if k % SCAN_EVERY == SCAN_EVERY // 2 or (hunting and k % 2 == 1):
            self.search.find_in(gray, [self.search.next_tile(w, h)], found, only_new=True)
        self.search.remember_foreign(k)
        self.counters["hunts" if hunting else "tracked_frames"] += 1
        self._frame += 1
        self.tracks = base.then(capture_time_us, {i: d.corners_px for i, d in found.items()}, turned, attitude)
        if self.shared is not None:  # before this frame's other work: the camera's next frame predicts from it
            self.shared.post(self.tracks)
        return list(found.values())

    def detect(
        self,
        gray: NDArray[np.uint8],
        capture_time_us: int,
        R_prev_now: Rotation | None = None,
        body_rate: BodyRate | None = None,
        body_velocity: BodyVelocity | None = None,
        attitude: Rotation | None = None,
    ) -> list[MarkerData]:
        """MarkerData of the configured markers in ``gray`` (``R_prev_now``, ``attitude``: see :meth:`find`;
        ``body_rate``, ``body_velocity``: the autopilot's at the capture, for a rolling shutter's shear,
        see :mod:`.motion`).

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
        singles: dict[int, SingleSolve] = {}
        # Camera motion: the frame's motion (rolling shutter, exposure; detector.motion)
        if self.motion_model is None:
            self.motion_model = CameraMotionModel.of(self.sensor, h)
        motion = self.motion_model.at(capture_time_us, body_rate, body_velocity)
        per_marker = self.per_marker is not None and self.per_marker.due(capture_time_us)
        candidates = []
        for d in self.find(gray, R_prev_now, capture_time_us, attitude):
            self.report.found.append(d.marker_id)
            if at_border(d.corners_px, w, h):
                # A marker cut by the border, or one whose corner is extrapolated or nearly outside: its
                # edges cannot be fitted, and such poses were off by many of their sigmas.
                self.counters["dropped_image_border"] += 1
                self.report.dropped[d.marker_id] = "at the image border"
                continue
            candidates.append(d)
        # Every marker's corners undistorted, refitted on its edges, and their undistortion's Jacobian, at once.
        found_px = np.array([d.corners_px for d in candidates]).reshape(-1, 2)
        undistorted = pose.undistort(found_px, K, cal.dist, cal.fisheye).reshape(-1, 4, 2) if candidates else []
        refits = refine_markers_undistorted(gray, list(undistorted), K, cal.dist, cal.fisheye, cal.lens_residual_px)
        stretches = pose.undistortion_jacobian(found_px, K, cal.dist, cal.fisheye) if candidates else None
        refined_ok = []
        raw: dict[int, SeenSquare] = {}
        for k, (d, refined) in enumerate(zip(candidates, refits, strict=True)):
            if refined is None:
                # The library's corners are straight-line fits in the distorted image: where the edge fit fails
                # (image edge, strong distortion, blur) they are off by many times the corner noise. Not used.
                self.counters["refine_failed"] += 1
                self.report.dropped[d.marker_id] = "corner refinement failed"
                continue
            stretch = None if stretches is None else stretches[4 * k : 4 * k + 4]
            if self.entity_of[d.marker_id] == WORLD:  # as found, for the camera's own motion history
                raw[d.marker_id] = SeenSquare(self.marker_pose[d.marker_id], d.corners_px, refined.corners,
                                              refined.sigma_px, refined.covariance, stretch, self.sizes[d.marker_id],
                                              pose.model_sigma_px(d.family), K)  # fmt: skip
            refined_ok.append((d, refined, stretch, 0.0))
        ds, rs = [t[0] for t in refined_ok], [t[1] for t in refined_ok]  # camera motion: corners to the stamp
        moves = self.motion_model.correct_all(motion, [d.corners_px for d in ds], [r.corners for r in rs],
            [r.covariance for r in rs], K, [self.sizes[d.marker_id] for d in ds])  # fmt: skip
        # A moving rolling shutter's corners as seen, at their rows' instants: the joint solve fits the motion too.
        timed = self.motion_model.timed(motion, [d.corners_px for d in ds], [(r.corners, r.covariance) for r in rs])
        self.joint_solve.motion = motion
        for k, ((d, refined, stretch, _), moved) in enumerate(zip(refined_ok, moves, strict=True)):
            grown = max(float(np.trace(moved.covariance)) - float(np.trace(refined.covariance)), 0.0) / 8.0
            refined_ok[k] = (d, replace(refined, corners=moved.corners, sigma_px=math.sqrt(refined.sigma_px**2 + grown),
                                        covariance=moved.covariance), stretch, moved.shear_px)  # fmt: skip
        # Every marker's pose at once (pose.solve's, one by one).
        poses = solve_markers(
            [r.corners for _, r, _, _ in refined_ok],
            [self.sizes[d.marker_id] for d, _, _, _ in refined_ok],
            K,
            [pose.model_sigma_px(d.family) for d, _, _, _ in refined_ok],
            [s for _, _, s, _ in refined_ok],
            [r.sigma_px for _, r, _, _ in refined_ok],
            [r.covariance for _, r, _, _ in refined_ok],
        )
        for (d, refined, stretch, motion_px), mp, seen in zip(refined_ok, poses, timed, strict=True):
            if mp is None:
                self.counters["pnp_failed"] += 1
                self.report.dropped[d.marker_id] = "no pose"
                continue
            singles[d.marker_id] = SingleSolve(
                mp, refined.corners, stretch, refined.sigma_px, refined.covariance, motion_px, seen
            )
        self.report.found.sort()
        # Camera motion: the best world marker (its own square as found) for the next frames' velocity
        best = sorted((singles[m].pose.sigma_m, m) for m in raw if m in singles)[:1]
        self.motion_model.observe(capture_time_us, [replace(raw[m], solved=singles[m].pose) for _, m in best], motion)
        out = []
        groups: dict[str, list[int]] = {}
        for mid in sorted(singles):
            groups.setdefault(self.entity_of[mid], []).append(mid)
        for entity, ids in groups.items():
            if entity == WORLD and len(ids) > 1:  # evidence of where each world marker is, placed by the others
                self.world_check.gather_places(ids, singles, capture_time_us)
            # Evidence for the consistency of the markers over time (the camera cannot jump) and in pairs.
            verdicts = self.world_check.consistency_evidence(entity, ids, singles, capture_time_us)
            fed = False
            each = per_marker and len(ids) >= 3
            if self.joint and len(ids) > 1 and not each:
                self.world_check.offsets = {}
                doubtful = self.world_check.doubtful(entity, ids, capture_time_us)
                joint = self.joint_solve.robust(ids, singles, capture_time_us)
                self.world_check.take_joint(entity, ids, joint, singles, capture_time_us, self.report)
                md, used = joint.md, joint.used
                if len(ids) >= 3 and used is not None:  # one that does not fit can be singled out
                    self.world_check.check(entity, ids, capture_time_us)
                    fed = True
                elif len(ids) == 2 and (md is not None or used is None):
                    a, b = ids
                    verdicts += self.world_check.pair_verdicts(entity, a, b, md is not None, singles, capture_time_us)
                if not fed:
                    self.world_check.feed(entity, verdicts, capture_time_us)
                if md is not None and used is not None and doubtful & set(used):
                    # A moved or suspect marker that fitted is still left out: the rest give the pose.
                    for m in doubtful & set(used):
                        self.counters["dropped_suspect"] += 1
                        self.report.dropped[m] = "moved or suspect: left out of the joint solve"
                    used = [m for m in used if m not in doubtful]
                    md = None
                    if len(used) > 1:
                        md = self.joint_solve.solve(used, singles, capture_time_us, count=False)[0]
                    if md is None:
                        ids = used
                if md is not None:
                    out.append(md)
                    self.report.reported += used
                    continue
                if used is None:
                    # The squares contradict each other: a pair's member that others trust is used alone,
                    # when the other is suspect; otherwise none of them is trusted in this image. The suspect
                    # one is used too where its place has already been measured (the pair judged the file's).
                    pair = joint.misfit_pair
                    suspects = self.world_check.doubtful(entity, pair, capture_time_us)
                    rest = [m for m in pair if m not in suspects]
                    if len(rest) != 1 or len(pair) != 2:
                        continue
                    ids = sorted(rest + [m for m in suspects if self.world_check.places.place(m) is not None])
            else:
                self.world_check.feed(entity, verdicts, capture_time_us)
            for mid in ids:
                mp = singles[mid].pose
                # A moved or suspect marker whose place has been measured is used there, with the place's covariance.
                place = (
                    None if each or mp.covariance is None else self.world_check.place_of(entity, mid, capture_time_us)
                )
                if place is None and not each and self._doubtful_alone(entity, mid, verdicts, capture_time_us):
                    continue
                if place is not None and self.world_check.jumped(entity, mid, verdicts, capture_time_us, place):
                    self.counters["dropped_jump"] += 1  # moved again since? the trusted markers' images will say
                    self.report.dropped[mid] = "off its measured place by more than the camera can have moved"
                    continue
                ambiguous = mp.ambiguity > AMBIGUITY_THRESHOLD
                if mp.ambiguity > self.max_ambiguity or (ambiguous and mp.p_alt_m is None):
                    # Too poor a fit, or nothing downstream could resolve it: drop it here.
                    self.counters["ambiguous_dropped"] += 1
                    self.report.dropped[mid] = "ambiguous"
                    continue
                self.counters["ambiguous"] += ambiguous
                if place is not None:
                    out.append(self.world_check.at_place(mid, mp, place, capture_time_us))
                    self.report.reported.append(mid)
                    continue
                alt = (mp.p_alt_m, mp.q_alt_xyzw) if mp.p_alt_m is not None and mp.q_alt_xyzw is not None else None
                out.append(marker_data(self.sensor.id, mid, mp.p_m, mp.q_xyzw, mp.sigma_m, mp.reprojection_error_px,
                                       mp.ambiguity, capture_time_us, alt, mp.covariance))  # fmt: skip
                self.report.reported.append(mid)
        # Camera motion: the frame's timing uncertainty moves every pose alike (detector.motion)
        out = [self.motion_model.with_timing(md, motion) for md in out]
        self.counters["detections"] += len(out)
        if self.per_marker is not None:
            self.per_marker.saw(capture_time_us, per_marker, self.report.found)
        return out

    def _doubtful_alone(self, entity: str, mid: int, verdicts: list[PairVerdict], capture_time_us: int) -> bool:
        """Whether a marker seen alone must not give the pose (counted and explained in the report)."""
        if (entity, mid) in self.world_check.moved:  # alone it would move the pose by its offset
            self.counters["dropped_moved"] += 1
            self.report.dropped[mid] = "reported moved (the world file disagrees with what is seen)"
        elif self.world_check.consistency.is_suspect(entity, mid, capture_time_us):
            # It disagrees with markers that agree among themselves: alone it would move the pose.
            self.counters["dropped_suspect"] += 1
            self.report.dropped[mid] = "suspect: disagrees with markers that agree with each other"
        elif self.world_check.jumped(entity, mid, verdicts, capture_time_us):
            # It puts the camera where it cannot have gone since a better supported marker saw it.
            self.counters["dropped_jump"] += 1
            self.report.dropped[mid] = "puts the camera where it cannot have moved since the last frame"
        else:
            return False
        return True

    @property
    def moved(self) -> dict[tuple[str, int], MovedMarker]:
        """The markers reported moved so far, (entity, id) -> the latest verdict (the world check's)."""
        return self.world_check.moved

    @property
    def disagreements(self) -> Counter[int]:
        """Marker id -> images in which it disagreed with the other markers (the world check's)."""
        return self.world_check.disagreements

    def map_pose_changed(self, marker_id: int) -> None:
        """The node's map now holds another pose of the marker than the world file's (live refinement)."""
        self.world_check.map_pose_changed(marker_id)

    def take_status(self) -> list[str]:
        """STATUSTEXT lines to send (at most one a minute), emptied by the call."""
        out = []
        while self.world_check.status:  # a deque: the camera thread appends while the node's thread takes
            out.append(self.world_check.status.popleft())
        return out
