"""Encoding and decoding: MarkerData <-> ATLAS_OBSERVATION (and its TUNNEL form), fused poses, and the
external-vision messages PX4 and ArduPilot accept. Decoders never raise: a bad message becomes a
counted rejection with a reason."""

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

FORMAT_VERSION = 1
TUNNEL_PAYLOAD_OBSERVATION = 43100
# TUNNEL payload of an observation, little endian, 87 bytes (docs/wire-format.md):
# time_usec u64, fingerprint u32, x y z f32, q[4] f32, sigma f32, reprojection_error f32, ambiguity f32,
# x_alt y_alt z_alt f32, q_alt[4] f32, sensor_id u16, marker_id u16, seq u16, format_version u8.
TUNNEL_STRUCT = struct.Struct("<QI3f4f3f3f4fHHHB")

MAV_FRAME_LOCAL_FRD = 20
MAV_FRAME_BODY_FRD = 12
MAV_ESTIMATOR_TYPE_VISION = 2


class RejectionError(Exception):
    """A received message that must not reach the graph; ``reason`` names the counter."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


def _f32(v: float) -> float:
    return float(np.float32(v))


def observation_fields(
    md: MarkerData, fingerprint: int, alt: tuple[Sequence[float], Sequence[float]] | None = None
) -> dict[str, Any]:
    """The ATLAS_OBSERVATION fields of a MarkerData (``alt``: the other IPPE solution, p and q_wxyz)."""
    nan4 = [math.nan] * 4
    p_alt, q_alt = alt if alt is not None else ([math.nan] * 3, nan4)
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
    }


def encode_observation(dialect: ModuleType, md: MarkerData, fingerprint: int) -> Any:
    """An ATLAS_OBSERVATION message object, ready for ``mav.send``."""
    return dialect.MAVLink_atlas_observation_message(**observation_fields(md, fingerprint))


def decode_observation(msg: Any, origin: int, fingerprint: int) -> MarkerData:
    """MarkerData from an ATLAS_OBSERVATION (or its TUNNEL fields); RejectionError on a wrong version or world."""
    if msg.format_version != FORMAT_VERSION:
        raise RejectionError("bad_version")
    if msg.fingerprint != fingerprint:
        raise RejectionError("wrong_fingerprint")
    q = tuple(float(v) for v in msg.q)
    return MarkerData(
        sensor_id=int(msg.sensor_id),
        marker_id=int(msg.marker_id),
        sigma_m=float(msg.sigma),
        p_sensor_marker_m=(float(msg.x), float(msg.y), float(msg.z)),
        q_sensor_marker_wxyz=(q[0], q[1], q[2], q[3]),
        capture_time_us=int(msg.time_usec),
        reprojection_error_px=float(msg.reprojection_error),
        ambiguity_ratio=float(msg.ambiguity),
        origin=origin,
        seq=int(msg.seq),
    )


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


def tunnel_payload(md: MarkerData, fingerprint: int) -> bytes:
    """The observation packed for a TUNNEL message (payload_type 43100)."""
    f = observation_fields(md, fingerprint)
    return TUNNEL_STRUCT.pack(
        f["time_usec"], f["fingerprint"], f["x"], f["y"], f["z"], *f["q"], f["sigma"], f["reprojection_error"],
        f["ambiguity"], f["x_alt"], f["y_alt"], f["z_alt"], *f["q_alt"], f["sensor_id"], f["marker_id"], f["seq"],
        f["format_version"],
    )  # fmt: skip


def decode_tunnel(payload_type: int, length: int, payload: Sequence[int], origin: int, fingerprint: int) -> MarkerData:
    """MarkerData from a TUNNEL message's fields; RejectionError if it is not ours or is malformed."""
    if payload_type != TUNNEL_PAYLOAD_OBSERVATION:
        raise RejectionError("tunnel_unknown_type")
    if length != TUNNEL_STRUCT.size or len(payload) < length:
        raise RejectionError("tunnel_bad_length")
    v = TUNNEL_STRUCT.unpack(bytes(payload[:length]))
    fields = _TunnelFields(v[0], v[1], v[2], v[3], v[4], v[5:9], v[9], v[10], v[11], v[12], v[13], v[14], v[15:19],
                           v[19], v[20], v[21], v[22])  # fmt: skip
    return decode_observation(fields, origin, fingerprint)


