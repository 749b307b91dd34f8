"""What PX4 and ArduPilot accept, as pure functions: message fields from poses, sigmas and times.

Nothing here imports pymavlink, reads a clock or sends anything: each function returns the fields
of one message as a ``dict`` (keyword arguments of pymavlink's ``MAVLink_<name>_message``), so they
are tested on numbers alone. The facts they follow (from PX4's and ArduPilot's sources; see
docs/px4.md and docs/ardupilot.md):

- VISION_POSITION_ESTIMATE (#102) is local NED, body FRD, ``usec`` the capture time; covariance is
  the upper-right triangle (row-major, states x y z roll pitch yaw) of a 6x6 matrix, with the
  variances at indices 0, 6, 11, 15, 18, 20. Zero is raised to the autopilot's floor and NaN means
  "unknown": neither is sent for a known pose.
- ODOMETRY (#331) with frame_id LOCAL_FRD and child_frame_id BODY_FRD (ArduPilot ignores any other
  pair; PX4 accepts it), estimator_type VISION, quality in percent.
- ``reset_counter`` increments on every jump (pose lost then found, or a step beyond a threshold).
- TIMESYNC: PX4 uses our ``usec`` only once TIMESYNC converges, and converts it with the offset it
  estimates from our ``tc1``; so ``tc1`` must be read from the same clock as the capture times
  (UNIX epoch), or every stamp would be shifted by the difference of the two clocks.

Frames: poses come in as the internal world ENU / body FLU (``T_enu_flu``) and leave through
:func:`atlas_onboard.core.frames.enu_flu_to_ned_frd`, the one tested conversion.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import frames
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink.covariance import (
    _covariance_21,
    _finite,
    quality_percent,
)

MAV_FRAME_LOCAL_NED = 1
MAV_FRAME_BODY_FRD = 12
MAV_FRAME_LOCAL_FRD = 20
MAV_ESTIMATOR_TYPE_VISION = 2
MAV_ESTIMATOR_TYPE_VIO = 3
MAV_TYPE_ONBOARD_CONTROLLER = 18
MAV_AUTOPILOT_INVALID = 8
MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12
MAV_CMD_REQUEST_MESSAGE = 512
MAV_CMD_SET_MESSAGE_INTERVAL = 511
MSG_ATTITUDE = 30
MSG_ATTITUDE_QUATERNION = 31
MSG_LOCAL_POSITION_NED = 32
MSG_GPS_GLOBAL_ORIGIN = 49
MAV_STATE_ACTIVE = 4
MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY = 197


def euler_zyx(q_xyzw: np.ndarray) -> tuple[float, float, float]:
    """(yaw, pitch, roll), intrinsic Z-Y'-X'' (aerospace), of a non-zero x-first quaternion: what
    scipy's ``as_euler("ZYX")`` gives (tested), in scalar math for the publishing hot path."""
    x, y, z, w = (float(v) for v in q_xyzw)
    n = x * x + y * y + z * z + w * w
    # n R[2, 0] = -n sin(pitch); n R[2, 1] and n R[2, 2] = n cos(pitch) (sin, cos)(roll): pitch by atan2
    # keeps its precision next to +-90 degrees, where asin would not. Differences of squares as products
    # of sums and differences: n - 2 (x^2 + y^2) loses n's last bits, which next to the lock (both terms
    # of an atan2 ~cos(pitch)) turn roll and yaw by eps / cos(pitch).
    a, b = 2.0 * (w * x + y * z), (w - y) * (w + y) + (z - x) * (z + x)
    cos_pitch = math.hypot(a, b)
    pitch = math.atan2(2.0 * (w * y - x * z), cos_pitch)
    if cos_pitch <= 1e-12 * n:  # gimbal lock: only yaw -/+ roll is defined; roll 0, as scipy does
        return math.atan2(2.0 * (w * z - x * y), (w - z) * (w + z) + (y - x) * (y + x)), pitch, 0.0
    return math.atan2(2.0 * (w * z + x * y), (w - y) * (w + y) + (x - z) * (x + z)), pitch, math.atan2(a, b)


def _check_pose(p_ned_m: np.ndarray, q_ned_frd_xyzw: np.ndarray, capture_time_us: int) -> None:
    if not (_finite(np.asarray(p_ned_m, dtype=float)) and _finite(q_ned_frd_xyzw)):
        raise AtlasError("expected a finite pose, got NaN or inf")
    if not float(q_ned_frd_xyzw @ q_ned_frd_xyzw) > 1e-12:
        raise AtlasError("expected a rotation, got a zero quaternion")
    if not 0 <= int(capture_time_us) < 2**64:
        raise AtlasError(f"expected a capture time in [0, 2^64) us, got {capture_time_us}")


