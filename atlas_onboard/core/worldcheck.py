"""The live world-file check: which markers the cameras keep seeing away from where the world file puts them.

Evidence comes one image at a time from the detector's joint solve of an entity's markers seen
together (three or more, so that one that does not fit can be singled out): every marker of the
group was checked, and the one left out because it did not fit the others disagreed, by an offset
(where its own square puts it minus where the world file puts it, in the entity's frame, metres). One
image proves nothing (a blurred corner, a mirrored pose); a marker is reported moved only when,
within a sliding window, it was checked in many images, disagreed in most of them, over more than a
moment, and the median of its offsets is beyond what the corners' noise gives.

Faster evidence is in :mod:`atlas_onboard.core.consistency` (markers compared with each other, in one
image and across frames); a moved marker's measured place in :mod:`atlas_onboard.core.places`.

Pure: the time is each image's capture stamp, passed in.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

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