def encode_fused(dialect: ModuleType, pose: EntityPose, entity_index: int, frame_index: int, fingerprint: int) -> Any:
    x, y, z, w = pose.q_world_xyzw
    return dialect.MAVLink_atlas_fused_pose_message(
        time_usec=max(int(pose.capture_time_us), 0),
        fingerprint=fingerprint & 0xFFFFFFFF,
        x=float(pose.p_world_m[0]),
        y=float(pose.p_world_m[1]),
        z=float(pose.p_world_m[2]),
        q=[float(w), float(x), float(y), float(z)],
        sigma=float(pose.sigma_m),
        entity_index=entity_index & 0xFF,
        frame_index=frame_index & 0xFF,
        level=min(pose.level, 255),
        n_observations=min(pose.n_observations, 255),
        format_version=FORMAT_VERSION,
    )


# --- external vision for the autopilot ----------------------------------------------------------------


def attitude_sigma_rad(sigma_m: float) -> float:
    """Attitude standard deviation used when only a position sigma is known.

    A marker pose's angular error scales with its position error over the marker's lever arm; with
    markers of 10-20 cm, 1 cm of position error goes with about 2-3 degrees. Clamped to [1, 30] deg.
    """
    return float(np.clip(sigma_m / 0.25, math.radians(1.0), math.radians(30.0)))


def pose_covariance(sigma_m: float, sigma_att_rad: float | None = None) -> list[float]:
    """21-element upper-triangle covariance (x y z roll pitch yaw), variances at 0, 6, 11, 15, 18, 20.

    Never zero and never NaN for a known pose: PX4 would raise zero to its floor, ArduPilot would
    take NaN as "unknown", and both would then ignore the honest uncertainty.
    """
    var_p = max(sigma_m, 1e-4) ** 2
    var_a = (sigma_att_rad if sigma_att_rad is not None else attitude_sigma_rad(sigma_m)) ** 2
    cov = [0.0] * 21
    for i in (0, 6, 11):
        cov[i] = var_p
    for i in (15, 18, 20):
        cov[i] = var_a
    return cov


def quality_percent(sigma_m: float) -> int:
    """ODOMETRY.quality from sigma: 100 at <= 1 cm, falling logarithmically to 1 at >= 50 cm."""
    if not math.isfinite(sigma_m) or sigma_m <= 0:
        return 0
    q = 100.0 * (1.0 - math.log10(max(sigma_m, 0.01) / 0.01) / math.log10(50.0))
    return int(np.clip(round(q), 1, 100))


def ned_pose(pose: EntityPose) -> tuple[np.ndarray, Rotation]:
    """The autopilot's view: position in local NED and the FRD body's attitude (the one conversion)."""
    return frames.enu_flu_to_ned_frd_arrays(pose.p_world_m, pose.q_world_xyzw)


def vision_position_estimate(dialect: ModuleType, pose: EntityPose, reset_counter: int) -> Any:
    """VISION_POSITION_ESTIMATE: usec = capture time of the newest contributing observation."""
    p_ned, R_ned_frd = ned_pose(pose)
    yaw, pitch, roll = R_ned_frd.as_euler("ZYX")
    x, y, z = p_ned
    return dialect.MAVLink_vision_position_estimate_message(
        usec=int(pose.capture_time_us), x=float(x), y=float(y), z=float(z), roll=float(roll), pitch=float(pitch),
        yaw=float(yaw), covariance=pose_covariance(pose.sigma_m), reset_counter=reset_counter & 0xFF,
    )  # fmt: skip


def odometry(dialect: ModuleType, pose: EntityPose, reset_counter: int) -> Any:
    """ODOMETRY in LOCAL_FRD / BODY_FRD (what ArduPilot requires; PX4 accepts it too), velocity unknown."""
    p_ned, R_ned_frd = ned_pose(pose)
    qx, qy, qz, qw = R_ned_frd.as_quat()
    x, y, z = p_ned
    nan = math.nan
    vel_cov = [nan] + [0.0] * 20
    return dialect.MAVLink_odometry_message(
        time_usec=int(pose.capture_time_us), frame_id=MAV_FRAME_LOCAL_FRD, child_frame_id=MAV_FRAME_BODY_FRD,
        x=float(x), y=float(y), z=float(z), q=[float(qw), float(qx), float(qy), float(qz)], vx=nan, vy=nan, vz=nan,
        rollspeed=nan, pitchspeed=nan, yawspeed=nan, pose_covariance=pose_covariance(pose.sigma_m),
        velocity_covariance=vel_cov, reset_counter=reset_counter & 0xFF, estimator_type=MAV_ESTIMATOR_TYPE_VISION,
        quality=quality_percent(pose.sigma_m),
    )  # fmt: skip
