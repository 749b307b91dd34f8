"""Faster evidence for the world-file check: every pair of markers compared, in one image or across frames.

Every pair of markers seen together and every marker seen a frame after another (where it puts the
camera against where the other put it, moved on as a multirotor can move) agree or disagree; a marker
that disagrees with markers that agree among themselves is suspect at once, and its verdicts against
such markers feed :class:`atlas_onboard.core.worldcheck.MovedMarkerCheck`.

Pure: the time is each image's capture stamp, passed in.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core.worldcheck import MIN_OFFSET_M, WINDOW_S

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
        return self._relation_of(q, now_us) if q else None

    def _relation_of(self, q: deque[tuple[int, bool]], now_us: int) -> bool | None:
        """:meth:`relation` of a pair's verdicts ``q`` (not empty)."""
        start = now_us - self.window_us
        n_agree = n_dis = 0
        for t, agree in q:
            if t >= start:
                if agree:
                    n_agree += 1
                else:
                    n_dis += 1
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
            rel = self._relation_of(q, now_us)
            find(a), find(b)
            if rel is True:
                parent[find(a)] = find(b)
            elif rel is False:
                disagree.append((a, b))
        group = {m: find(m) for m in parent}
        size = Counter(group.values())
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
