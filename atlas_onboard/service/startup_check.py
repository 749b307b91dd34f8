"""The bench checks once at service start: the poses the node sends in its first seconds against the
autopilot's attitude, judged as ``atlas-onboard preflight`` judges them, logged and sent as STATUSTEXT.

Non-blocking: the transport (:class:`CheckedTransport`) keeps each pose it sends with the autopilot's
attitude at its capture time, and once :data:`WINDOW_S` have passed since the first pose it judges
them (a few milliseconds, once) and stops keeping. Without ATTITUDE from the autopilot the attitude
check says SKIP. The parameter, TIMESYNC, origin and LOCAL_POSITION_NED checks need the relay of
``atlas-onboard preflight``: not here.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.config import NodeConfig, WorldConfig
from atlas_onboard.core import frames
from atlas_onboard.core.records import AutopilotPose
from atlas_onboard.mavlink.samples import AttitudeSample, VisionSample
from atlas_onboard.mavlink.transport import MavlinkTransport
from atlas_onboard.preflight.checks import Check, Verdict, check_attitude, check_rate, optical_axes_frd

_logger = logging.getLogger(__name__)

WINDOW_S = 10.0
MAV_SEVERITY_WARNING, MAV_SEVERITY_INFO = 4, 6


class StartupCheck:
    """Collects the first :data:`WINDOW_S` of poses with the autopilot's attitude, then judges them once."""

    def __init__(self, world: WorldConfig, entity: str, window_s: float = WINDOW_S) -> None:
        self.axes = optical_axes_frd(world, entity)
        self.window_s = window_s
        self.vision: list[VisionSample] = []
        self.attitude: list[AttitudeSample] = []
        self.done = False

    def add(self, pose: AutopilotPose, R_level_flu: Rotation | None, now_s: float) -> list[Check] | None:
        """Keep one sent pose (ENU/FLU) and the autopilot's attitude at its capture time (body FLU in a
        level ENU frame); the checks once the window has passed, else None."""
        if self.done:
            return None
        p = pose.pose
        _, R_vis = frames.enu_flu_to_ned_frd_arrays(np.asarray(p.p_world_m), np.asarray(p.q_world_xyzw))
        x, y, z, w = R_vis.as_quat()
        self.vision.append(VisionSample(now_s, int(p.capture_time_us), (0.0, 0.0, 0.0), (w, x, y, z)))
        if R_level_flu is not None:
            R_ap = frames.R_ENU_NED.inv() * R_level_flu * frames.R_FLU_FRD
            yaw, pitch, roll = R_ap.as_euler("ZYX")
            self.attitude.append(AttitudeSample(now_s - 1e-6, roll, pitch, yaw))
        if now_s - self.vision[0].arrival_s < self.window_s:
            return None
        self.done = True
        checks = [check_rate(self.vision, now_s - self.vision[0].arrival_s, None)]
        checks += check_attitude(self.vision, self.attitude, self.axes)
        self.vision, self.attitude = [], []
        return checks


class CheckedTransport(MavlinkTransport):
    """The node's transport, judging its first seconds of poses against the autopilot's attitude."""

    def __init__(self, world: WorldConfig, config: NodeConfig) -> None:
        super().__init__(world, config)
        self.startup = StartupCheck(world, config.entity)

    def send_autopilot(self, pose: AutopilotPose) -> None:
        super().send_autopilot(pose)
        if self.startup.done:
            return
        checks = self.startup.add(pose, self.attitude_at(int(pose.pose.capture_time_us)), time.time())
        for c in checks or ():
            failed = c.verdict is Verdict.FAIL
            _logger.log(logging.WARNING if failed else logging.INFO, "startup check: %s", c.line())
            if c.verdict is not Verdict.PASS:
                text = f"atlas {c.verdict.value} {c.name}: {c.short or c.detail}"  # 50 characters go out
                self.send_status(text, MAV_SEVERITY_WARNING if failed else MAV_SEVERITY_INFO)
