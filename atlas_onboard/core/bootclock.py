"""The autopilot's boot clock on the node's wall clock: :class:`BootClock` maps ``time_boot_ms`` to the
wall time (UNIX epoch, microseconds) by the lower envelope of the offsets seen, which follows a clock
that drifts; a mapped stamp is then late by about the link's smallest latency.

Pure: the standard library only; times are passed in.
"""

from __future__ import annotations

import itertools
from collections import deque
from collections.abc import Iterable

REBOOT_BACK_US = 1_000_000
"""``time_boot_ms`` going back by more than this is a reboot of the autopilot: the mapping restarts."""


class BootClock:
    """Maps the autopilot's boot time (``time_boot_ms``) to the node's wall clock (us), following its drift.

    Each sample gives ``offset = arrival - boot``: the clocks' offset, which drifts at the rate the two
    clocks differ (their skew), plus the link's delay, never below its floor. The mapping is the lower
    envelope of the recent offsets: the line below every (boot, offset) point of the last
    ``BOOT_WINDOW_US`` that lies closest to them on average, a linear programme solved by the lower
    convex hull's edge over their mean boot time (Moon, Skelly and Towsley, "Estimation and removal of
    clock skew from network delay measurements", INFOCOM 1999). Late packets sit above it and never
    move it; a clock that runs slow or fast tilts it. A mapped stamp is late by the link's delay floor
    (which no one-way measurement can tell from an offset) plus the envelope's own error, a small part
    of the delays' spread over a window of thousands of samples. One point is kept per ``BOOT_BIN_US``
    of boot time (the lowest about the current line), so that the hull stays small.

    Until the samples span ``BOOT_MIN_SPAN_US`` the offset is the smallest seen (no rate yet). A boot
    time that goes back by more than ``REBOOT_BACK_US`` starts over.
    """

    def __init__(self) -> None:
        self._points: deque[tuple[int, int]] = deque()  # (boot us, offset us): one per bin, oldest first
        self._boot_sum = 0  # of the points' boot times, for their mean
        self._prefix: list[tuple[int, int]] | None = None  # lower hull of all points but the last
        self._last_boot_us = -1
        self._line: tuple[float, float, float] | None = None  # (boot0 us, offset at boot0 us, slope)

    def wall_us(self, time_boot_us: int, arrival_wall_us: int) -> int:
        """The wall time (us) of a sample the autopilot stamped ``time_boot_us`` and that arrived at
        ``arrival_wall_us`` (both integers); never later than its arrival."""
        if time_boot_us < self._last_boot_us - REBOOT_BACK_US:
            self._points.clear()
            self._boot_sum, self._prefix, self._line = 0, None, None
        self._last_boot_us = time_boot_us
        offset = arrival_wall_us - time_boot_us
        points = self._points
        slope = self._line[2] if self._line is not None else 0.0
        if points and points[-1][0] // BOOT_BIN_US == time_boot_us // BOOT_BIN_US:
            b, o = points[-1]
            if offset - slope * time_boot_us < o - slope * b:  # lower than the bin's point about the line
                points[-1] = (time_boot_us, offset)
                self._boot_sum += time_boot_us - b
                self._line = None
        else:
            if points and self._prefix is not None:  # the hull so far grows by the point no longer last
                _push_lower(self._prefix, points[-1])
            points.append((time_boot_us, offset))
            self._boot_sum += time_boot_us
            while points[0][0] < time_boot_us - BOOT_WINDOW_US:
                self._boot_sum -= points.popleft()[0]
                self._prefix = None  # its first vertices may be gone: built again when next needed
            self._line = None
        if self._line is None:
            self._line = self._envelope()
        b0, o0, slope = self._line
        return min(time_boot_us + round(o0 + slope * (time_boot_us - b0)), arrival_wall_us)

    def _envelope(self) -> tuple[float, float, float]:
        """:func:`_lower_envelope` of the points, with the hull of all but the last kept between calls
        (the last point is the one a new sample may replace)."""
        points = self._points
        if points[-1][0] - points[0][0] < BOOT_MIN_SPAN_US:
            return _lower_envelope(list(points))
        if self._prefix is None:
            self._prefix = _lower_hull(itertools.islice(points, len(points) - 1))
        hull = self._prefix.copy()
        _push_lower(hull, points[-1])
        return _hull_line(hull, self._boot_sum / len(points))

    def lead_us(self, time_boot_us: int, arrival_wall_us: int) -> int:
        """How far after its own arrival a sample stamped ``time_boot_us`` would map on the mapping so
        far (0 before any, or after a reboot): never positive for a real sample but for the clocks'
        drift since the mapping was set; a stamp ahead of the autopilot's clock is what makes it so."""
        if self._line is None or time_boot_us < self._last_boot_us - REBOOT_BACK_US:
            return 0
        b0, o0, slope = self._line
        return time_boot_us + round(o0 + slope * (time_boot_us - b0)) - arrival_wall_us


