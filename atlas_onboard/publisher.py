"""The graph publisher (the paper's block 3): decides what leaves the node, and when.

Pure: no I/O and no clock (times are passed in as integer nanoseconds of the node's monotonic clock).
The node asks it after every accepted observation and on every tick; it answers with what to send:

- the own entity's pose for the autopilot, only when a newer observation contributed to it (so a
  pose is never sent twice, and never once its edges have expired), at most ``rate_hz``;
- a reset counter that increments when the pose was lost and is found again, or jumps;
- status changes (pose lost / found) for STATUSTEXT and the log;
- the fused poses of every entity for peers and the ground station, at ``fused_rate_hz``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field

import numpy as np

from atlas_onboard.core.graph import EntityPose, GraphResult

NS = 1_000_000_000


@dataclass(frozen=True, slots=True)
class AutopilotPose:
    """A pose to send to the autopilot, with what the message needs beyond the pose itself."""

    pose: EntityPose
    reset_counter: int


class PoseState(enum.IntEnum):
    """The own pose as the ground station sees it: HEARTBEAT ``system_status`` (MAV_STATE)."""

    NONE = 3  # MAV_STATE_STANDBY: no pose yet since the start
    ACTIVE = 4  # MAV_STATE_ACTIVE: a fresh own pose goes to the autopilot
    LOST = 5  # MAV_STATE_CRITICAL: the pose was lost, nothing goes to the autopilot


@dataclass(frozen=True, slots=True)
class Telemetry:
    """What the ground station graphs (NAMED_VALUE_FLOAT, docs/wire-format.md), over the last period.

    ``sigma_m``: the own pose's position sigma (NaN without a pose); ``detections_hz``: the own
    cameras' observations per second; ``latency_ms``: mean capture-to-send time of the poses sent
    to the autopilot, from the stamp they carry (with the EKF, the time predicted for; NaN when none
    was sent).
    """

    sigma_m: float
    detections_hz: float
    latency_ms: float


@dataclass(slots=True)
class Publisher:
    """Publishing decisions for the node of ``entity``."""

    entity: str
    rate_hz: float = 30.0
    fused_rate_hz: float = 5.0
    reset_jump_m: float = 0.5
    reset_counter: int = 0
    has_pose: bool = False
    sent: int = 0
    suppressed_rate: int = 0
    burst: float = 2.0
    _tokens: float = 2.0
    _tokens_ns: int | None = None
    _last_sent_ns: int | None = None
    _last_capture_us: int = -1
    _last_p: np.ndarray | None = None
    _last_fused_ns: int | None = None
    _lost_since_sent: bool = field(default=False)
    _held: bool = False  # a new pose was held back by the rate cap and has not gone since

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
            return None, status  # nothing new contributed since the last message
        if not self._take_token(now_ns):
            self.suppressed_rate += 1
            self._held = True
            return None, status
        self._held = False
        if self._lost_since_sent or (
            self._last_p is not None and float(np.linalg.norm(pose.p_world_m - self._last_p)) > self.reset_jump_m
        ):
            if self._last_p is not None:
                self.reset_counter = (self.reset_counter + 1) % 256
        self._lost_since_sent = False
        self._last_sent_ns = now_ns
        self._last_capture_us = pose.capture_time_us
        self._last_p = pose.p_world_m.copy()
        self.sent += 1
        return AutopilotPose(pose, self.reset_counter), status

    def _take_token(self, now_ns: int) -> bool:
        """Token bucket: at most ``rate_hz`` on average, ``burst`` back to back. A camera at the cap's
        own rate then never waits for its jitter, and a burst of detections cannot flood the autopilot."""
        if self._tokens_ns is not None:
            self._tokens = min(self.burst, self._tokens + (now_ns - self._tokens_ns) * self.rate_hz / NS)
        self._tokens_ns = now_ns
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        return False

    def next_autopilot_ns(self) -> int | None:
        """When a pose held back by the rate cap may go (the node publishes then); None when none is
        held (a node that asked after every step would otherwise publish nothing hundreds of times a
        second once the bucket ran low)."""
        if not self._held or self._tokens_ns is None or self._tokens >= 1.0:
            return None
        return self._tokens_ns + int((1.0 - self._tokens) * NS / self.rate_hz) + 1

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
