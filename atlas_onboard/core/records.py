"""The records the node and its transport exchange, below both (the transport knows neither the publisher's
policy nor the node's scheduling): a peer's observation as delivered (:class:`Inbound`), the pose for the
autopilot (:class:`AutopilotPose`), the own pose's state (:class:`PoseState`) and the telemetry
(:class:`Telemetry`)."""

from __future__ import annotations

import enum
from collections.abc import Callable
from dataclasses import dataclass

from atlas_onboard.core.graph import EdgeKey, EntityPose
from atlas_onboard.core.markerdata import MarkerData

ImageKey = tuple[int, int, int]  # a peer's image: (origin system id, sensor id, capture time in us)


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


@dataclass(slots=True, eq=False)
class Inbound:
    """A peer's observation as the transport delivers it: its sender (system id), edge, capture time
    and place in its image read from the frame, when it arrived, and :meth:`take`, which gives the checked
    MarkerData (decoded and checked at the first call, in the caller's thread; None if refused,
    counted by the transport). One that is never taken is never decoded."""

    origin: int
    sensor_id: int
    marker_id: int
    capture_time_us: int
    frame_remaining: int
    arrival_ns: int
    _admit: Callable[[], MarkerData | None] | None
    _md: MarkerData | None = None

    @classmethod
    def of(cls, md: MarkerData, arrival_ns: int) -> Inbound:
        """One already decoded and checked."""
        item = cls(md.origin, md.sensor_id, md.marker_id, md.capture_time_us, md.frame_remaining, arrival_ns, _none)
        item._admit, item._md = None, md
        return item

    @property
    def edge(self) -> EdgeKey:
        return (self.sensor_id, self.marker_id)

    @property
    def image(self) -> ImageKey:
        return (self.origin, self.sensor_id, self.capture_time_us)

    def take(self) -> MarkerData | None:
        """The checked observation, or None if it is refused (decided once)."""
        admit = self._admit
        if admit is not None:
            self._admit = None
            self._md = admit()
        return self._md


def _none() -> None:
    return None
