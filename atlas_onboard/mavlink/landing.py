"""LANDING_TARGET (#149) on the wire: the fields of the one form each autopilot takes, from plain numbers.

- PX4 v1.16 (``handle_message_landing_target``): ``position_valid=1`` with MAV_FRAME_LOCAL_NED only; any
  other frame with a position is refused ("coordinate frame not supported"), without a position the
  angles go the IR-lock way. ``time_usec`` goes through its TIMESYNC (``sync_stamp``).
- ArduPilot ``PLND_TYPE=1``: ``position_valid=1`` with MAV_FRAME_BODY_FRD and ``distance > 0`` (the
  vector is divided by it); the stamp is the arrival time less ``PLND_LAG``. The angles of the same line
  of sight are filled too: they are what it reads when a position is not valid.

Every float goes out as float32; a value that is not finite raises AtlasError (the caller counts it).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

from atlas_onboard.errors import AtlasError

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
LANDING_TARGET_TYPE_VISION_FIDUCIAL = 2


def px4_landing_target_fields(
    time_usec: int, x_m: float, y_m: float, z_m: float, q_wxyz: Sequence[float], target_num: int = 0
) -> dict[str, Any]:
    """The target's position in the vehicle's local NED frame (m) and its FRD orientation (w, x, y, z)."""
    _finite("x y z q", (x_m, y_m, z_m, *q_wxyz))
    return _fields(time_usec, MAV_FRAME_LOCAL_NED, x_m, y_m, z_m, tuple(float(v) for v in q_wxyz), 0.0, 0.0, 0.0,
                   target_num)  # fmt: skip


def ardupilot_landing_target_fields(
    time_usec: int,
    x_m: float,
    y_m: float,
    z_m: float,
    distance_m: float,
    angle_x_rad: float,
    angle_y_rad: float,
    target_num: int = 0,
) -> dict[str, Any]:
    """The target relative to the vehicle in body FRD axes (m), its distance (m, > 0) and line-of-sight angles."""
    _finite("x y z distance angles", (x_m, y_m, z_m, distance_m, angle_x_rad, angle_y_rad))
    if distance_m <= 0.0:
        raise AtlasError(f"LANDING_TARGET: expected a distance > 0 m (ArduPilot drops the rest), got {distance_m}")
    return _fields(time_usec, MAV_FRAME_BODY_FRD, x_m, y_m, z_m, (1.0, 0.0, 0.0, 0.0), distance_m, angle_x_rad,
                   angle_y_rad, target_num)  # fmt: skip


def _fields(
    time_usec: int,
    frame: int,
    x_m: float,
    y_m: float,
    z_m: float,
    q_wxyz: tuple[float, ...],
    distance_m: float,
    angle_x_rad: float,
    angle_y_rad: float,
    target_num: int,
) -> dict[str, Any]:
    if time_usec < 0:
        raise AtlasError(f"LANDING_TARGET: expected a time >= 0 us, got {time_usec}")
    return {
        "time_usec": int(time_usec),
        "target_num": int(target_num) & 0xFF,
        "frame": frame,
        "angle_x": float(angle_x_rad),
        "angle_y": float(angle_y_rad),
        "distance": float(distance_m),
        "size_x": 0.0,
        "size_y": 0.0,
        "x": float(x_m),
        "y": float(y_m),
        "z": float(z_m),
        "q": [float(v) for v in q_wxyz],
        "type": LANDING_TARGET_TYPE_VISION_FIDUCIAL,
        "position_valid": 1,
    }


def _finite(what: str, values: Sequence[float]) -> None:
    if not all(math.isfinite(float(v)) for v in values):
        raise AtlasError(f"LANDING_TARGET: expected finite {what}, got {[float(v) for v in values]}")
