"""The live world-file check: which markers the cameras keep seeing away from where the world file puts them.

Evidence comes one image at a time from the detector's joint solve of an entity's markers seen
together (three or more, so that one that does not fit can be singled out): every marker of the
group was checked, and the one left out because it did not fit the others disagreed, by an offset
(where its own square puts it minus where the world file puts it, in the entity's frame, metres). One
image proves nothing (a blurred corner, a mirrored pose); a marker is reported moved only when,
within a sliding window, it was checked in many images, disagreed in most of them, over more than a
moment, and the median of its offsets is beyond what the corners' noise gives.

Faster evidence (:class:`MarkerConsistency`, :class:`MotionCheck`): every pair of markers seen together
and every marker seen a frame after another (where it puts the camera against where the other put it,
moved on as a multirotor can move) agree or disagree; a marker that disagrees with markers that agree
among themselves is suspect at once, and its verdicts against such markers feed the check above.

A moved world marker need not be lost (:class:`MeasuredPlaces`): where images in which trusted markers
placed the camera put it, with the covariance of that estimate, is its measured place, used instead of the
world file's while new evidence keeps fitting it.

Pure: the time is each image's capture stamp, passed in.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.special import chdtri  # chi-square's inverse survival function (scipy.stats costs 0.6 s to import)

from atlas_onboard.core import covariance
from atlas_onboard.core.refine import MapRefiner, RefineOptions, residuals
from atlas_onboard.core.refine import Sighting as PlacedSighting

WINDOW_S = 60.0  # evidence older than this is forgotten (a marker put back stops being reported)
MIN_VIEWS = 20  # images in which the marker was checked together with two or more others
MIN_FRACTION = 0.5  # of those, the share in which it did not fit
MIN_SPAN_S = 1.0  # the disagreeing images span at least this long (not one burst of similar frames)
MIN_OFFSET_M = 0.02  # the median offset must reach this (smaller moves hide in the poses' noise)
MAX_EVIDENCE = 1000  # images kept per marker (a minute at 15 fps; at higher rates the newest 1000)


@dataclass(frozen=True)
class MovedMarker:
    """A marker that looks moved.

    Attributes:
        entity: the entity whose marker it is (``world`` for the room's markers).
        marker_id: its id.
        offset_m: (3,) median of where it was seen minus where the world file has it, entity frame, m.
        views: images in the window in which it was checked.
        disagreeing: of those, the images in which it did not fit the others.
    """

    entity: str
    marker_id: int
    offset_m: NDArray[np.float64]
    views: int
    disagreeing: int

    @property
    def distance_m(self) -> float:
        return float(np.linalg.norm(self.offset_m))


class MovedMarkerCheck:
    """Accumulates the joint solves' verdicts per marker over a sliding window (see the module)."""

    def __init__(
        self,
        window_s: float = WINDOW_S,
        min_views: int = MIN_VIEWS,
        min_fraction: float = MIN_FRACTION,
        min_span_s: float = MIN_SPAN_S,
        min_offset_m: float = MIN_OFFSET_M,
    ) -> None:
        self.window_us = round(window_s * 1e6)
        self.min_views = min_views
        self.min_fraction = min_fraction
        self.min_span_us = round(min_span_s * 1e6)
        self.min_offset_m = min_offset_m
        # (entity, marker id) -> (capture time us, offset (3,) in the entity frame or None when it fitted)
        self._evidence: dict[tuple[str, int], deque[tuple[int, NDArray[np.float64] | None]]] = {}

    def add(
        self,
        capture_time_us: int,
        entity: str,
        checked_ids: Iterable[int],
        offsets_m: Mapping[int, NDArray[np.float64]],
    ) -> list[MovedMarker]:
        """One image's verdict on a group of ``entity``'s markers: each of ``checked_ids`` was
        checked, those in ``offsets_m`` did not fit (offset (3,), entity frame, m). Returns the
        markers of the group that now look moved."""
        out = []
        for mid in checked_ids:
            q = self._evidence.setdefault((entity, mid), deque(maxlen=MAX_EVIDENCE))
            offset = offsets_m.get(mid)
            q.append((capture_time_us, None if offset is None else np.asarray(offset, dtype=float)))
            while q and q[0][0] < capture_time_us - self.window_us:
                q.popleft()
            moved = self._verdict(entity, mid, q)
            if moved is not None:
                out.append(moved)
        return out

    def disagrees(self, entity: str, marker_id: int) -> bool:
        """Whether the marker did not fit in at least ``min_fraction`` of its images in the window."""
        q = self._evidence.get((entity, marker_id))
        if not q:
            return False
        return sum(o is not None for _, o in q) >= self.min_fraction * len(q)

    def _verdict(self, entity: str, mid: int, q: deque[tuple[int, NDArray[np.float64] | None]]) -> MovedMarker | None:
        if len(q) < self.min_views:
            return None
        bad = [(t, o) for t, o in q if o is not None]
        if len(bad) < self.min_fraction * len(q) or bad[-1][0] - bad[0][0] < self.min_span_us:
            return None
        # Component-wise median: a few images with a mirrored pose do not move it.
        offset = np.median(np.array([o for _, o in bad]), axis=0)
        if np.linalg.norm(offset) < self.min_offset_m:
            return None
        return MovedMarker(entity, mid, offset, len(q), len(bad))


# --- Faster evidence: every pair of markers compared, in one image or across a few frames ----------------

PAIR_VERDICTS = 5  # the newest verdicts of a pair that decide whether the two agree
PAIR_MIN = 2  # a relation needs at least this many of the deciding kind (one blurred image is no relation)
A_MAX_M_S2 = 10.0
"""Acceleration the camera can have between frames: a multirotor tilted 45 deg (1 g); attitude
controllers hold indoor vehicles well below it."""
MOTION_K_SIGMA = 4.0  # standard deviations of the compared positions allowed beyond the motion bound
MOTION_MAX_GAP_S = 0.1  # sightings further apart than this are not compared (the allowance grows as dt^2)
MOTION_MAX_ALLOWANCE_M = 0.05  # beyond this allowance a comparison proves nothing either way


@dataclass(frozen=True)
class PairVerdict:
    """Marker ``marker_id`` compared with ``other`` (same entity) in one image: whether they agree, and
    where ``marker_id`` was seen minus where the world file has it, placed by ``other`` (entity frame, m)."""

    marker_id: int
    other: int
    agree: bool
    offset_m: NDArray[np.float64]


class MarkerConsistency:
    """A consistency graph over one entity's markers, from pairwise verdicts within a sliding window.

    Two markers agree (or disagree) when most of the newest ``PAIR_VERDICTS`` verdicts of the pair say
    so, at least ``PAIR_MIN`` of them. Markers that agree form groups (connected components); a marker
    is *suspect* when it disagrees with a marker whose group is larger than its own: its disagreement is
    explained by itself having moved, not by the others (which agree among themselves). Two markers
    that disagree and have equal support cannot say which of them moved: neither is suspect. A suspect
    marker that agrees again (put back) joins the others' group and is cleared.
    """

    def __init__(self, window_s: float = WINDOW_S) -> None:
        self.window_us = round(window_s * 1e6)
        # (entity, low id, high id) -> (capture time us, agree) newest last
        self._pairs: dict[tuple[str, int, int], deque[tuple[int, bool]]] = {}
        self._cache: dict[str, tuple[dict[int, int], set[int]]] = {}  # entity -> (groups, suspects)
        self._cache_at: dict[str, int] = {}

    def add(self, capture_time_us: int, entity: str, a: int, b: int, agree: bool) -> None:
        """One image's verdict on markers ``a`` and ``b`` of ``entity``."""
        if a == b:
            return
        key = (entity, min(a, b), max(a, b))
        q = self._pairs.setdefault(key, deque(maxlen=PAIR_VERDICTS))
        q.append((capture_time_us, agree))
        self._cache.pop(entity, None)

    def add_group(self, capture_time_us: int, entity: str, fitted: Iterable[int], left_out: Iterable[int]) -> None:
        """One joint solve: the ``fitted`` markers agree with each other, each of ``left_out`` disagrees
        with every fitted one."""
        fitted, left_out = list(fitted), list(left_out)
        for i, a in enumerate(fitted):
            for b in fitted[i + 1 :]:
                self.add(capture_time_us, entity, a, b, True)
            for m in left_out:
                self.add(capture_time_us, entity, a, m, False)

    def relation(self, entity: str, a: int, b: int, now_us: int) -> bool | None:
        """True (agree), False (disagree) or None (no sound relation) for the pair, at ``now_us``."""
        q = self._pairs.get((entity, min(a, b), max(a, b)))
        if not q:
            return None
        recent = [agree for t, agree in q if t >= now_us - self.window_us]
        n_agree = sum(recent)
        n_dis = len(recent) - n_agree
        if n_agree >= PAIR_MIN and n_agree > n_dis:
            return True
        if n_dis >= PAIR_MIN and n_dis > n_agree:
            return False
        return None

    def support(self, entity: str, marker_id: int, now_us: int) -> int:
        """How many markers (itself included) its group of agreeing markers holds."""
        group, _ = self._state(entity, now_us)
        root = group.get(marker_id)
        return 1 if root is None else sum(r == root for r in group.values())

    def suspects(self, entity: str, now_us: int) -> set[int]:
        """The markers of ``entity`` whose disagreements only they can explain (see the class)."""
        return self._state(entity, now_us)[1]

    def is_suspect(self, entity: str, marker_id: int, now_us: int) -> bool:
        return marker_id in self.suspects(entity, now_us)

    def _state(self, entity: str, now_us: int) -> tuple[dict[int, int], set[int]]:
        # Recomputed when a verdict arrives (or once a second, as verdicts leave the window).
        cached = self._cache.get(entity)
        if cached is not None and self._cache_at.get(entity, -1) // 1_000_000 == now_us // 1_000_000:
            return cached
        parent: dict[int, int] = {}

        def find(x: int) -> int:
            parent.setdefault(x, x)
            while parent[x] != x:
                parent[x] = parent[parent[x]]
                x = parent[x]
            return x

        disagree = []
        for (e, a, b), q in list(self._pairs.items()):
            if e != entity:
                continue
            if q[-1][0] < now_us - self.window_us:
                del self._pairs[(e, a, b)]
                continue
            rel = self.relation(entity, a, b, now_us)
            find(a), find(b)
            if rel is True:
                parent[find(a)] = find(b)
            elif rel is False:
                disagree.append((a, b))
        group = {m: find(m) for m in parent}
        size = {r: sum(g == r for g in group.values()) for r in set(group.values())}
        suspects = set()
        for a, b in disagree:
            sa, sb = size[group[a]], size[group[b]]
            if sa < sb:
                suspects.add(a)
            elif sb < sa:
                suspects.add(b)
        self._cache[entity] = (group, suspects)
        self._cache_at[entity] = now_us
        return group, suspects


@dataclass(frozen=True)
class Sighting:
    """Where one marker (by its world-file place) put the camera: ``p_m`` (3,) and its covariance
    ``cov_m2`` (3, 3), entity frame, at ``capture_time_us``."""

    capture_time_us: int
    p_m: NDArray[np.float64]
    cov_m2: NDArray[np.float64]


class MotionCheck:
    """Temporal evidence: the camera cannot jump. Where a marker seen now puts the camera is compared
    with where another marker put it in the last frames, moved on by the camera's velocity (from two
    sightings of one marker: the same for every marker, whatever its error in the world file) and
    allowed the change of velocity that ``a_max_m_s2`` permits, plus ``k_sigma`` standard deviations of
    both positions along the jump. Sightings more than ``max_gap_s`` apart are not compared and the
    allowance grows as dt^2, so a camera that really moved (re-acquired after a gap) is never held to
    an old pose. A jump of less than ``MIN_OFFSET_M`` is no disagreement, and an agreement counts only
    when a move of ``max_allowance_m`` in any direction would have shown.
    """

    def __init__(
        self,
        a_max_m_s2: float = A_MAX_M_S2,
        k_sigma: float = MOTION_K_SIGMA,
        max_gap_s: float = MOTION_MAX_GAP_S,
        max_allowance_m: float = MOTION_MAX_ALLOWANCE_M,
    ) -> None:
        self.a_max = a_max_m_s2
        self.k_sigma = k_sigma
        self.max_gap_us = round(max_gap_s * 1e6)
        self.max_allowance_m = max_allowance_m
        # entity -> marker id -> its newest two sightings
        self._seen: dict[str, dict[int, deque[Sighting]]] = {}

    def compare(self, entity: str, now: Mapping[int, Sighting]) -> list[PairVerdict]:
        """Verdicts of this image's sightings ``now`` (marker id -> sighting, one capture time) against
        the markers not seen now but seen within ``max_gap_s``; then remembers ``now``."""
        seen = self._seen.setdefault(entity, {})
        out: list[PairVerdict] = []
        if now:
            t_us = next(iter(now.values())).capture_time_us
            velocity = self._velocity(seen, t_us)
            for b, hist in seen.items():
                last = hist[-1]
                dt_s = (t_us - last.capture_time_us) / 1e6
                if b in now or not 0.0 < dt_s <= self.max_gap_us / 1e6:
                    continue
                own = self._velocity({b: hist}, t_us)
                v = own if own is not None else velocity
                if v is None:
                    continue
                v_m_s, cov_v, t0_us = v
                # Constant velocity from the mean over [t0, t1]: off by at most a_max dt (t - t0 - dt/2).
                motion_m = self.a_max * dt_s * ((t_us - t0_us) / 1e6 - dt_s / 2.0)
                p_pred = last.p_m + v_m_s * dt_s
                if own is not None:  # p1 + (p1 - p0) r: both sightings' noise, correlated through p1
                    r = dt_s / ((last.capture_time_us - hist[0].capture_time_us) / 1e6)
                    cov_pred = (1.0 + r) ** 2 * last.cov_m2 + r**2 * hist[0].cov_m2
                else:
                    cov_pred = last.cov_m2 + cov_v * dt_s**2
                for m, s in now.items():
                    cov = cov_pred + s.cov_m2
                    d = s.p_m - p_pred
                    dist = float(np.linalg.norm(d))
                    sigma_dir = math.sqrt(float(d @ cov @ d)) / dist if dist > 0 else 0.0
                    if dist > max(self.k_sigma * sigma_dir + motion_m, MIN_OFFSET_M):
                        agree = False  # beyond the bound along the direction it jumped
                    elif (
                        self.k_sigma * math.sqrt(max(np.linalg.eigvalsh(cov)[-1], 0.0)) + motion_m
                        <= self.max_allowance_m
                    ):
                        agree = True  # close, and a move of max_allowance_m in any direction would have shown
                    else:
                        continue  # close, but too uncertain along some direction to say it fits
                    # The camera seen too far by d: marker m's square is -d from its world-file place.
                    out.append(PairVerdict(m, b, agree, -d))
        for m, s in now.items():
            seen.setdefault(m, deque(maxlen=2)).append(s)
        for b in [b for b, h in seen.items() if now and h[-1].capture_time_us < t_us - 10 * self.max_gap_us]:
            del seen[b]
        return out

    def _velocity(
        self, seen: Mapping[int, deque[Sighting]], t_us: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], int] | None:
        """The newest velocity (m/s, its (3, 3) covariance, the older sighting's time) from two
        sightings of one marker at most ``max_gap_s`` apart, both within ``max_gap_s`` of ``t_us``."""
        best = None
        for hist in seen.values():
            if len(hist) < 2:
                continue
            s0, s1 = hist[0], hist[1]
            dt_s = (s1.capture_time_us - s0.capture_time_us) / 1e6
            if not 0.0 < dt_s <= self.max_gap_us / 1e6 or t_us - s1.capture_time_us > self.max_gap_us:
                continue
            if best is None or s1.capture_time_us > best[0]:
                best = (
                    s1.capture_time_us,
                    (s1.p_m - s0.p_m) / dt_s,
                    (s0.cov_m2 + s1.cov_m2) / dt_s**2,
                    s0.capture_time_us,
                )
        return None if best is None else best[1:]