def vision_position_estimate_from_ned(
    p_ned_m: np.ndarray,
    R_ned_frd: Rotation | np.ndarray,
    capture_time_us: int,
    reset_counter: int,
    covariance_21: Sequence[float],
) -> dict[str, Any]:
    """VISION_POSITION_ESTIMATE fields from a pose already in local NED / body FRD (the attitude as a
    Rotation or an x-first quaternion)."""
    q = R_ned_frd.as_quat() if isinstance(R_ned_frd, Rotation) else np.asarray(R_ned_frd, dtype=float)
    _check_pose(p_ned_m, q, capture_time_us)
    yaw, pitch, roll = euler_zyx(q)  # intrinsic Z-Y'-X'': aerospace yaw, pitch, roll
    return {
        "usec": int(capture_time_us),
        "x": float(p_ned_m[0]),
        "y": float(p_ned_m[1]),
        "z": float(p_ned_m[2]),
        "roll": float(roll),
        "pitch": float(pitch),
        "yaw": float(yaw),
        "covariance": list(covariance_21),
        "reset_counter": int(reset_counter) & 0xFF,
    }


def odometry_from_ned(
    p_ned_m: np.ndarray,
    R_ned_frd: Rotation,
    capture_time_us: int,
    reset_counter: int,
    covariance_21: Sequence[float],
    quality: int,
) -> dict[str, Any]:
    """ODOMETRY fields (LOCAL_FRD / BODY_FRD, VISION, velocity unknown) from a pose in NED / FRD."""
    _check_pose(p_ned_m, R_ned_frd.as_quat(), capture_time_us)
    qx, qy, qz, qw = R_ned_frd.as_quat()
    nan = math.nan
    return {
        "time_usec": int(capture_time_us),
        "frame_id": MAV_FRAME_LOCAL_FRD,
        "child_frame_id": MAV_FRAME_BODY_FRD,
        "x": float(p_ned_m[0]),
        "y": float(p_ned_m[1]),
        "z": float(p_ned_m[2]),
        "q": [float(qw), float(qx), float(qy), float(qz)],
        "vx": nan,
        "vy": nan,
        "vz": nan,
        "rollspeed": nan,
        "pitchspeed": nan,
        "yawspeed": nan,
        "pose_covariance": list(covariance_21),
        "velocity_covariance": [nan] + [0.0] * 20,  # NaN in [0]: velocity unknown
        "reset_counter": int(reset_counter) & 0xFF,
        "estimator_type": MAV_ESTIMATOR_TYPE_VISION,
        "quality": int(quality),
    }


def vision_position_estimate_fields(
    T_enu_flu: RigidTransform,
    capture_time_us: int,
    reset_counter: int,
    sigma_m: float | None = None,
    covariance_enu_flu: np.ndarray | None = None,
) -> dict[str, Any]:
    """VISION_POSITION_ESTIMATE fields of a world ENU / body FLU pose.

    Args:
        T_enu_flu: the body's pose in the world (ENU world, FLU body).
        capture_time_us: capture time of the newest observation that contributed (UNIX epoch, us).
        reset_counter: the current reset counter (core.publisher.Publisher keeps it); sent modulo 256.
        sigma_m: position standard deviation (m); the attitude's follows from it.
        covariance_enu_flu: or a full 6x6 covariance (m^2, rad^2) of x y z in ENU and small
            rotations about the FLU body axes; it wins over ``sigma_m``.

    Raises AtlasError for a non-finite pose or an uncertainty that is missing, non-finite or negative.
    """
    T_ned_frd = frames.enu_flu_to_ned_frd(T_enu_flu)
    cov = _covariance_21(sigma_m, covariance_enu_flu)
    return vision_position_estimate_from_ned(
        T_ned_frd.translation, T_ned_frd.rotation, capture_time_us, reset_counter, cov
    )


def odometry_fields(
    T_enu_flu: RigidTransform,
    capture_time_us: int,
    reset_counter: int,
    sigma_m: float | None = None,
    covariance_enu_flu: np.ndarray | None = None,
    quality: int | None = None,
) -> dict[str, Any]:
    """ODOMETRY fields of a world ENU / body FLU pose (arguments as :func:`vision_position_estimate_fields`;
    ``quality`` in percent, by default from ``sigma_m`` by :func:`quality_percent`, 0 when unknown)."""
    T_ned_frd = frames.enu_flu_to_ned_frd(T_enu_flu)
    cov = _covariance_21(sigma_m, covariance_enu_flu)
    if quality is None:
        quality = quality_percent(sigma_m) if sigma_m is not None else 0
    return odometry_from_ned(T_ned_frd.translation, T_ned_frd.rotation, capture_time_us, reset_counter, cov, quality)


