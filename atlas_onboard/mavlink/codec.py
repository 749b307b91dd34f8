"""Encoding and decoding: MarkerData <-> ATLAS_OBSERVATION (and its TUNNEL form), fused poses, and the
external-vision messages PX4 and ArduPilot accept. Decoders never raise anything but RejectionError: a
bad message becomes a counted rejection with a reason (the counter's name)."""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.core import frames
from atlas_onboard.core.graph import EntityPose
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.rejection import Rejection
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink import autopilot
from atlas_onboard.mavlink.covariance import (
    MIN_SIGMA_M,
    covariance_21_from_enu_flu,
    covariance_from_sigma,
    covariance_upper_triangle,
    quality_from_covariance,
    quality_percent,
)

FORMAT_VERSION = 1
TUNNEL_PAYLOAD_OBSERVATION = 43100
TUNNEL_PAYLOAD_MAX = 128
# TUNNEL payload of an observation, little endian, 88 bytes (docs/wire-format.md):
# time_usec u64, fingerprint u32, x y z f32, q[4] f32, sigma f32, reprojection_error f32, ambiguity f32,
# x_alt y_alt z_alt f32, q_alt[4] f32, sensor_id u16, marker_id u16, seq u16, format_version u8,
# then frame_remaining u8 (the extension of ATLAS_OBSERVATION; an 87-byte payload reads it as 0).
TUNNEL_STRUCT = struct.Struct("<QI3f4f3f3f4fHHHB")
TUNNEL_EXTENDED_SIZE = TUNNEL_STRUCT.size + 1
ENTITY_NAME_LEN = 16

MAV_FRAME_LOCAL_FRD = autopilot.MAV_FRAME_LOCAL_FRD
MAV_FRAME_BODY_FRD = autopilot.MAV_FRAME_BODY_FRD
MAV_ESTIMATOR_TYPE_VISION = autopilot.MAV_ESTIMATOR_TYPE_VISION


class RejectionError(AtlasError):
    """A received message that must not reach the graph, and why (its message is the reason's value)."""

    def __init__(self, reason: Rejection) -> None:
        super().__init__(reason.value)
        self.reason = reason


def observation_fields(md: MarkerData, fingerprint: int) -> dict[str, Any]:
    """The ATLAS_OBSERVATION fields of a MarkerData, the other IPPE solution (NaN: none) included."""
    p_alt, q_alt = md.p_sensor_marker_alt_m, md.q_sensor_marker_alt_wxyz
    return {
        "time_usec": int(md.capture_time_us) & 0xFFFFFFFFFFFFFFFF,
        "fingerprint": fingerprint & 0xFFFFFFFF,
        "x": md.p_sensor_marker_m[0],
        "y": md.p_sensor_marker_m[1],
        "z": md.p_sensor_marker_m[2],
        "q": list(md.q_sensor_marker_wxyz),
        "sigma": md.sigma_m,
        "reprojection_error": md.reprojection_error_px,
        "ambiguity": md.ambiguity_ratio,
        "x_alt": p_alt[0],
        "y_alt": p_alt[1],
        "z_alt": p_alt[2],
        "q_alt": list(q_alt),
        "sensor_id": md.sensor_id & 0xFFFF,
        "marker_id": md.marker_id & 0xFFFF,
        "seq": md.seq & 0xFFFF,
        "format_version": FORMAT_VERSION,
        "frame_remaining": min(max(int(md.frame_remaining), 0), 255),
        "covariance": list(md.covariance) if md.covariance else _NO_COVARIANCE,
    }


_NO_COVARIANCE = [0.0] * 21  # none: all zero, which MAVLink 2 cuts from the payload (as a sender without it)


def _covariance(values: Sequence[float] | None) -> tuple[float, ...]:
    """MarkerData.covariance from the wire. None when absent (the TUNNEL form), all 0 (a sender
    without the extension, or without a covariance) or marked unknown (first element NaN, MAVLink's
    way); otherwise the 21 numbers as they came (a bad one is the listener's ``bad_covariance``).
    21 float32 keep the covariance's thin directions (a far marker's lateral offset and tilt
    correlate at 0.98 and more): a compact code of the correlations in int8 made them thousands of
    times too narrow for the simulator's ceiling cameras."""
    if values is None or len(values) != 21:
        return ()
    first = float(values[0])
    if math.isnan(first) or (first == 0.0 and not any(values)):
        return ()
    return tuple(values)


def encode_observation(dialect: ModuleType, md: MarkerData, fingerprint: int) -> Any:
    """An ATLAS_OBSERVATION message object, ready for ``mav.send``."""
    return dialect.MAVLink_atlas_observation_message(**observation_fields(md, fingerprint))