# --- A moved world marker used at its measured place --------------------------------------------------------

PLACE_MIN_VIEWS = 3  # independent views (refine's view gap) behind a measured place: not one burst of frames
PLACE_MAX_SCATTER = 9.0  # the evidence may scatter at most 3x (in sigma) what its covariances say
PLACE_MAX_OUTLIERS = 0.25  # of the evidence items, the share the robust mean may set aside
PLACE_MAX_SIGMA_M = 0.02  # a place more uncertain than this is not used (its poses would be worth little)
PLACE_MAX_SIGMA_DEG = 3.0
RECHECK_P = 1e-4  # a new item does not fit the place when its position's distance has this tail probability
RECHECK_MIN_M = 0.01  # and it is at least this far (closer, the pose errs by less than the bars allow)
RECHECK_MIN_DEG = 2.0  # or turned by at least this much (and beyond the same distance, in rotation)
RECHECK_LAST = 5  # the newest trusted items that decide whether the place still holds
RECHECK_MISFITS = 3  # of those, this many that do not fit: the marker has moved again


@dataclass(frozen=True)
class MeasuredPlace:
    """Where a moved world marker really is, from images in which trusted markers placed the camera.

    Attributes:
        marker_id: the marker.
        p_world_marker_m: (3,) its measured position, world frame, m.
        R_world_marker: (3, 3) its measured rotation.
        cov: (6, 6) the place's covariance (``[dp, dtheta]``, dp world frame m, dtheta marker axes rad):
            the evidence's information inverted, inflated by its scatter and by frames per view.
        offset_m: (3,) measured position minus the world file's, world frame, m.
        scatter: the evidence's scatter factor (squared distances over what the covariances say, >= 1).
        items: evidence items used; views: independent views among them.
        since_us: capture time of the image in which it was established.
    """

    marker_id: int
    p_world_marker_m: NDArray[np.float64]
    R_world_marker: NDArray[np.float64]
    cov: NDArray[np.float64]
    offset_m: NDArray[np.float64]
    scatter: float
    items: int
    views: int
    since_us: int

    @property
    def sigma_m(self) -> float:
        """The position's largest 1-sigma, m."""
        return float(math.sqrt(max(np.linalg.eigvalsh(self.cov[:3, :3])[-1], 0.0)))

    @property
    def sigma_deg(self) -> float:
        """The rotation's largest 1-sigma, degrees."""
        return float(math.degrees(math.sqrt(max(np.linalg.eigvalsh(self.cov[3:, 3:])[-1], 0.0))))

    def fits(
        self, p_world_marker_m: NDArray[np.float64], R_world_marker: NDArray[np.float64], cov: NDArray[np.float64]
    ) -> bool:
        """Whether a new sighting of the marker's pose in the world (covariance ``cov`` (6, 6), scaled by the
        evidence's scatter) is where the place is: a position beyond ``RECHECK_P`` of both covariances and
        ``RECHECK_MIN_M`` away, or a rotation beyond it and ``RECHECK_MIN_DEG``, does not fit. The floors:
        images from one view share errors their covariances do not show, and a move below them costs the
        pose less than its bars."""
        r = residuals(p_world_marker_m[None], R_world_marker[None], self.p_world_marker_m, self.R_world_marker)[0]
        C = self.scatter * cov + self.cov
        gate = chdtri(3, RECHECK_P)
        try:
            far = float(r[:3] @ np.linalg.solve(C[:3, :3], r[:3])) > gate and np.linalg.norm(r[:3]) >= RECHECK_MIN_M
            turned = float(r[3:] @ np.linalg.solve(C[3:, 3:], r[3:])) > gate and (
                math.degrees(float(np.linalg.norm(r[3:]))) >= RECHECK_MIN_DEG
            )
        except np.linalg.LinAlgError:
            return False
        return not (far or turned)

    def correct(
        self,
        p_sensor_marker_m: NDArray[np.float64],
        R_sensor_marker: NDArray[np.float64],
        cov: NDArray[np.float64],
        R_world_file: NDArray[np.float64],
        p_world_file_m: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """A sighting of the marker re-expressed for its world-file pose (``p_world_file_m``,
        ``R_world_file``): ``T_sensor_marker' = T_sensor_marker T_place^-1 T_file``, so that eq. 1 with the
        file pose places the sensor where the measured place does. Returns p' (3,), R' (3, 3), its
        covariance (6, 6: the sighting's ``cov`` and the place's together) and the (3, 3) covariance the
        place adds to the sensor's position in the world frame."""
        # D = T_place^-1 T_file: the place's error through the inverse, then composed with the exact file pose.
        R_mw = self.R_world_marker.T
        C_inv = covariance.transform(covariance.inverse_jacobian(self.p_world_marker_m, self.R_world_marker), self.cov)
        d = R_mw @ (p_world_file_m - self.p_world_marker_m)
        R_d = R_mw @ R_world_file
        Jp_d, _ = covariance.compose_jacobians(R_mw, p_world_file_m, R_world_file)
        C_d = covariance.transform(Jp_d, C_inv)
        Jp, Je = covariance.compose_jacobians(R_sensor_marker, d, R_d)
        C = covariance.transform(Jp, cov) + covariance.transform(Je, C_d)
        # The sensor in the world through the place: T_place T_marker_sensor, the place's share of its position.
        R_ms = R_sensor_marker.T
        Jw, _ = covariance.compose_jacobians(self.R_world_marker, -R_ms @ p_sensor_marker_m, R_ms)
        C_sensor = covariance.transform(Jw, self.cov)[:3, :3]
        return (
            p_sensor_marker_m + R_sensor_marker @ d,
            R_sensor_marker @ R_d,
            0.5 * (C + C.T),
            0.5 * (C_sensor + C_sensor.T),
        )


class MeasuredPlaces:
    """The measured places of moved world markers (:class:`MeasuredPlace`), on the evidence of
    :class:`~atlas_onboard.core.refine.MapRefiner` (leave-one-out: the other markers of an image place the
    camera, the camera places the marker; the map stays the world file's).

    Only items whose placing markers the caller trusts count (``trusted``, asked when a place is
    established and when an item is re-checked: a marker placed by a moved or suspect one, or by itself,
    would be circular). A place is established when the evidence is consistent (its scatter and
    outliers bounded), from several independent views and precise enough; it is then re-checked with
    every new trusted item: when ``RECHECK_MISFITS`` of the newest ``RECHECK_LAST`` do not fit it (the
    marker was moved again, or is on something that moves), it is withdrawn and the evidence before those
    items forgotten, so that a new place can only come from what was seen since.
    """

    def __init__(
        self,
        T_world_marker: Mapping[int, tuple[NDArray[np.float64], NDArray[np.float64]]],
        window_s: float = WINDOW_S,
    ) -> None:
        # One other marker may place the camera (pairs): trust is decided by the caller, per item.
        self.refiner = MapRefiner(T_world_marker, options=RefineOptions(min_others=1, max_evidence=MAX_EVIDENCE))
        self.window_us = round(window_s * 1e6)
        self._places: dict[int, MeasuredPlace] = {}
        self._checks: dict[int, deque[tuple[int, bool]]] = {}  # marker -> (capture time us, fits) newest last

    def add_image(
        self,
        camera: Hashable,
        capture_time_us: int,
        sightings: Sequence[PlacedSighting],
        trusted: Callable[[frozenset[int]], bool],
    ) -> list[MeasuredPlace]:
        """One image's world markers (two or more); returns the places withdrawn by this image's evidence."""
        if len(sightings) < 2 or not self.refiner.add_image(camera, capture_time_us, sightings):
            return []
        out = []
        for s in sightings:
            place = self._places.get(s.marker_id)
            item = self.refiner.latest(s.marker_id)
            if place is None or item is None or item.capture_time_us != capture_time_us or not trusted(item.others):
                continue
            checks = self._checks.setdefault(s.marker_id, deque(maxlen=RECHECK_LAST))
            checks.append((capture_time_us, place.fits(item.p_world_marker_m, item.R_world_marker, item.cov)))
            misfits = [t for t, fits in checks if not fits]
            if len(misfits) >= RECHECK_MISFITS:
                self._checks.pop(s.marker_id, None)
                withdrawn = self._places.pop(s.marker_id, None)  # (None: dropped meanwhile by another thread)
                if withdrawn is not None:
                    out.append(withdrawn)
                self.refiner.forget(s.marker_id, misfits[0])
        return out

    def establish(self, marker_id: int, now_us: int, trusted: Callable[[frozenset[int]], bool]) -> MeasuredPlace | str:
        """The marker's measured place from its trusted evidence within the window, kept and returned, or
        why there is none yet (one line)."""
        if marker_id in self._places:
            return self._places[marker_id]
        since = now_us - self.window_us
        est = self.refiner.estimate(marker_id, accept=lambda e: e.capture_time_us >= since and trusted(e.others))
        if est is None:
            return "too little evidence from trusted markers"
        if est.views < PLACE_MIN_VIEWS:
            return f"{est.views} independent views (needs {PLACE_MIN_VIEWS})"
        if est.scatter > PLACE_MAX_SCATTER or est.outliers > PLACE_MAX_OUTLIERS * est.items:
            return f"inconsistent evidence (scatter {est.scatter:.1f}, {est.outliers} of {est.items} outliers)"
        if est.max_sigma_m > PLACE_MAX_SIGMA_M or est.max_sigma_deg > PLACE_MAX_SIGMA_DEG:
            return f"not precise enough (sigma {est.max_sigma_m * 1000:.1f} mm, {est.max_sigma_deg:.2f} deg)"
        place = MeasuredPlace(
            marker_id, est.p_world_marker_m, est.R_world_marker, est.cov, est.offset_m, est.scatter,
            est.items - est.outliers, est.views, now_us,
        )  # fmt: skip
        self._places[marker_id] = place
        return place

    def place(self, marker_id: int) -> MeasuredPlace | None:
        return self._places.get(marker_id)

    def drop(self, marker_id: int) -> None:
        """Forget a marker's place (it fits the world file again)."""
        self._places.pop(marker_id, None)
        self._checks.pop(marker_id, None)
