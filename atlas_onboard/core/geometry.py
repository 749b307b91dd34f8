"""Poses on ``scipy.spatial.transform``: construction from user input, and batched array helpers.

A single pose is a scipy ``RigidTransform``. Hot paths (the graph, the listener) keep poses as arrays:
positions ``p`` of shape (N, 3) in metres and quaternions ``q_xyzw`` of shape (N, 4), scalar last as
scipy has them (MAVLink is w-first: such arrays are named ``q_wxyz``).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.errors import GeometryError

UNIT_QUATERNION_TOLERANCE = 1e-3
"""A user-written quaternion whose norm differs from 1 by more than this is rejected, not normalised."""


def as_vector3(value: ArrayLike, name: str = "vector") -> NDArray[np.float64]:
    """A finite float vector of shape (3,), or GeometryError naming what arrived."""
    arr = np.asarray(value, dtype=float)
    if arr.shape != (3,):
        raise GeometryError(f"expected {name} of shape (3,), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise GeometryError(f"expected a finite {name}, got {arr.tolist()}")
    return arr


def rotation_from_wxyz(q_wxyz: Sequence[float], *, strict: bool = True) -> Rotation:
    """Rotation from a w-first quaternion. With ``strict`` a non-unit (beyond 1e-3) or zero one raises."""
    q = np.asarray(q_wxyz, dtype=float)
    if q.shape != (4,):
        raise GeometryError(f"expected a quaternion of shape (4,), got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise GeometryError(f"expected a finite quaternion, got {q.tolist()}")
    norm = float(np.linalg.norm(q))
    if norm < 1e-9:
        raise GeometryError("expected a unit quaternion, got a zero quaternion")
    if strict and abs(norm - 1.0) > UNIT_QUATERNION_TOLERANCE:
        raise GeometryError(f"expected a unit quaternion, got norm {norm:.6g}")
    return Rotation.from_quat(np.roll(q, -1))


def rotation_from_rpy_deg(rpy_deg: Sequence[float]) -> Rotation:
    """Rotation from roll, pitch, yaw in degrees, aerospace order: R = Rz(yaw) * Ry(pitch) * Rx(roll)."""
    rpy = as_vector3(rpy_deg, "roll/pitch/yaw")
    return Rotation.from_euler("ZYX", rpy[::-1], degrees=True)


def rpy_deg(rotation: Rotation) -> NDArray[np.float64]:
    """Roll, pitch, yaw in degrees of a rotation, inverse of :func:`rotation_from_rpy_deg`."""
    return rotation.as_euler("ZYX", degrees=True)[::-1].copy()


def make_pose(p_m: ArrayLike, rotation: Rotation | None = None) -> RigidTransform:
    """A pose from a position in metres and a rotation (identity if None)."""
    rot = Rotation.identity() if rotation is None else rotation
    return RigidTransform.from_components(as_vector3(p_m, "position"), rot)


def pose_arrays(T: RigidTransform) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(p, q_xyzw)`` of a single pose or a stack of poses."""
    return T.translation, T.rotation.as_quat()


def pose_from_arrays(p: ArrayLike, q_xyzw: ArrayLike) -> RigidTransform:
    """A pose (or stack) from positions and x-first quaternions; quaternions are normalised by scipy."""
    return RigidTransform.from_components(np.asarray(p, dtype=float), Rotation.from_quat(q_xyzw))


def compose_arrays(
    p_a: NDArray[np.float64], q_a: NDArray[np.float64], p_b: NDArray[np.float64], q_b: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Batched ``T_a * T_b`` on arrays of shape (N, 3)/(N, 4): one scipy call, no Python loop."""
    R_a = Rotation.from_quat(q_a)
    return p_a + R_a.apply(p_b), (R_a * Rotation.from_quat(q_b)).as_quat()


def quat_multiply(q_a: NDArray[np.float64], q_b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Batched Hamilton product of x-first quaternions, shape (..., 4): the rotation ``R_a * R_b``.

    The same as ``(Rotation.from_quat(q_a) * Rotation.from_quat(q_b)).as_quat()`` for unit inputs
    (tested against it), without scipy's per-call overhead, which dominates on the graph's small
    batches (about 170 us for 100 products against 10 us here).
    """
    a, b = np.asarray(q_a, dtype=float), np.asarray(q_b, dtype=float)
    x1, y1, z1, w1 = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    x2, y2, z2, w2 = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    out = np.empty(np.broadcast_shapes(a.shape, b.shape))
    out[..., 0] = w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2
    out[..., 1] = w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2
    out[..., 2] = w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2
    out[..., 3] = w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2
    return out


def quat_matrix(q_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """Batched rotation matrices of unit x-first quaternions, shape (..., 4) -> (..., 3, 3).

    The same as ``Rotation.from_quat(q).as_matrix()`` for unit inputs (tested against it); the graph
    calls it on every stage of every evaluation.
    """
    q = np.asarray(q_xyzw, dtype=float)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty((*q.shape[:-1], 3, 3))
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    out[..., 0, 0] = 1 - 2 * (yy + zz)
    out[..., 0, 1] = 2 * (xy - wz)
    out[..., 0, 2] = 2 * (xz + wy)
    out[..., 1, 0] = 2 * (xy + wz)
    out[..., 1, 1] = 1 - 2 * (xx + zz)
    out[..., 1, 2] = 2 * (yz - wx)
    out[..., 2, 0] = 2 * (xz - wy)
    out[..., 2, 1] = 2 * (yz + wx)
    out[..., 2, 2] = 1 - 2 * (xx + yy)
    return out


def invert_arrays(
    p: NDArray[np.float64], q_xyzw: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Batched inverse of poses given as arrays."""
    R_inv = Rotation.from_quat(q_xyzw).inv()
    return -R_inv.apply(p), R_inv.as_quat()


def canonical_quat(q_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """The representative of q and -q with w >= 0 (ties broken by the first non-zero component)."""
    q = np.array(q_xyzw, dtype=float)
    flat = q.reshape(-1, 4)
    for row in flat:
        for i in (3, 0, 1, 2):
            if row[i] != 0.0:
                if row[i] < 0.0:
                    row *= -1.0
                break
    return q


def angle_between(r1: Rotation, r2: Rotation) -> float | NDArray[np.float64]:
    """Rotation angle in radians of ``r1^-1 * r2`` (the geodesic distance, sign-of-q independent)."""
    return (r1.inv() * r2).magnitude()


def is_finite_pose(p: ArrayLike, q: ArrayLike) -> bool:
    """True when every component is finite and the quaternion is not zero."""
    p_arr = np.asarray(p, dtype=float)
    q_arr = np.asarray(q, dtype=float)
    return bool(np.all(np.isfinite(p_arr)) and np.all(np.isfinite(q_arr)) and np.linalg.norm(q_arr) > 1e-9)
