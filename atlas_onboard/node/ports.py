"""What the node needs from its MAVLink links and its cameras (the node is in :mod:`atlas_onboard.node`)."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from atlas_onboard.config import WorldConfig
from atlas_onboard.core.attitude import AttitudeHistory
from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.records import AutopilotPose, Inbound, PoseState, Telemetry


class Transport(Protocol):
    """What the node needs from its MAVLink links (implemented in :mod:`atlas_onboard.mavlink`)."""

    def start(self, deliver: Callable[[Sequence[Inbound]], None], may_read: threading.Event | None = None) -> None:
        """Start the receive threads; ``deliver(items)`` with the peer observations of each read (a
        datagram) that passed the checks made before decoding (signature, origin binding, stamp, world
        file); each is decoded and checked further (duplicates, rate) when the node takes it
        (:meth:`Inbound.take`). Peer links read only while ``may_read`` is set (the node holds them
        while it publishes)."""

    def send_observations(self, mds: Sequence[MarkerData]) -> None:
        """Our accepted detections to every peer, together (an image's in one datagram where it fits)."""

    def send_fused(self, poses: Sequence[EntityPose], world: WorldConfig) -> None: ...

    def send_autopilot(self, pose: AutopilotPose) -> None: ...

    def send_status(self, text: str, severity: int) -> None: ...

    def send_landing_target(self, fields: dict[str, Any]) -> None:
        """LANDING_TARGET to the autopilot (the fields of :mod:`atlas_onboard.mavlink.landing`)."""

    def set_pose_state(self, state: PoseState) -> None:
        """The own pose's state, for the HEARTBEAT's system_status."""

    def send_telemetry(self, telemetry: Telemetry) -> None:
        """Graphable values for the ground station (about once a second)."""

    def tick(self, now_ns: int) -> None:
        """Periodic duties (heartbeats, TIMESYNC, origin, reconnects), called by the main loop."""

    @property
    def attitude(self) -> AttitudeHistory | None:
        """The autopilot's attitude history (gravity for a single tag's ambiguity), or None when the
        transport keeps none."""

    def counters(self) -> dict[str, int]: ...

    def close(self) -> None: ...


class Camera(Protocol):
    """A camera worker (implemented in :mod:`atlas_onboard.detector`): frames in, MarkerData out."""

    name: str

    def start(self, deliver: Callable[[Sequence[MarkerData]], None]) -> None:
        """Start the camera's thread; ``deliver(detections)`` once per image, with all of its detections."""

    def stop(self) -> None: ...

    def counters(self) -> dict[str, int]: ...

    def map_pose_changed(self, marker_id: int) -> None:
        """The node's map moved world marker ``marker_id`` from the world file's pose (live refinement)."""

    def take_status(self) -> list[str]:
        """The camera's STATUSTEXT lines since the last call (a marker that disagrees), rate-limited there."""
