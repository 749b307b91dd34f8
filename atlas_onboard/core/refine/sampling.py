"""Which images a refining node's camera reports marker by marker (pure; the detector asks it each frame).

Refinement needs each world marker's own pose in an image that shows three or more of them, and counts
an image as a new view only when it is at least
:attr:`~atlas_onboard.core.refine.refiner.RefineOptions.view_gap_s` after the last one of its camera: the
images between would add no views, and the joint solve gives far better poses than the fusion of single
squares. So an image is taken marker by marker when ``period_us`` has passed since the last one (capture
time; 0: every image) and three or more world markers were found in the previous image (the next one most
likely shows them too); every other image is solved as always.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

MIN_WORLD_MARKERS = 3  # a marker is placed by two or more others in the same image


@dataclass
class PerMarkerSchedule:
    """The per-marker images of one camera (see the module)."""

    world_ids: frozenset[int]
    period_us: int
    _last_us: int | None = field(default=None, init=False)
    _world_seen: int = field(default=0, init=False)  # world markers found in the previous image

    def due(self, capture_time_us: int) -> bool:
        """Whether the image captured at ``capture_time_us`` is to be reported marker by marker."""
        elapsed = self._last_us is None or not 0 <= capture_time_us - self._last_us < self.period_us
        return elapsed and self._world_seen >= MIN_WORLD_MARKERS

    def saw(self, capture_time_us: int, per_marker: bool, found: Iterable[int]) -> None:
        """After the image: whether it was taken marker by marker, and the markers found in it (reported
        or not: a joint solve leaves out the marker that does not fit, the one to refine)."""
        if per_marker:
            self._last_us = capture_time_us
        self._world_seen = len(self.world_ids.intersection(found))
