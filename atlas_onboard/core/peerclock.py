"""Each peer's clock as its observations show it: how far its capture stamps run behind their arrival
on this node's wall clock (its offset and the link's latency), and how much that varies (jitter).

A capture stamp ahead of its arrival by more than the peer's measured offset and jitter allow (plus a
small margin) is refused: stamped in the future, it would make the poses it contributes to look newer
than the own camera's frames, and a pose goes to the autopilot only for a newer capture. Pure: the
times are passed in (microseconds on the swarm's wall clock).

The measure is robust: the median of the last ``WINDOW`` ages at arrival of each origin, and their
scaled median absolute deviation, which a few forged stamps cannot move (every received observation
is counted, refused or not, so that a peer whose clock really runs ahead is learnt, not refused for
ever). Until ``MIN_SAMPLES`` have arrived from an origin, its clock is taken as synchronised and a
stamp may lead its arrival by ``UNMEASURED_LEAD_S``.
"""

from __future__ import annotations

from collections import deque

WINDOW = 64
"""Ages at arrival remembered per origin (about two seconds of a 30 Hz camera)."""
MIN_SAMPLES = 8
"""An origin's offset is measured once this many of its observations have arrived."""
JITTER_K = 4.0
"""A stamp may lead the measured offset by this many times the measured jitter (1.4826 MAD)..."""
FUTURE_MARGIN_S = 0.02
"""... plus this margin (a scheduler's hiccup on either node)."""
REFRESH_EVERY = 4
"""Once an origin's window is full, its bound is recomputed every this many observations (a sort of
the window each time is most of the cost)."""
UNMEASURED_LEAD_S = 0.1
"""The lead allowed before an origin's offset is measured: the clock skew the node already warns about
(clocks synchronised by chrony agree within milliseconds)."""


class PeerClocks:
    """The measured clocks of up to 256 origins (system ids)."""

    def __init__(
        self,
        window: int = WINDOW,
        min_samples: int = MIN_SAMPLES,
        jitter_k: float = JITTER_K,
        margin_s: float = FUTURE_MARGIN_S,
        unmeasured_lead_s: float = UNMEASURED_LEAD_S,
    ) -> None:
        self.window = window
        self.min_samples = min_samples
        self.jitter_k = jitter_k
        self.margin_us = margin_s * 1e6
        self.unmeasured_lead_us = unmeasured_lead_s * 1e6
        self._ages: dict[int, deque[int]] = {}
        self._bounds: dict[int, float] = {}  # origin -> the smallest age accepted, us (from its window)
        self._seen: dict[int, int] = {}  # origin -> observations counted

    def future(self, origin: int, capture_us: int, arrival_wall_us: int) -> bool:
        """Whether an observation of ``origin`` captured at ``capture_us`` and arriving at
        ``arrival_wall_us`` is stamped further in the future than its clock allows (then refuse it).
        The observation is counted in its origin's measure either way."""
        origin &= 0xFF
        age = arrival_wall_us - capture_us
        bound = self._bounds.get(origin, -self.unmeasured_lead_us)
        ages = self._ages.get(origin)
        if ages is None:
            ages = self._ages[origin] = deque(maxlen=self.window)
        ages.append(age)
        self._seen[origin] = seen = self._seen.get(origin, 0) + 1
        if len(ages) >= self.min_samples and (len(ages) < self.window or seen % REFRESH_EVERY == 0):
            self._bounds[origin] = self._bound(ages)
        return age < bound

    def _bound(self, ages: deque[int]) -> float:
        s = sorted(ages)
        n = len(s)
        median = (s[n // 2] + s[(n - 1) // 2]) / 2.0
        dev = sorted(abs(a - median) for a in s)
        mad = (dev[n // 2] + dev[(n - 1) // 2]) / 2.0
        return median - self.jitter_k * 1.4826 * mad - self.margin_us

    def offset_us(self, origin: int) -> float | None:
        """The median age at arrival of ``origin``'s observations (its clock's lag behind ours plus the
        latency), or None before ``MIN_SAMPLES``."""
        ages = self._ages.get(origin & 0xFF)
        if ages is None or len(ages) < self.min_samples:
            return None
        s = sorted(ages)
        return (s[len(s) // 2] + s[(len(s) - 1) // 2]) / 2.0