def decode_observation(msg: Any, origin: int, fingerprint: int, check: bool = False) -> MarkerData:
    """MarkerData from an ATLAS_OBSERVATION (or its TUNNEL fields).

    RejectionError (reason ``bad_version``, ``wrong_fingerprint``, ``malformed``) for a message that is
    not a version-1 observation of our world. The other IPPE solution (``x_alt``..``q_alt``) is carried
    as it arrived; its validity is the listener's to judge (an unusable one is ignored there, counted).
    With ``check``, also the record's own validity
    (:meth:`MarkerData.rejection`: ``non_finite``, ``zero_quaternion``, ``bad_sigma``, ``out_of_range``);
    the node leaves that to the listener, which counts those reasons for local and peer records alike.
    """
    if msg.format_version != FORMAT_VERSION:
        raise RejectionError(Rejection.BAD_VERSION)
    if msg.fingerprint != fingerprint & 0xFFFFFFFF:
        raise RejectionError(Rejection.WRONG_FINGERPRINT)
    try:
        q = tuple(map(float, msg.q))  # map, not a generator: this runs for every peer observation
        q_alt = tuple(map(float, msg.q_alt))
        if len(q) != 4 or len(q_alt) != 4:
            raise RejectionError(Rejection.MALFORMED)
        md = MarkerData(
            sensor_id=int(msg.sensor_id),
            marker_id=int(msg.marker_id),
            sigma_m=float(msg.sigma),
            p_sensor_marker_m=(float(msg.x), float(msg.y), float(msg.z)),
            q_sensor_marker_wxyz=q,  # type: ignore[arg-type]  # length checked above
            capture_time_us=int(msg.time_usec),
            reprojection_error_px=float(msg.reprojection_error),
            ambiguity_ratio=float(msg.ambiguity),
            origin=int(origin),
            seq=int(msg.seq),
            p_sensor_marker_alt_m=(float(msg.x_alt), float(msg.y_alt), float(msg.z_alt)),
            q_sensor_marker_alt_wxyz=q_alt,  # type: ignore[arg-type]
            frame_remaining=int(msg.frame_remaining or 0),
            covariance=_covariance(msg.covariance),
        )
    except (TypeError, ValueError, AttributeError):
        raise RejectionError(Rejection.MALFORMED) from None
    if check:
        reason = md.rejection()
        if reason is not None:
            raise RejectionError(reason)
    return md


@dataclass
class _TunnelFields:
    time_usec: int
    fingerprint: int
    x: float
    y: float
    z: float
    q: tuple[float, ...]
    sigma: float
    reprojection_error: float
    ambiguity: float
    x_alt: float
    y_alt: float
    z_alt: float
    q_alt: tuple[float, ...]
    sensor_id: int
    marker_id: int
    seq: int
    format_version: int
    frame_remaining: int = 0
    covariance: tuple[float, ...] | None = None  # the TUNNEL form carries none


def tunnel_payload(md: MarkerData, fingerprint: int) -> bytes:
    """The observation packed for a TUNNEL message (payload_type 43100)."""
    f = observation_fields(md, fingerprint)
    return TUNNEL_STRUCT.pack(
        f["time_usec"], f["fingerprint"], f["x"], f["y"], f["z"], *f["q"], f["sigma"], f["reprojection_error"],
        f["ambiguity"], f["x_alt"], f["y_alt"], f["z_alt"], *f["q_alt"], f["sensor_id"], f["marker_id"], f["seq"],
        f["format_version"],
    ) + bytes([f["frame_remaining"]])  # fmt: skip


def tunnel_fields(md: MarkerData, fingerprint: int) -> dict[str, Any]:
    """The TUNNEL message fields carrying an observation (broadcast, payload zero-padded to 128 bytes)."""
    payload = tunnel_payload(md, fingerprint)
    return {
        "target_system": 0,
        "target_component": 0,
        "payload_type": TUNNEL_PAYLOAD_OBSERVATION,
        "payload_length": len(payload),
        "payload": list(payload) + [0] * (TUNNEL_PAYLOAD_MAX - len(payload)),
    }


def encode_tunnel(dialect: ModuleType, md: MarkerData, fingerprint: int) -> Any:
    """A TUNNEL message object carrying the observation, ready for ``mav.send``."""
    return dialect.MAVLink_tunnel_message(**tunnel_fields(md, fingerprint))