def heartbeat_fields(system_status: int = MAV_STATE_ACTIVE) -> dict[str, Any]:
    """HEARTBEAT of a companion computer: MAV_TYPE_ONBOARD_CONTROLLER, MAV_AUTOPILOT_INVALID, and
    ``system_status`` the own pose's state: MAV_STATE_STANDBY (3) before the first pose,
    MAV_STATE_ACTIVE (4) while a fresh pose goes out, MAV_STATE_CRITICAL (5) once it is lost.

    The system and component ids are the link's (the autopilot's system id, component 197 by default).
    """
    return {
        "type": MAV_TYPE_ONBOARD_CONTROLLER,
        "autopilot": MAV_AUTOPILOT_INVALID,
        "base_mode": 0,
        "custom_mode": 0,
        "system_status": int(system_status),
        "mavlink_version": 3,
    }


TELEMETRY_NAMES = ("atl_sigma", "atl_det_hz", "atl_lat_ms", "atl_peers")
"""NAMED_VALUE_FLOAT names (MAVLink allows 10 characters): the own pose's position sigma (m, NaN
without a pose), the own cameras' observations per second, the mean capture-to-send latency of the
poses sent to the autopilot (ms, NaN when none was sent) and the peers heard within 3 s."""


def telemetry_values(sigma_m: float, detections_hz: float, latency_ms: float, peers: int) -> list[tuple[str, float]]:
    """The (name, value) pairs of the ground-station telemetry, in TELEMETRY_NAMES order."""
    return list(
        zip(TELEMETRY_NAMES, (float(sigma_m), float(detections_hz), float(latency_ms), float(peers)), strict=True)
    )


def timesync_reply(
    tc1: int, ts1: int, now_wall_ns: int, requester: tuple[int, int], own_system: int, target_system: int = 0
) -> dict[str, Any] | None:
    """The answer to a TIMESYNC request, addressed to its sender, or None when there is none to give.

    A request has ``tc1 == 0`` and the sender's time in ``ts1``; the answer echoes ``ts1``, puts our
    time in ``tc1`` (nanoseconds of the clock our ``usec`` stamps use, UNIX epoch: PX4 estimates the
    offset between the two clocks from it) and names the requester (system, component) in its
    target fields. A reply (``tc1 != 0``) or a request addressed to another system than
    ``own_system`` (``target_system`` 0 is a broadcast) is not answered.
    """
    if tc1 != 0 or target_system not in (0, own_system):
        return None
    return {
        "tc1": int(now_wall_ns),
        "ts1": int(ts1),
        "target_system": int(requester[0]) & 0xFF,
        "target_component": int(requester[1]) & 0xFF,
    }


def set_gps_global_origin_fields(
    target_system: int, lat_deg: float, lon_deg: float, alt_m: float, time_usec: int = 0
) -> dict[str, Any]:
    """SET_GPS_GLOBAL_ORIGIN: latitude/longitude in 1e-7 degrees, altitude in mm (AMSL)."""
    for name, value, lo, hi in (("lat_deg", lat_deg, -90.0, 90.0), ("lon_deg", lon_deg, -180.0, 180.0)):
        if not (math.isfinite(value) and lo <= value <= hi):
            raise AtlasError(f"expected {name} in [{lo:g}, {hi:g}] degrees, got {value!r}")
    if not math.isfinite(alt_m):
        raise AtlasError(f"expected a finite alt_m, got {alt_m!r}")
    return {
        "target_system": int(target_system) & 0xFF,
        "latitude": round(lat_deg * 1e7),
        "longitude": round(lon_deg * 1e7),
        "altitude": round(alt_m * 1000.0),
        "time_usec": max(int(time_usec), 0),
    }


def request_message_fields(target_system: int, target_component: int, message_id: int) -> dict[str, Any]:
    """COMMAND_LONG MAV_CMD_REQUEST_MESSAGE: ask the target to send message ``message_id`` once."""
    return {
        "target_system": int(target_system) & 0xFF,
        "target_component": int(target_component) & 0xFF,
        "command": MAV_CMD_REQUEST_MESSAGE,
        "confirmation": 0,
        "param1": float(message_id),
        "param2": 0.0,
        "param3": 0.0,
        "param4": 0.0,
        "param5": 0.0,
        "param6": 0.0,
        "param7": 0.0,
    }


def attitude_level_flu(roll_rad: float, pitch_rad: float, yaw_rad: float) -> Rotation:
    """R_level_body of ATTITUDE's roll, pitch, yaw (rad; body FRD in local NED, aerospace Z-Y'-X''):
    the body FLU in a level ENU frame, ``R_ENU_NED * R_ned_frd * R_FRD_FLU``. Its heading is the
    autopilot's (which may be a compass's): only the up vector it implies is frame-independent.

    Raises AtlasError for a non-finite angle."""
    if not all(math.isfinite(a) for a in (roll_rad, pitch_rad, yaw_rad)):
        raise AtlasError(f"expected finite roll, pitch, yaw, got {(roll_rad, pitch_rad, yaw_rad)!r}")
    R_ned_frd = Rotation.from_euler("ZYX", [yaw_rad, pitch_rad, roll_rad])
    return frames.R_ENU_NED * R_ned_frd * frames.R_FLU_FRD.inv()


