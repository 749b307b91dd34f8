"""The graph publisher (the paper's block 3): decides what leaves the node, and when.

Pure: no I/O and no clock (times are passed in as integer nanoseconds of the node's monotonic clock).
The node asks it after every accepted observation and on every tick; it answers with what to send:

- the own entity's pose for the autopilot, only when a newer observation contributed to it (so a
  pose is never sent twice, and never once its edges have expired), at most ``rate_hz`` (:class:`RateCap`);
- a reset counter that increments when a pose goes after nothing was sent for at least ``reset_gap_s``
  and the pose was lost meanwhile (a re-acquisition after a real loss: said, or held that long by the
  gate, whose held pose is not sent again), or when a pose resting on the node's own cameras jumps
  (never for a jump of a pose peers alone made: peers' candidates are held to the speed bound
  instead, and a jump must not make the autopilot snap);
- status changes (pose lost / found) for STATUSTEXT and the log;
- the fused poses of every entity for peers and the ground station, at ``fused_rate_hz``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from atlas_onboard.core.graph import EntityPose, GraphResult
from atlas_onboard.core.records import AutopilotPose
from atlas_onboard.errors import AtlasError

NS = 1_000_000_000


@dataclass(slots=True)
class RateCap:
    """The autopilot's rate cap: at most ``rate_hz`` poses a second on average, and a camera at the
    cap's own rate has every frame sent on arrival, whatever its jitter.

    Two token buckets of ``burst`` tokens. One fills on capture times (a token a period of 1 /
    ``rate_hz`` of the poses' capture stamps): it keeps the average, and since capture times are the
    camera's rhythm its level only wanders by the capture jitter, so a camera at the cap's rate never
    runs it dry, hiccup or not. The other fills on arrival times, ``arrival_margin`` times faster: it
    bounds a flood however its capture times are spread, and regains its burst after a detector's
    hiccup (at exactly the cap's rate it would stay as low as the hiccup left it, and drop a jittered
    frame much later). A new pose goes at once when it
    finds a token and spacing from the last sent pose: a capture time at least ``min_spacing`` of a
    period newer, or an arrival a full period later. Capture times are the camera's rhythm, free of
    the detector's varying time: a camera at the cap's rate passes with capture jitter up to 40 % of
    a period, one at twice the rate has exactly every other frame sent. Without spacing, a spare
    token will do while nothing was refused for ``hold_periods`` (two sources' views in the same
    period, when both together stay under the cap).

    A refused pose is dropped, not delayed until a token is due: that would lock every later frame
    to the phase of one late frame (or of a camera a little faster than the cap), adding up to a
    period of latency to each, differently from run to run. Only if nothing newer has gone
    ``hold_periods`` periods after the refusal does it go then (a sporadic source, whose next pose
    may be far off); a stream faster than the cap brings its next frame sooner.
    """

    rate_hz: float
    min_spacing: float = 0.6
    burst: float = 3.0  # three frames handed over at once (after a detector's hiccup) all go
    hold_periods: float = 2.0
    arrival_margin: float = 1.1
    _tokens: float = 3.0
    _tokens_ns: int | None = None
    _ctokens: float = 3.0  # the capture-time bucket
    _ctokens_us: int | None = None  # the newest capture time it was filled to
    _last_capture_us: int | None = None
    _last_sent_ns: int | None = None
    _held_ns: int | None = None  # when the pose now held back was refused
    _held_capture_us: int | None = None
    _refused_ns: int | None = None  # the last refusal of a new pose

    def __post_init__(self) -> None:
        if not self.rate_hz > 0:
            raise AtlasError(f"rate_hz: expected a rate cap > 0 Hz, got {self.rate_hz}")
        self._tokens = self._ctokens = self.burst

    @property
    def period_ns(self) -> float:
        return NS / self.rate_hz

    @property
    def held_capture_us(self) -> int | None:
        """The capture time of the pose held back, or None."""
        return self._held_capture_us

    def admit(self, capture_time_us: int, now_ns: int) -> bool:
        """Whether a pose may go now (the caller sends it if so). ``capture_time_us``: its capture
        stamp (us), newer than the last one sent; ``now_ns``: now on the monotonic clock (ns). A pose
        asked about again after a refusal goes only at its release time (:meth:`release_ns`)."""
        if self._tokens_ns is not None:
            gained = (now_ns - self._tokens_ns) * self.arrival_margin / self.period_ns
            self._tokens = min(self.burst, self._tokens + gained)
        self._tokens_ns = now_ns
        if self._ctokens_us is None or capture_time_us > self._ctokens_us:
            if self._ctokens_us is not None:
                gained = (capture_time_us - self._ctokens_us) * 1000 / self.period_ns
                self._ctokens = min(self.burst, self._ctokens + gained)
            self._ctokens_us = capture_time_us
        again = capture_time_us == self._held_capture_us
        hold_ns = self.hold_periods * self.period_ns
        release = self._held_ns is not None and now_ns >= self._held_ns + hold_ns
        spare = self._tokens >= 2.0 and (self._refused_ns is None or now_ns - self._refused_ns >= hold_ns)
        spaced = self._last_capture_us is None or (
            not again
            and (
                spare
                or (capture_time_us - self._last_capture_us) * 1000 >= self.min_spacing * self.period_ns
                or now_ns - self._last_sent_ns >= self.period_ns
            )
        )
        # A held pose's release (a sporadic source) needs no capture token: its capture time cannot
        # grow while it waits; what it borrows, the next captures repay.
        if self._tokens >= 1.0 and (release or (spaced and self._ctokens >= 1.0)):
            self._tokens -= 1.0
            self._ctokens = max(self._ctokens - 1.0, -self.burst)
            self._last_capture_us, self._last_sent_ns = capture_time_us, now_ns
            self._held_ns = self._held_capture_us = None
            return True
        if self._held_ns is None:
            self._held_ns = now_ns
        if not again:
            self._refused_ns = now_ns
        self._held_capture_us = capture_time_us
        return False

    def release_ns(self) -> int | None:
        """When the pose held back may go (its fallback time, with a token due by then), or None."""
        if self._held_ns is None or self._tokens_ns is None:
            return None
        at = self._held_ns + self.hold_periods * self.period_ns
        token = self._tokens_ns + max(1.0 - self._tokens, 0.0) * self.period_ns / self.arrival_margin
        return int(max(at, token)) + 1


@dataclass(slots=True)
class Publisher:
    """Publishing decisions for the node of ``entity``."""

    entity: str
    rate_hz: float = 30.0
    fused_rate_hz: float = 5.0
    reset_jump_m: float = 0.5
    # A loss shorter than this (no pose sent for less; the node's edge_timeout) is no re-acquisition: an
    # evaluation that missed the own pose between two frames must not make the autopilot reset its position.
    reset_gap_s: float = 0.25
    reset_counter: int = 0
    has_pose: bool = False
    sent: int = 0
    suppressed_rate: int = 0
    cap: RateCap = field(init=False)
    _last_capture_us: int = -1
    _last_p: np.ndarray | None = None
    _last_fused_ns: int | None = None
    _lost_since_sent: bool = field(default=False)  # said lost, or held for reset_gap_s, since the last sent
    _last_sent_ns: int | None = None

    def __post_init__(self) -> None:
        self.cap = RateCap(self.rate_hz)

    def autopilot(self, result: GraphResult, now_ns: int) -> tuple[AutopilotPose | None, str | None]:
        """The pose to send now (or None) and a status change (``"pose lost"``/``"pose found"``) or None."""
        pose = result.poses.get(self.entity)
        status = None
        if pose is None or not _finite(pose):
            if self.has_pose:
                self.has_pose = False
                self._lost_since_sent = True
                status = "pose lost"
            return None, status
        if not self.has_pose:
            self.has_pose = True
            status = "pose found"
        if pose.capture_time_us <= self._last_capture_us:
            # Nothing new contributed since the last message. Held that long (the gate keeps an
            # estimate while it refuses every candidate), it is a loss the graph did not say.
            if self._last_sent_ns is not None and now_ns - self._last_sent_ns >= self.reset_gap_s * NS:
                self._lost_since_sent = True
            return None, status
        again = pose.capture_time_us == self.cap.held_capture_us
        if not self.cap.admit(pose.capture_time_us, now_ns):
            self.suppressed_rate += not again  # each capture refused counts once, however often asked
            return None, status
        reacquired = (
            self._lost_since_sent
            and self._last_sent_ns is not None
            and now_ns - self._last_sent_ns >= self.reset_gap_s * NS
        )
        jumped = (
            pose.own_view is not False
            and self._last_p is not None
            and float(np.linalg.norm(pose.p_world_m - self._last_p)) > self.reset_jump_m
        )
        if reacquired or jumped:
            self.reset_counter = (self.reset_counter + 1) % 256
        self._lost_since_sent = False
        self._last_sent_ns = now_ns
        self._last_capture_us = pose.capture_time_us
        self._last_p = pose.p_world_m.copy()
        self.sent += 1
        return AutopilotPose(pose, self.reset_counter), status

    def next_autopilot_ns(self) -> int | None:
        """When a pose held back by the rate cap may go (the node publishes then), or None."""
        return self.cap.release_ns()

    def next_fused_ns(self) -> int:
        """When the fused poses go next (0: at once)."""
        return 0 if self._last_fused_ns is None else self._last_fused_ns + int(NS / self.fused_rate_hz)

    def fused_due(self, now_ns: int) -> bool:
        """True when the fused poses of every entity should go to peers now."""
        if self._last_fused_ns is None or now_ns - self._last_fused_ns >= NS / self.fused_rate_hz:
            self._last_fused_ns = now_ns
            return True
        return False


def _finite(pose: EntityPose) -> bool:
    return bool(
        np.all(np.isfinite(pose.p_world_m)) and np.all(np.isfinite(pose.q_world_xyzw)) and np.isfinite(pose.sigma_m)
    )