BOOT_BIN_US = 500_000
"""Boot time per point of :class:`BootClock`'s envelope (its lowest sample about the current line)."""
BOOT_WINDOW_US = 60_000_000
"""How far back :class:`BootClock`'s envelope reaches: long enough that the delays' spread over it is a
small tilt, short enough to follow a clock whose rate changes with its temperature."""
BOOT_MIN_SPAN_US = 1_000_000
"""The boot time the points must span before the envelope's slope is believed (before: the smallest offset)."""
MAX_SKEW = 0.05
"""The fastest drift believed (5 %): a steeper envelope is a degenerate fit (a reboot not seen as one)."""


def _lower_envelope(points: list[tuple[int, int]]) -> tuple[float, float, float]:
    """(boot0, offset0, slope) of the line below every (boot, offset) point, sorted by boot, with the
    least summed distance to them: the lower hull's edge over their mean boot time (the smallest offset,
    flat, while they span less than ``BOOT_MIN_SPAN_US``)."""
    if points[-1][0] - points[0][0] < BOOT_MIN_SPAN_US:
        lowest = min(points, key=lambda p: p[1])
        return float(lowest[0]), float(lowest[1]), 0.0
    return _hull_line(_lower_hull(points), sum(p[0] for p in points) / len(points))


def _lower_hull(points: Iterable[tuple[int, int]]) -> list[tuple[int, int]]:
    """The lower convex hull of points sorted by boot (Andrew's monotone chain, lower half, exact integers)."""
    hull: list[tuple[int, int]] = []
    for p in points:
        _push_lower(hull, p)
    return hull


def _push_lower(hull: list[tuple[int, int]], p: tuple[int, int]) -> None:
    """One step of the monotone chain: ``p`` appended to ``hull``, dropping the vertices it makes non-convex."""
    px, py = p
    while len(hull) >= 2:
        (ax, ay), (bx, by) = hull[-2], hull[-1]
        if (bx - ax) * (py - ay) - (by - ay) * (px - ax) > 0:  # a, b, p turn counter-clockwise
            break
        hull.pop()
    hull.append(p)


def _hull_line(hull: list[tuple[int, int]], mean_boot: float) -> tuple[float, float, float]:
    """The lower hull's edge over ``mean_boot`` as (boot0, offset0, slope), its slope within ``MAX_SKEW``."""
    for (b0, o0), (b1, o1) in itertools.pairwise(hull):
        if b1 >= mean_boot:
            slope = min(max((o1 - o0) / (b1 - b0), -MAX_SKEW), MAX_SKEW)
            # Clamped or not, the line through the vertex nearer the mean stays below its neighbours.
            return (float(b0), float(o0), slope) if mean_boot - b0 <= b1 - mean_boot else (float(b1), float(o1), slope)
    return float(hull[-1][0]), float(hull[-1][1]), 0.0