def body_rates_flu(rollspeed: float, pitchspeed: float, yawspeed: float) -> NDArray[np.float64] | None:
    """The body's angular rate (3,) rad/s about its FLU axes from ATTITUDE's (or ATTITUDE_QUATERNION's)
    rates about FRD; None when they are not all finite or all exactly zero (an autopilot that does not
    fill them: a real gyro's noise is never zero on three axes at once)."""
    w = (float(rollspeed), float(pitchspeed), float(yawspeed))
    if not all(math.isfinite(v) for v in w) or w == (0.0, 0.0, 0.0):
        return None
    return np.array([w[0], -w[1], -w[2]])


def attitude_quaternion_level_flu(q_wxyz: Sequence[float]) -> Rotation:
    """R_level_body of ATTITUDE_QUATERNION's ``q`` (w, x, y, z; body FRD in local NED), as
    :func:`attitude_level_flu`. Raises AtlasError for a non-finite or zero quaternion."""
    w, x, y, z = (float(v) for v in q_wxyz)
    if not all(math.isfinite(v) for v in (w, x, y, z)) or w * w + x * x + y * y + z * z < 1e-12:
        raise AtlasError(f"expected a finite non-zero quaternion, got {tuple(q_wxyz)!r}")
    return frames.R_ENU_NED * Rotation.from_quat([x, y, z, w]) * frames.R_FLU_FRD.inv()


def odometry_velocity_ned(
    frame_id: int, child_frame_id: int, q_wxyz: Sequence[float], v: Sequence[float], estimator_type: int
) -> NDArray[np.float64] | None:
    """The velocity (m/s) of an autopilot's ODOMETRY in its local frame's axes (x north or the frame's own
    forward, y east or right, z down: the frame of ATTITUDE's heading), from ``v`` (vx vy vz) in
    ``child_frame_id``'s axes: LOCAL_NED or LOCAL_FRD as it is, BODY_FRD turned by ``q`` (w, x, y, z; body FRD
    in ``frame_id``). PX4 streams ODOMETRY from its estimator in LOCAL_NED (LOCAL_FRD without a heading) with
    its velocity in LOCAL_NED, LOCAL_FRD or BODY_FRD. None when the velocity is not all finite or all exactly
    zero (not filled). Raises AtlasError for another frame, or for an external vision's estimate looped back
    (estimator VISION or VIO: our own poses, not the autopilot's)."""
    if estimator_type in (MAV_ESTIMATOR_TYPE_VISION, MAV_ESTIMATOR_TYPE_VIO):
        raise AtlasError(f"ODOMETRY of estimator type {estimator_type} is an external vision's, not the autopilot's")
    if frame_id not in (MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD):
        raise AtlasError(f"expected ODOMETRY in frame LOCAL_NED or LOCAL_FRD, got frame_id {frame_id}")
    vel = np.array([float(a) for a in v])
    if not np.all(np.isfinite(vel)) or not np.any(vel):
        return None
    if child_frame_id in (MAV_FRAME_LOCAL_NED, MAV_FRAME_LOCAL_FRD):
        return vel
    if child_frame_id != MAV_FRAME_BODY_FRD:
        raise AtlasError(f"expected ODOMETRY's velocity in LOCAL_NED, LOCAL_FRD or BODY_FRD, got {child_frame_id}")
    w, x, y, z = (float(a) for a in q_wxyz)
    if not all(math.isfinite(a) for a in (w, x, y, z)) or w * w + x * x + y * y + z * z < 1e-12:
        raise AtlasError(f"expected a finite non-zero quaternion, got {tuple(q_wxyz)!r}")
    return Rotation.from_quat([x, y, z, w]).apply(vel)


def set_message_interval_fields(
    target_system: int, target_component: int, message_id: int, interval_us: int
) -> dict[str, Any]:
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: ask the target to stream ``message_id`` every
    ``interval_us`` microseconds (PX4 and ArduPilot both honour it)."""
    return {
        "target_system": int(target_system) & 0xFF,
        "target_component": int(target_component) & 0xFF,
        "command": MAV_CMD_SET_MESSAGE_INTERVAL,
        "confirmation": 0,
        "param1": float(message_id),
        "param2": float(interval_us),
        "param3": 0.0,
        "param4": 0.0,
        "param5": 0.0,
        "param6": 0.0,
        "param7": 0.0,
    }
