"""The live check of the world file in one sensor's detector: which markers are moved or suspect, where a
moved world marker really is, and what is said about it (logs, STATUSTEXT, counters).

It owns the moved-marker verdicts (:class:`~atlas_onboard.core.worldcheck.MovedMarkerCheck`), the
consistency graph and the motion check (:mod:`atlas_onboard.core.consistency`) and the measured places
(:mod:`atlas_onboard.core.places`); it takes the joint solve's results
(:class:`~atlas_onboard.detector.records.JointResult`) and asks that solve (:mod:`atlas_onboard.detector.joint`)
where a marker's square lies from the others.
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque
from collections.abc import Callable, Mapping

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import WORLD, SensorConfig
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.consistency import MOTION_MAX_ALLOWANCE_M, MarkerConsistency, MotionCheck, PairVerdict, Sighting
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.places import MeasuredPlace, MeasuredPlaces
from atlas_onboard.core.refine import Sighting as PlacedSighting
from atlas_onboard.core.worldcheck import MovedMarker, MovedMarkerCheck
from atlas_onboard.detector import pose
from atlas_onboard.detector.joint import JointSolve
from atlas_onboard.detector.records import FrameReport, JointResult, SingleSolve, marker_data
from atlas_onboard.detector.rotations import matrices_from_quats, matrix_from_quat

_logger = logging.getLogger(__name__)

CLEAR_OFFSET_M = 0.03  # a moved or suspect marker fits again when its square is this close to where others put it
STATUS_INTERVAL_US = 60_000_000  # at most one STATUSTEXT a minute about disagreeing markers
LOG_INTERVAL_US = 5_000_000
PLACE_RETRY_US = 250_000  # a moved marker's measured place is sought again at most this often


class WorldCheck:
    """The world check of one sensor's detector (see the module).

    ``sensor``: the detector's camera; ``marker_pose``: every marker's pose in its entity
    (``T_entity_marker``); ``world_markers``: the world's markers among them, whose measured places are
    sought; ``counters``: the detector's (shared); ``joint``: the detector's joint solve, asked where a
    marker's square is minus where the joint pose of others puts it (:meth:`JointSolve.offset`).
    """

    def __init__(
        self,
        sensor: SensorConfig,
        marker_pose: Mapping[int, RigidTransform],
        world_markers: Mapping[int, RigidTransform],
        counters: Counter[str],
        joint: JointSolve,
    ) -> None:
        # Where moved world markers really are, to use them there (evidence from every image of two or more).
        self.places = MeasuredPlaces({m: (T.translation, T.rotation.as_matrix()) for m, T in world_markers.items()})
        self.sensor = sensor
        self.marker_pose = marker_pose
        self.counters = counters
        self.joint = joint
        self._rt: dict[int, tuple[NDArray[np.float64], NDArray[np.float64]]] = {}  # see _marker_rt
        self.disagreements: Counter[int] = Counter()  # marker id -> images in which it disagreed
        self.status: deque[str] = deque()  # STATUSTEXT lines to send (the detector's take_status empties it)
        self._last_status_us: int | None = None
        self._last_log_us: int | None = None
        # The joint solves' verdicts over many images.
        self.moved_check = MovedMarkerCheck()
        self.offsets: dict[int, NDArray[np.float64]] = {}  # this image's disagreeing markers (entity frame)
        self._moved_log_us: dict[tuple[str, int], int] = {}
        self._moved_status_us: int | None = None
        self.moved: dict[tuple[str, int], MovedMarker] = {}  # reported so far, the latest verdict of each
        # Faster evidence: pairs and frame-to-frame motion, in a consistency graph over the markers.
        self.consistency = MarkerConsistency()
        self.motion = MotionCheck()
        self._place_tried_us: dict[int, int] = {}
        self._map_changed: set[int] = set()  # markers whose pose the node's map no longer takes from the file

    def check(self, entity: str, ids: list[int], capture_time_us: int) -> None:
        """Feed the image's verdict to the live check; say a marker that has moved (log at most once a
        minute per marker, a STATUSTEXT at most once a minute, ``markers_moved`` counts distinct markers)."""
        verdicts = self.moved_check.add(capture_time_us, entity, ids, self.offsets)
        still = {m.marker_id for m in verdicts}
        for mid in ids:  # a marker put back (it fits again in most images) is used again
            if (entity, mid) in self.moved and mid not in still and mid not in self.offsets:
                if not self.moved_check.disagrees(entity, mid):
                    del self.moved[(entity, mid)]
                    self.places.drop(mid)
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
                    " (%+.3f %+.3f %+.3f m) in %d of %d images; it is not used where the world file has it",
                    self.sensor.name, entity, moved.marker_id, moved.distance_m * 100, dx, dy, dz,
                    moved.disagreeing, moved.views,
                )  # fmt: skip
            if self._moved_status_us is None or capture_time_us - self._moved_status_us >= STATUS_INTERVAL_US:
                self._moved_status_us = capture_time_us
                self.status.append(
                    f"atlas: marker {moved.marker_id} moved {round(dx * 100):+d} {round(dy * 100):+d}"
                    f" {round(dz * 100):+d} cm"[:50]
                )

    # --- a moved world marker used at its measured place ------------------------------------------------

    def _trusted(self, now_us: int) -> Callable[[frozenset[int]], bool]:
        """Whether markers that placed the camera in an image are trusted now: none moved or suspect, and
        two or more (checked against each other), or one that agrees with another marker."""
        suspects = self.consistency.suspects(WORLD, now_us)

        def trusted(others: frozenset[int]) -> bool:
            if not others or any(m in suspects or (WORLD, m) in self.moved for m in others):
                return False
            return len(others) >= 2 or self.consistency.support(WORLD, next(iter(others)), now_us) >= 2

        return trusted

    def gather_places(self, ids: list[int], singles: dict[int, SingleSolve], capture_time_us: int) -> None:
        """This image's world markers as evidence of where each is (:class:`MeasuredPlaces`); a place that
        new evidence no longer fits is withdrawn, said and counted."""
        seen = []
        for m in ids:
            mp = singles[m].pose
            if mp.covariance is not None and mp.ambiguity <= AMBIGUITY_THRESHOLD:  # not maybe the mirrored one
                seen.append(PlacedSighting(m, mp.p_m, matrix_from_quat(mp.q_xyzw), mp.covariance))
        for place in self.places.add_image(self.sensor.id, capture_time_us, seen, self._trusted(capture_time_us)):
            self.counters["places_withdrawn"] += 1
            _logger.warning(
                "sensor %s: world marker %d has left its measured place (%+.3f %+.3f %+.3f m from the"
                " world file): it keeps moving; it is not used until it stays in one place",
                self.sensor.name, place.marker_id, *place.offset_m,
            )  # fmt: skip
            self._say_status(f"atlas: marker {place.marker_id} keeps moving, unused", capture_time_us)

    def place_of(self, entity: str, mid: int, capture_time_us: int) -> MeasuredPlace | None:
        """The measured place of a world marker reported moved or suspect, sought when there is none yet (at
        most every ``PLACE_RETRY_US``); said once when found (log and STATUSTEXT at most once a minute),
        counted. A marker no longer doubted is used where the world file has it: its place is forgotten."""
        if entity != WORLD or mid in self._map_changed:
            return None
        if (entity, mid) not in self.moved and not self.consistency.is_suspect(entity, mid, capture_time_us):
            self.places.drop(mid)
            return None
        place = self.places.place(mid)
        last = self._place_tried_us.get(mid)
        if place is not None or (last is not None and 0 <= capture_time_us - last < PLACE_RETRY_US):
            return place
        self._place_tried_us[mid] = capture_time_us
        found = self.places.establish(mid, capture_time_us, self._trusted(capture_time_us))
        if isinstance(found, str):
            return None
        self.counters["places_measured"] += 1
        dx, dy, dz = found.offset_m
        _logger.warning(
            "sensor %s: world marker %d is %.1f cm from its place in the world file (%+.3f %+.3f %+.3f m):"
            " using its measured place (sigma %.1f mm, %.2f deg; %d images in %d views, scatter %.1f)",
            self.sensor.name, mid, float(np.linalg.norm(found.offset_m)) * 100, dx, dy, dz, found.max_sigma_m * 1000,
            found.max_sigma_deg, found.items, found.views, found.scatter,
        )  # fmt: skip
        self._say_status(
            f"atlas: marker {mid} at {round(dx * 100):+d} {round(dy * 100):+d} {round(dz * 100):+d} cm, used",
            capture_time_us,
        )
        return found

    def map_pose_changed(self, marker_id: int) -> None:
        """The node's map now holds another pose of the marker than the world file's (live refinement): its
        measured place here, relative to the world file's, must no longer be used."""
        self._map_changed.add(marker_id)
        self.places.drop(marker_id)

    def at_place(self, mid: int, mp: pose.MarkerPose, place: MeasuredPlace, capture_time_us: int) -> MarkerData:
        """Marker ``mid``'s own square as an observation of its world-file pose that places the sensor where
        its measured place does, with the place's covariance carried along."""
        T_file = self.marker_pose[mid]
        R = Rotation.from_quat(mp.q_xyzw).as_matrix()
        p, R_new, cov, C_sensor = place.correct(mp.p_m, R, mp.covariance, T_file)
        alt = None
        if mp.p_alt_m is not None and mp.q_alt_xyzw is not None:  # the other planar solution, moved alike
            R_alt = Rotation.from_quat(mp.q_alt_xyzw).as_matrix()
            p_alt, R_alt_new, _, _ = place.correct(mp.p_alt_m, R_alt, mp.covariance, T_file)
            alt = (p_alt, Rotation.from_matrix(R_alt_new).as_quat())
        sigma = math.hypot(mp.sigma_m, math.sqrt(max(float(np.linalg.eigvalsh(C_sensor)[-1]), 0.0)))
        self.counters["placed_used"] += 1
        return marker_data(
            self.sensor.id, mid, p, Rotation.from_matrix(R_new).as_quat(), sigma, mp.reprojection_error_px,
            mp.ambiguity, capture_time_us, alt, cov,
        )  # fmt: skip

    def _say_status(self, text: str, capture_time_us: int) -> None:
        """A STATUSTEXT about moved markers, at most one a minute."""
        if self._moved_status_us is None or capture_time_us - self._moved_status_us >= STATUS_INTERVAL_US:
            self._moved_status_us = capture_time_us
            self.status.append(text[:50])

    def doubtful(self, entity: str, ids: list[int], capture_time_us: int) -> set[int]:
        """Those of ``ids`` reported moved or suspect."""
        suspects = self.consistency.suspects(entity, capture_time_us)
        return {m for m in ids if m in suspects or (entity, m) in self.moved}

    def record_group(
        self, entity: str, fitted: list[int], left_out: list[int], singles: dict[int, SingleSolve], capture_time_us: int
    ) -> None:
        """A joint solve's verdicts to the consistency graph. A moved or suspect marker that fitted is
        judged by its offset from the others instead: the joint fit cannot see a move along the line of
        sight of far squares, and such a marker must not be cleared by it."""
        doubtful = self.doubtful(entity, fitted, capture_time_us)
        trusted = [m for m in fitted if m not in doubtful]
        if not trusted or not doubtful:
            self.consistency.add_group(capture_time_us, entity, fitted, left_out)
            return
        self.consistency.add_group(capture_time_us, entity, trusted, left_out)
        for m in doubtful:
            offset = self.joint.offset(m, trusted, singles)
            if offset is not None:
                agree = bool(np.linalg.norm(offset) <= CLEAR_OFFSET_M)
                for b in trusted:
                    self.consistency.add(capture_time_us, entity, m, b, agree)

    def _sightings(self, ids: list[int], singles: dict[int, SingleSolve], capture_time_us: int) -> dict[int, Sighting]:
        """Where each marker's own square puts the camera in its entity's frame, with the (3, 3) covariance
        of that position from the pose's 6x6, all at once (each one's products those of it alone); not for
        a marker without a covariance, or whose pose may be the mirrored planar solution."""
        use = [
            m
            for m in ids
            if singles[m].pose.covariance is not None and singles[m].pose.ambiguity <= AMBIGUITY_THRESHOLD
        ]
        if not use:
            return {}
        poses = [singles[m].pose for m in use]
        R_cm = matrices_from_quats(np.array([mp.q_xyzw for mp in poses]))
        Rt = np.swapaxes(R_cm, 1, 2)
        u = (Rt @ np.array([mp.p_m for mp in poses])[:, :, None])[..., 0]  # minus the camera's position, marker frame
        # c = -R^T p; with p + dp and R exp(dtheta): dc = -R^T dp - [u]x dtheta (pose_covariance's error vector)
        J = np.full((len(use), 3, 6), -0.0)
        J[:, :, :3] = -Rt
        J[:, 0, 4], J[:, 0, 5], J[:, 1, 5] = u[:, 2], -u[:, 1], u[:, 0]  # -[u]x
        J[:, 1, 3], J[:, 2, 3], J[:, 2, 4] = -u[:, 2], u[:, 1], -u[:, 0]
        frames = [self._marker_rt(m) for m in use]
        R_em = np.array([R for R, _ in frames])
        R_emT, Jt = np.swapaxes(R_em, 1, 2), np.swapaxes(J, 1, 2)
        cov = R_em @ J @ np.array([mp.covariance for mp in poses]) @ Jt @ R_emT
        p = (R_em @ -u[:, :, None])[..., 0] + np.array([t for _, t in frames])
        cov = (cov + np.swapaxes(cov, 1, 2)) / 2.0
        return {m: Sighting(capture_time_us, p[k], cov[k]) for k, m in enumerate(use)}

    def _marker_rt(self, m: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Marker ``m``'s rotation matrix and translation in its entity (``T_entity_marker``), kept."""
        got = self._rt.get(m)
        if got is None:
            T = self.marker_pose[m]
            got = self._rt[m] = (T.rotation.as_matrix(), T.translation)
        return got

    def consistency_evidence(
        self, entity: str, ids: list[int], singles: dict[int, SingleSolve], capture_time_us: int
    ) -> list[PairVerdict]:
        """The temporal verdicts of this image's markers of ``entity`` (:class:`MotionCheck`), added to
        the consistency graph and returned. Only for the world's markers: the camera's motion in the
        world's frame is bounded by its vehicle alone; in another entity's frame that entity's motion and
        turns add to it."""
        if entity != WORLD:
            return []
        now = self._sightings(ids, singles, capture_time_us)
        verdicts = self.motion.compare(entity, now)
        for v in verdicts:
            self.consistency.add(capture_time_us, entity, v.marker_id, v.other, v.agree)
        self.counters["motion_disagrees"] += sum(not v.agree for v in verdicts)
        return verdicts

    def _trusted_verdicts(
        self, entity: str, verdicts: list[PairVerdict], capture_time_us: int
    ) -> dict[int, PairVerdict]:
        """Per marker, its verdict against the best supported marker that is not suspect and agrees with
        at least one other (the reference the world check can trust)."""
        best: dict[int, tuple[int, PairVerdict]] = {}
        suspects = self.consistency.suspects(entity, capture_time_us)
        for v in verdicts:
            if v.other in suspects:
                continue
            support = self.consistency.support(entity, v.other, capture_time_us)
            if support >= 2 and (v.marker_id not in best or support > best[v.marker_id][0]):
                best[v.marker_id] = (support, v)
        return {m: v for m, (_, v) in best.items()}

    def pair_verdicts(
        self, entity: str, a: int, b: int, agree: bool, singles: dict[int, SingleSolve], capture_time_us: int
    ) -> list[PairVerdict]:
        """The joint solve's verdict on a pair for each of its markers, for the world check (a moved or
        suspect one that fitted is judged by its offset, as in :meth:`_record_group`)."""
        out = []
        for m, other in ((a, b), (b, a)):
            doubtful = bool(self.doubtful(entity, [m], capture_time_us))
            offset = np.zeros(3) if agree and not doubtful else self.joint.offset(m, [other], singles)
            if offset is not None:
                fits = agree and (not doubtful or bool(np.linalg.norm(offset) <= CLEAR_OFFSET_M))
                out.append(PairVerdict(m, other, fits, offset))
        return out

    def feed(self, entity: str, verdicts: list[PairVerdict], capture_time_us: int) -> None:
        """Pair and temporal verdicts against trusted markers, one per marker and image, to the live check."""
        trusted = self._trusted_verdicts(entity, verdicts, capture_time_us)
        if trusted:
            self.offsets = {m: v.offset_m for m, v in trusted.items() if not v.agree}
            self.check(entity, sorted(trusted), capture_time_us)

    def jumped(
        self, entity: str, m: int, verdicts: list[PairVerdict], capture_time_us: int, place: MeasuredPlace | None = None
    ) -> bool:
        """Whether marker ``m`` put the camera this image where it cannot have moved to from where a
        better supported marker put it a frame ago. At its measured ``place`` (the verdicts judge the world
        file's): when what it shows is off that place by more than any comparison allows."""
        own = self.consistency.support(entity, m, capture_time_us)
        for v in verdicts:
            if v.marker_id != m or self.consistency.support(entity, v.other, capture_time_us) <= own:
                continue
            if place is None and not v.agree:
                return True
            if place is not None and np.linalg.norm(v.offset_m - place.offset_m) > MOTION_MAX_ALLOWANCE_M:
                return True
        return False

    def take_joint(
        self,
        entity: str,
        ids: list[int],
        result: JointResult,
        singles: dict[int, SingleSolve],
        capture_time_us: int,
        report: FrameReport,
    ) -> None:
        """A joint solve's result (:meth:`JointSolve.robust`) of ``ids``: each marker left out counted,
        explained and logged, its offset kept as this image's; the fitted markers' verdicts to the
        consistency graph; two that disagree recorded as such, explained and logged."""
        for out in result.left_out:
            if out.offset is not None:
                self.offsets[out.marker_id] = out.offset
            self.disagrees(entity, out.marker_id, out.distance_m, capture_time_us, report)
        if result.md is not None and result.used is not None:
            left_out = [i for i in ids if i not in result.used]
            self.record_group(entity, result.used, left_out, singles, capture_time_us)
            return
        if result.used is not None:  # the joint solve failed: nothing was judged
            return
        for m in result.unfit:
            report.dropped.setdefault(m, "joint misfit: the markers do not fit together as placed")
        if result.pair_offset is not None:
            a, b = result.unfit
            self.consistency.add(capture_time_us, entity, a, b, False)
            if result.pair_offset.offset is not None:
                self.offsets[b] = result.pair_offset.offset
            offset = result.pair_offset.distance_m
            report.dropped[a] = report.dropped[b] = (
                f"joint misfit, markers {a} and {b} disagree by {offset * 100:.1f} cm"
            )
            self.log_disagreement(entity, f"markers {a} and {b} disagree", offset, capture_time_us)

    def disagrees(self, entity: str, m: int, offset_m: float, capture_time_us: int, report: FrameReport) -> None:
        """Marker ``m`` left out of a joint solve: counted, explained in this frame's ``report``, logged."""
        self.counters["marker_disagrees"] += 1
        self.disagreements[m] += 1
        report.dropped[m] = f"joint misfit, marker {m} disagrees by {offset_m * 100:.1f} cm"
        self.log_disagreement(entity, f"marker {m} disagrees", offset_m, capture_time_us)

    def log_disagreement(self, entity: str, what: str, offset_m: float, capture_time_us: int) -> None:
        """A disagreement with the world file: a log line at most every ``LOG_INTERVAL_US``, a STATUSTEXT at most
        every ``STATUS_INTERVAL_US``."""
        text = f"{entity}: {what} by {offset_m * 100:.1f} cm"
        if self._last_log_us is None or abs(capture_time_us - self._last_log_us) >= LOG_INTERVAL_US:
            self._last_log_us = capture_time_us
            _logger.warning("sensor %s: %s with the world file (not used)", self.sensor.name, text)
        if self._last_status_us is None or abs(capture_time_us - self._last_status_us) >= STATUS_INTERVAL_US:
            self._last_status_us = capture_time_us
            self.status.append(f"atlas {text}"[:50])
