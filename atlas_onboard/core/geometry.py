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


def _bilinear(terms: dict[int, Sequence[tuple[float, int, int]]], size: int) -> NDArray[np.float64]:
    """A (16, size) matrix K such that ``outer(a, b).reshape(16) @ K`` gives each output k as the sum
    of ``c * a[i] * b[j]`` over ``terms[k]``: a bilinear map of two quaternions as one product."""
    K = np.zeros((16, size))
    for k, rows in terms.items():
        for c, i, j in rows:
            K[4 * i + j, k] += c
    return K


_X, _Y, _Z, _W = 0, 1, 2, 3
# Hamilton product of x-first quaternions: out = a * b.
_K_MULTIPLY = _bilinear(
    {
        0: ((1, _W, _X), (1, _X, _W), (1, _Y, _Z), (-1, _Z, _Y)),
        1: ((1, _W, _Y), (-1, _X, _Z), (1, _Y, _W), (1, _Z, _X)),
        2: ((1, _W, _Z), (1, _X, _Y), (-1, _Y, _X), (1, _Z, _W)),
        3: ((1, _W, _W), (-1, _X, _X), (-1, _Y, _Y), (-1, _Z, _Z)),
    },
    4,
)
# Rotation matrix of a unit x-first quaternion q (row-major), from the products q_i q_j.
_K_MATRIX = _bilinear(
    {
        0: ((1, _W, _W), (1, _X, _X), (-1, _Y, _Y), (-1, _Z, _Z)),
        1: ((2, _X, _Y), (-2, _W, _Z)),
        2: ((2, _X, _Z), (2, _W, _Y)),
        3: ((2, _X, _Y), (2, _W, _Z)),
        4: ((1, _W, _W), (-1, _X, _X), (1, _Y, _Y), (-1, _Z, _Z)),
        5: ((2, _Y, _Z), (-2, _W, _X)),
        6: ((2, _X, _Z), (-2, _W, _Y)),
        7: ((2, _Y, _Z), (2, _W, _X)),
        8: ((1, _W, _W), (-1, _X, _X), (-1, _Y, _Y), (1, _Z, _Z)),
    },
    9,
)


def quat_multiply(q_a: NDArray[np.float64], q_b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Batched Hamilton product of x-first quaternions, shape (..., 4): the rotation ``R_a * R_b``.

    The same as ``(Rotation.from_quat(q_a) * Rotation.from_quat(q_b)).as_quat()`` for unit inputs
    (tested against it), without scipy's per-call overhead, which dominates on the graph's small
    batches: the product is bilinear, so it is one outer product and one matrix product (two numpy
    calls, whatever the batch).
    """
    a, b = np.asarray(q_a, dtype=float), np.asarray(q_b, dtype=float)
    outer = a[..., :, None] * b[..., None, :]
    return outer.reshape(*outer.shape[:-2], 16) @ _K_MULTIPLY


def quat_matrix(q_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """Batched rotation matrices of unit x-first quaternions, shape (..., 4) -> (..., 3, 3).

    The same as ``Rotation.from_quat(q).as_matrix()`` for unit inputs (tested against it); the graph
    calls it on every stage of every evaluation (each entry is quadratic in q: one outer product and
    one matrix product).
    """
    q = np.asarray(q_xyzw, dtype=float)
    outer = q[..., :, None] * q[..., None, :]
    return (outer.reshape(*q.shape[:-1], 16) @ _K_MATRIX).reshape(*q.shape[:-1], 3, 3)


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
