"""Frame conventions, each defined once.

Internally atlas-onboard uses one convention: the world frame is ENU (x east, y north, z up, as in ROS
REP-103) and every body frame is FLU (x forward, y left, z up). A world file written in NED/FRD is
normalised to ENU/FLU once, at load. NED/FRD appear again only at the autopilot boundary
(:func:`enu_flu_to_ned_frd`).

Fixed frames:

- camera optical frame (OpenCV): x right, y down, z forward along the optical axis;
- camera *mount* frame: a body frame (FLU or FRD, as the file says) whose x axis is the optical axis,
  so that a camera looking forward from the nose has the identity mount pose;
- marker frame (OpenCV ArUco/AprilTag): origin at the marker centre, x right, y up, z out of the
  printed face, so a marker lying face-up on an ENU floor with identity pose has its x axis east.

``T_a_b`` is the pose of frame b in frame a (it maps points from b into a); ``R_a_b`` likewise.
"""

from __future__ import annotations

from enum import StrEnum

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import geometry


class WorldConvention(StrEnum):
    """Axes of the world frame as written in a world file."""

    ENU = "ENU"
    NED = "NED"


class BodyConvention(StrEnum):
    """Axes of body frames (entities, camera mounts) as written in a world file."""

    FLU = "FLU"
    FRD = "FRD"


# R_ENU_NED maps NED vectors into ENU: e = n_y, n = n_x, u = -n_z. It is its own inverse.
R_ENU_NED = Rotation.from_matrix(np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
# R_FLU_FRD maps FRD vectors into FLU: y and z flip. It is its own inverse.
R_FLU_FRD = Rotation.from_matrix(np.diag([1.0, -1.0, -1.0]))
# Columns are the optical axes (right, down, forward) written in the mount frame.
R_FLU_OPTICAL = Rotation.from_matrix(np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]))
R_FRD_OPTICAL = Rotation.from_matrix(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))

T_ENU_NED = RigidTransform.from_rotation(R_ENU_NED)
T_FLU_FRD = RigidTransform.from_rotation(R_FLU_FRD)


def world_to_enu(T_world_x: RigidTransform, convention: WorldConvention) -> RigidTransform:
    """Re-express a pose given in the file's world frame in the internal ENU world frame."""
    if convention is WorldConvention.ENU:
        return T_world_x
    return T_ENU_NED * T_world_x


def body_to_flu(T_body_x: RigidTransform, convention: BodyConvention) -> RigidTransform:
    """Re-express a pose given in a body frame of the file's convention in the internal FLU frame."""
    if convention is BodyConvention.FLU:
        return T_body_x
    return T_FLU_FRD * T_body_x


def mount_to_optical(T_parent_mount: RigidTransform, convention: BodyConvention) -> RigidTransform:
    """Pose of a camera's optical frame from the pose of its mount frame (x along the optical axis)."""
    R_mount_optical = R_FLU_OPTICAL if convention is BodyConvention.FLU else R_FRD_OPTICAL
    return T_parent_mount * RigidTransform.from_rotation(R_mount_optical)


def enu_flu_to_ned_frd(T_enu_flu: RigidTransform) -> RigidTransform:
    """The autopilot boundary: an ENU-world pose of an FLU body -> the NED-world pose of its FRD body.

    ``T_ned_frd = T_NED_ENU * T_enu_flu * T_FLU_FRD``; a drone at ENU (1, 2, 3) with yaw 90 degrees
    (nose north) becomes NED (2, 1, -3) with yaw 0 (nose north).
    """
    return T_ENU_NED.inv() * T_enu_flu * T_FLU_FRD


_M_NED_ENU = R_ENU_NED.as_matrix().T
# q_ned_frd = q_NED_ENU * q_enu_flu * q_FLU_FRD is linear in q_enu_flu: one constant 4x4 matrix (the
# products of the identity's columns), so the hot path is one matrix product.
_M_Q_NED_FRD = geometry.quat_multiply(
    geometry.quat_multiply(R_ENU_NED.inv().as_quat(), np.eye(4)), R_FLU_FRD.as_quat()
).T


def enu_flu_to_ned_frd_arrays(p_enu_m: np.ndarray, q_enu_flu_xyzw: np.ndarray) -> tuple[np.ndarray, Rotation]:
    """:func:`enu_flu_to_ned_frd` on a position and an x-first quaternion (a 3x3 and a 4x4 product
    instead of RigidTransform objects or scipy's from_matrix, which checks its input for hundreds of
    microseconds)."""
    p_ned, q_ned_frd = enu_flu_to_ned_frd_quat(p_enu_m, q_enu_flu_xyzw)
    return p_ned, Rotation.from_quat(q_ned_frd)


def enu_flu_to_ned_frd_quat(p_enu_m: np.ndarray, q_enu_flu_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`enu_flu_to_ned_frd_arrays` with the attitude as an x-first quaternion (not normalised:
    as unit as its input), for the publishing hot path."""
    return _M_NED_ENU @ np.asarray(p_enu_m, dtype=float), _M_Q_NED_FRD @ np.asarray(q_enu_flu_xyzw, dtype=float)


def ned_frd_to_enu_flu(T_ned_frd: RigidTransform) -> RigidTransform:
    """Inverse of :func:`enu_flu_to_ned_frd`."""
    return T_ENU_NED * T_ned_frd * T_FLU_FRD.inv()