def decode_tunnel(
    payload_type: int, length: int, payload: Sequence[int], origin: int, fingerprint: int, check: bool = False
) -> MarkerData:
    """MarkerData from a TUNNEL message's fields; RejectionError (``tunnel_unknown_type``,
    ``tunnel_bad_length``, then as :func:`decode_observation`) if it is not ours or is malformed."""
    if payload_type != TUNNEL_PAYLOAD_OBSERVATION:
        raise RejectionError(Rejection.TUNNEL_UNKNOWN_TYPE)
    if length not in (TUNNEL_STRUCT.size, TUNNEL_EXTENDED_SIZE) or len(payload) < length:
        raise RejectionError(Rejection.TUNNEL_BAD_LENGTH)
    try:
        raw = bytes(payload[:length])
        v = TUNNEL_STRUCT.unpack(raw[: TUNNEL_STRUCT.size])
    except (struct.error, TypeError, ValueError):
        raise RejectionError(Rejection.TUNNEL_BAD_LENGTH) from None
    remaining = raw[TUNNEL_STRUCT.size] if length == TUNNEL_EXTENDED_SIZE else 0
    fields = _TunnelFields(v[0], v[1], v[2], v[3], v[4], v[5:9], v[9], v[10], v[11], v[12], v[13], v[14], v[15:19],
                           v[19], v[20], v[21], v[22], remaining)  # fmt: skip
    return decode_observation(fields, origin, fingerprint, check)


def fused_fields(pose: EntityPose, entity_index: int, frame_index: int, fingerprint: int) -> dict[str, Any]:
    """ATLAS_FUSED_POSE fields of an entity's pose (ENU world, FLU body; ``frame_index`` 0 = world)."""
    x, y, z, w = pose.q_world_xyzw
    return {
        "time_usec": min(max(int(pose.capture_time_us), 0), 2**64 - 1),
        "fingerprint": fingerprint & 0xFFFFFFFF,
        "x": float(pose.p_world_m[0]),
        "y": float(pose.p_world_m[1]),
        "z": float(pose.p_world_m[2]),
        "q": [float(w), float(x), float(y), float(z)],
        "sigma": float(pose.sigma_m),
        "entity_index": entity_index & 0xFF,
        "frame_index": frame_index & 0xFF,
        "level": min(max(pose.level, 0), 255),
        "n_observations": min(max(pose.n_observations, 0), 255),
        "format_version": FORMAT_VERSION,
        "entity_name": pose.name.encode("ascii", "replace")[:ENTITY_NAME_LEN],
    }


def encode_fused(dialect: ModuleType, pose: EntityPose, entity_index: int, frame_index: int, fingerprint: int) -> Any:
    """An ATLAS_FUSED_POSE message object."""
    return dialect.MAVLink_atlas_fused_pose_message(**fused_fields(pose, entity_index, frame_index, fingerprint))


# --- external vision for the autopilot ----------------------------------------------------------------
# Thin wrappers over the pure field functions of :mod:`atlas_onboard.mavlink.autopilot` and
# :mod:`atlas_onboard.mavlink.covariance`, for the node's EntityPose (position and x-first quaternion
# arrays: the hot path converts with 3x3 products).


def pose_covariance(sigma_m: float, sigma_att_rad: float | None = None) -> list[float]:
    """21-element upper-triangle covariance (x y z roll pitch yaw), variances at 0, 6, 11, 15, 18, 20.

    Never zero and never NaN for a known pose: PX4 would raise zero to its floor, ArduPilot would
    take NaN as "unknown", and both would then ignore the honest uncertainty. A sigma of 0 is sent as
    the floor (0.1 mm); a non-finite or negative sigma raises AtlasError.
    """
    sigma = max(sigma_m, MIN_SIGMA_M) if math.isfinite(sigma_m) and sigma_m >= 0.0 else sigma_m
    return covariance_upper_triangle(covariance_from_sigma(sigma, sigma_att_rad))


def ned_pose(pose: EntityPose) -> tuple[np.ndarray, Rotation]:
    """The autopilot's view: position in local NED and the FRD body's attitude (the one conversion)."""
    return frames.enu_flu_to_ned_frd_arrays(pose.p_world_m, pose.q_world_xyzw)


def _pose_covariance_21(pose: EntityPose) -> list[float]:
    """The propagated 6x6 covariance when the pose has one, else the diagonal from its sigma."""
    if pose.covariance is not None:
        return covariance_21_from_enu_flu(pose.covariance)
    return pose_covariance(pose.sigma_m)


def vision_position_estimate_fields(pose: EntityPose, reset_counter: int) -> dict[str, Any]:
    """VISION_POSITION_ESTIMATE fields: usec = capture time of the newest contributing observation
    (or, with the EKF, the time the pose is predicted for)."""
    p_ned, q_ned_frd = frames.enu_flu_to_ned_frd_quat(pose.p_world_m, pose.q_world_xyzw)
    cov = _pose_covariance_21(pose)
    return autopilot.vision_position_estimate_from_ned(p_ned, q_ned_frd, pose.capture_time_us, reset_counter, cov)


