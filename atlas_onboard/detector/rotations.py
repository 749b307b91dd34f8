"""One rotation at a time in plain floats: a rotation vector, quaternion (x, y, z, w) or 3x3 matrix into
another, with scipy's ``Rotation`` formulas (its values to a few ulps) without the cost of building a
``Rotation`` for one small matrix, which is most of a marker's pose solve; and quaternions to matrices stacked
with the same arithmetic (:func:`matrices_from_quats`). Other stacked rotations go to scipy."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

SMALL_ANGLE = 1e-3  # below it, the Taylor series of scipy's scale factors (rad)


def quat_from_rotvec(r: NDArray[np.float64]) -> NDArray[np.float64]:
    """``Rotation.from_rotvec(r).as_quat()`` of one rotation vector (3,): (x, y, z, w)."""
    x, y, z = float(r[0]), float(r[1]), float(r[2])
    angle = math.sqrt(x * x + y * y + z * z)
    if angle <= SMALL_ANGLE:
        a2 = angle * angle
        scale = 0.5 - a2 / 48.0 + a2 * a2 / 3840.0
    else:
        scale = math.sin(angle / 2.0) / angle
    return np.array([scale * x, scale * y, scale * z, math.cos(angle / 2.0)])


def matrix_from_quat(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """``Rotation.from_quat(q).as_matrix()`` of one quaternion (x, y, z, w), normalised first."""
    x, y, z, w = (float(v) for v in q)
    n = math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    return np.array(
        [
            [x2 - y2 - z2 + w2, 2.0 * (xy - zw), 2.0 * (xz + yw)],
            [2.0 * (xy + zw), -x2 + y2 - z2 + w2, 2.0 * (yz - xw)],
            [2.0 * (xz - yw), 2.0 * (yz + xw), -x2 - y2 + z2 + w2],
        ]
    )


def matrices_from_quats(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """:func:`matrix_from_quat` of quaternions (M, 4) (x, y, z, w), each normalised first: (M, 3, 3), each
    the same floating-point operations on the same values (so the same bits)."""
    x, y, z, w = (np.ascontiguousarray(c, dtype=np.float64) for c in np.asarray(q).T)
    n = np.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x / n, y / n, z / n, w / n
    x2, y2, z2, w2 = x * x, y * y, z * z, w * w
    xy, zw, xz, yw, yz, xw = x * y, z * w, x * z, y * w, y * z, x * w
    out = np.empty((len(x), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = x2 - y2 - z2 + w2, 2.0 * (xy - zw), 2.0 * (xz + yw)
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = 2.0 * (xy + zw), -x2 + y2 - z2 + w2, 2.0 * (yz - xw)
    out[:, 2, 0], out[:, 2, 1], out[:, 2, 2] = 2.0 * (xz - yw), 2.0 * (yz + xw), -x2 - y2 + z2 + w2
    return out


def quat_from_matrix(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """The unit quaternion (x, y, z, w) of one rotation matrix (3, 3) (Shepperd's method, as scipy's
    ``Rotation.from_matrix``, for a matrix that is a rotation to rounding)."""
    m = [[float(v) for v in row] for row in R]
    trace = m[0][0] + m[1][1] + m[2][2]
    diag = (m[0][0], m[1][1], m[2][2])
    i = max(range(3), key=lambda k: diag[k])
    q = [0.0, 0.0, 0.0, 0.0]
    if trace >= diag[i]:
        q[0], q[1], q[2] = m[2][1] - m[1][2], m[0][2] - m[2][0], m[1][0] - m[0][1]
        q[3] = 1.0 + trace
    else:
        j, k = (i + 1) % 3, (i + 2) % 3
        q[i] = 1.0 - trace + 2.0 * m[i][i]
        q[j] = m[j][i] + m[i][j]
        q[k] = m[k][i] + m[i][k]
        q[3] = m[k][j] - m[j][k]
    n = math.sqrt(q[0] ** 2 + q[1] ** 2 + q[2] ** 2 + q[3] ** 2)
    return np.array([v / n for v in q])


def rotvec_from_quat(q: NDArray[np.float64]) -> NDArray[np.float64]:
    """``Rotation.from_quat(q).as_rotvec()`` of one unit quaternion (x, y, z, w)."""
    x, y, z, w = (float(v) for v in q)
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    angle = 2.0 * math.atan2(math.sqrt(x * x + y * y + z * z), w)
    if angle <= SMALL_ANGLE:
        a2 = angle * angle
        scale = 2.0 + a2 / 12.0 + 7.0 * a2 * a2 / 2880.0
    else:
        scale = angle / math.sin(angle / 2.0)
    return np.array([scale * x, scale * y, scale * z])


def rotvec_from_matrix(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """``Rotation.from_matrix(R).as_rotvec()`` of one rotation matrix (3, 3)."""
    return rotvec_from_quat(quat_from_matrix(R))
