"""What the bench check's relay (:mod:`atlas_onboard.mavlink.relay`) keeps of the autopilot link:
plain records, importable without pymavlink (the node's start-up check uses them too)."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field


@dataclass(frozen=True, slots=True)
class VisionSample:
    arrival_s: float  # wall clock (UNIX), as the node's stamps
    usec: int  # the node's capture stamp
    xyz_ned_m: tuple[float, float, float]
    q_ned_frd_wxyz: tuple[float, float, float, float]


@dataclass(frozen=True, slots=True)
class AttitudeSample:
    arrival_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float


@dataclass(frozen=True, slots=True)
class PositionSample:
    arrival_s: float
    xyz_ned_m: tuple[float, float, float]


@dataclass
class Tap:
    """What the relay saw (appended by its thread; read after :meth:`Relay.stop`, or under ``lock``)."""

    vision: list[VisionSample] = field(default_factory=list)
    attitude: list[AttitudeSample] = field(default_factory=list)
    local_position: list[PositionSample] = field(default_factory=list)
    params: dict[str, float] = field(default_factory=dict)
    origin: tuple[float, float, float] | None = None  # lat deg, lon deg, alt m
    autopilot: int | None = None  # HEARTBEAT.autopilot (MAV_AUTOPILOT_PX4 12, ARDUPILOTMEGA 3)
    autopilot_system: int | None = None
    timesync_requests: int = 0  # the autopilot's (tc1 = 0; PX4 asks, the node answers)
    timesync_answers: int = 0  # the node's answers to them
    signed_from_node: int = 0
    unsigned_from_node: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)