def odometry_fields(pose: EntityPose, reset_counter: int) -> dict[str, Any]:
    """ODOMETRY fields in LOCAL_FRD / BODY_FRD (what ArduPilot requires; PX4 accepts it). Velocity
    (in the body FRD frame, as MAVLink wants it in child_frame_id) and angular rate when a filter
    estimates them, else NaN (unknown)."""
    p_ned, R_ned_frd = ned_pose(pose)
    cov = _pose_covariance_21(pose)
    # quality from the covariance's worst position axis when the pose has one (EKF2_EV_QMIN reads it)
    quality = quality_from_covariance(pose.covariance) if pose.covariance is not None else None
    if not quality:
        quality = quality_percent(pose.sigma_m)
    fields = autopilot.odometry_from_ned(p_ned, R_ned_frd, pose.capture_time_us, reset_counter, cov, quality)
    if pose.velocity_m_s is not None:
        M_frd_ned = R_ned_frd.as_matrix().T
        J_v = M_frd_ned @ _M_NED_ENU  # velocity: world ENU -> body FRD (ODOMETRY's child frame)
        v_frd = J_v @ np.asarray(pose.velocity_m_s, dtype=float)
        rates = pose.angular_rate_rad_s
        w_frd = _FLU_TO_FRD * np.asarray(rates, dtype=float) if rates is not None else np.full(3, math.nan)
        if np.all(np.isfinite(v_frd)):
            fields.update(vx=v_frd[0], vy=v_frd[1], vz=v_frd[2], rollspeed=w_frd[0], pitchspeed=w_frd[1])
            fields["yawspeed"] = w_frd[2]
            if pose.velocity_covariance is not None:
                J = np.zeros((6, 6))
                J[0:3, 0:3] = J_v
                J[3:6, 3:6] = np.diag(_FLU_TO_FRD)
                C = J @ pose.velocity_covariance @ J.T
                cov = covariance_upper_triangle(0.5 * (C + C.T))
                if rates is None:  # rates unknown: their variances NaN, their cross terms 0
                    cov = [
                        math.nan if i in (15, 18, 20) else (0.0 if _ROW[i] >= 3 or _COL[i] >= 3 else v)
                        for i, v in enumerate(cov)
                    ]
                fields["velocity_covariance"] = cov
    return fields


def vision_speed_estimate_fields(pose: EntityPose, reset_counter: int) -> dict[str, Any] | None:
    """VISION_SPEED_ESTIMATE (#103) fields: the velocity in local NED with its 3x3 covariance, or
    None when the pose has no velocity (no filter) or it is not finite."""
    if pose.velocity_m_s is None:
        return None
    v_ned = _M_NED_ENU @ np.asarray(pose.velocity_m_s, dtype=float)
    if not np.all(np.isfinite(v_ned)):
        return None
    if pose.velocity_covariance is not None:
        C = _M_NED_ENU @ pose.velocity_covariance[0:3, 0:3] @ _M_NED_ENU.T
        cov = [float(v) for v in (0.5 * (C + C.T)).reshape(-1)]
    else:
        cov = [math.nan] + [0.0] * 8
    return {
        "usec": int(pose.capture_time_us),
        "x": float(v_ned[0]),
        "y": float(v_ned[1]),
        "z": float(v_ned[2]),
        "covariance": cov,
        "reset_counter": int(reset_counter) & 0xFF,
    }


_M_NED_ENU = frames.R_ENU_NED.as_matrix().T
_FLU_TO_FRD = np.array([1.0, -1.0, -1.0])
_ROW, _COL = np.triu_indices(6)


def vision_position_estimate(dialect: ModuleType, pose: EntityPose, reset_counter: int) -> Any:
    """A VISION_POSITION_ESTIMATE message object; AtlasError for a non-finite pose or sigma."""
    return dialect.MAVLink_vision_position_estimate_message(**vision_position_estimate_fields(pose, reset_counter))


def odometry(dialect: ModuleType, pose: EntityPose, reset_counter: int) -> Any:
    """An ODOMETRY message object; AtlasError for a non-finite pose or sigma."""
    return dialect.MAVLink_odometry_message(**odometry_fields(pose, reset_counter))


def vision_speed_estimate(dialect: ModuleType, pose: EntityPose, reset_counter: int) -> Any | None:
    """A VISION_SPEED_ESTIMATE message object, or None when the pose has no velocity."""
    fields = vision_speed_estimate_fields(pose, reset_counter)
    return None if fields is None else dialect.MAVLink_vision_speed_estimate_message(**fields)
