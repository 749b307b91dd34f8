"""A sensor worker: one thread that produces MarkerData and hands each image's detections to a
callback at once (the node's ``Camera`` protocol). Cameras, simulated cameras and the simulated
motion capture derive from it."""

from __future__ import annotations

import threading
from collections.abc import Callable, Sequence

from scipy.spatial.transform import Rotation

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.shutter import BodyRate, BodyVelocity

Deliver = Callable[[Sequence[MarkerData]], None]
"""Called once per image with all of its detections (never with none)."""
AttitudeAt = Callable[[int], Rotation | None]
"""The autopilot's attitude (body FLU in a level ENU frame) at a capture stamp (us), or None."""
RateAt = Callable[[int], BodyRate | None]
"""The autopilot's body angular rate at a capture stamp (us), or None (no rate near it)."""
VelocityAt = Callable[[int], BodyVelocity | None]
"""The autopilot's velocity in the body's axes at a capture stamp (us), or None (none near it)."""


class SensorWorker:
    """Subclasses implement ``_run(deliver)``, returning when ``self._stop`` is set."""

    name: str = "sensor"
    join_timeout_s = 3.0
    attitude_at: AttitudeAt | None = None
    """Set by the node's start-up when the autopilot reports its attitude: cameras predict from it where
    a turn moves the markers (:class:`atlas_onboard.core.attitude.CameraTurn`)."""
    rate_at: RateAt | None = None
    """Set by the node's start-up when the autopilot streams its angular rates: cameras correct a rolling
    shutter's shear by them (:mod:`atlas_onboard.core.shutter`)."""
    velocity_at: VelocityAt | None = None
    """Set by the node's start-up when the autopilot streams its velocity: cameras correct a rolling
    shutter's shear by it (:mod:`atlas_onboard.core.velocity`)."""

    def __init__(self) -> None:
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self, deliver: Deliver) -> None:
        self._thread = threading.Thread(target=self._run, args=(deliver,), name=f"sensor-{self.name}", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=self.join_timeout_s)

    def counters(self) -> dict[str, int]:
        return {}

    def map_pose_changed(self, marker_id: int) -> None:
        """The node's map moved world marker ``marker_id`` from the world file's pose (live refinement):
        a detector that corrects sightings relative to the file stops doing so for it."""

    def take_status(self) -> list[str]:
        """The STATUSTEXT lines to send since the last call (a worker without a detector has none)."""
        return []

    def _run(self, deliver: Deliver) -> None:  # pragma: no cover - abstract
        raise NotImplementedError
