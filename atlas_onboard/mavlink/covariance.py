"""The covariance of a pose sent to the autopilot: from a sigma or a 6x6 ENU/FLU matrix to MAVLink's 21 NED/FRD
values (floored, checked), and ODOMETRY's quality from it (see :mod:`atlas_onboard.mavlink.autopilot`)."""

from __future__ import annotations

import math

import numpy as np

from atlas_onboard.core import frames
from atlas_onboard.errors import AtlasError

COVARIANCE_DIAGONAL = (0, 6, 11, 15, 18, 20)
"""Indices of the variances of x, y, z, roll, pitch, yaw in a 21-element MAVLink covariance."""
MIN_SIGMA_M = 1e-4
"""Position standard deviations below this are sent as this (0.1 mm): never a zero variance."""
MIN_SIGMA_RAD = 1e-4
"""Attitude standard deviations below this are sent as this."""

# J maps an ENU/FLU 6-vector (position in the world ENU, small rotation about the body FLU axes) to
# NED/FRD: position by R_NED_ENU, rotation by R_FRD_FLU. Covariances transform as J C J^T.
_M_NED_ENU = frames.R_ENU_NED.as_matrix().T
_M_FRD_FLU = frames.R_FLU_FRD.as_matrix().T
_J_NED_FRD_ENU_FLU = np.block([[_M_NED_ENU, np.zeros((3, 3))], [np.zeros((3, 3)), _M_FRD_FLU]])
_ROWS, _COLS = np.triu_indices(6)  # row-major upper triangle: (0,0) (0,1) ... (0,5) (1,1) ... (5,5)
_DIAG = np.arange(6)
_FLOORS = np.array([MIN_SIGMA_M**2] * 3 + [MIN_SIGMA_RAD**2] * 3)


def attitude_sigma_rad(sigma_m: float) -> float:
    """Attitude standard deviation (rad) used when only a position sigma (m) is known.

    A marker pose's angular error scales with its position error over the marker's lever arm; with
    markers of 10-20 cm, 1 cm of position error goes with about 2-3 degrees. Clamped to [1, 30] deg.
    """
    return float(np.clip(sigma_m / 0.25, math.radians(1.0), math.radians(30.0)))


def covariance_from_sigma(sigma_m: float, sigma_att_rad: float | None = None) -> np.ndarray:
    """Diagonal 6x6 covariance (m^2, rad^2) of x y z roll pitch yaw from a position sigma (m).

    Isotropic, so it is the same in ENU/FLU and NED/FRD. Raises AtlasError for a sigma that is not a
    positive finite number: a pose without an honest uncertainty is not sent.
    """
    if not (math.isfinite(sigma_m) and sigma_m > 0.0):
        raise AtlasError(f"expected a position sigma > 0 m, got {sigma_m!r}")
    att = attitude_sigma_rad(sigma_m) if sigma_att_rad is None else sigma_att_rad
    if not (math.isfinite(att) and att > 0.0):
        raise AtlasError(f"expected an attitude sigma > 0 rad, got {att!r}")
    var_p, var_a = max(sigma_m, MIN_SIGMA_M) ** 2, max(att, MIN_SIGMA_RAD) ** 2
    return np.diag([var_p, var_p, var_p, var_a, var_a, var_a])


def covariance_ned_frd(cov_enu_flu: np.ndarray) -> np.ndarray:
    """A 6x6 covariance of (x y z in world ENU, small rotations about body FLU x y z) in NED/FRD.

    ``C_ned_frd = J C J^T`` with J = blockdiag(R_NED_ENU, R_FRD_FLU): position axes swap (east <-> north)
    and up flips; rotations about the body's y and z axes flip sign, which flips the sign of their
    cross terms but never of a variance.
    """
    cov = np.asarray(cov_enu_flu, dtype=float)
    if cov.shape != (6, 6):
        raise AtlasError(f"expected a covariance of shape (6, 6), got shape {cov.shape}")
    if not _finite(cov):
        raise AtlasError("expected a finite covariance, got NaN or inf")
    return _J_NED_FRD_ENU_FLU @ cov @ _J_NED_FRD_ENU_FLU.T


def covariance_upper_triangle(cov: np.ndarray) -> list[float]:
    """The 21 MAVLink covariance values (row-major upper triangle) of a 6x6 covariance, already in NED/FRD.

    Variances (indices 0, 6, 11, 15, 18, 20) are floored at MIN_SIGMA_M^2 / MIN_SIGMA_RAD^2 so none is
    ever zero. Raises AtlasError for a non-finite, asymmetric or negative-variance matrix.
    """
    c = np.asarray(cov, dtype=float)
    if c.shape != (6, 6):
        raise AtlasError(f"expected a covariance of shape (6, 6), got shape {c.shape}")
    if not _finite(c):
        raise AtlasError("expected a finite covariance, got NaN or inf")
    scale = max(float(np.abs(c).max()), 1e-300)
    if float(np.abs(c - c.T).max()) > 1e-9 * scale:
        raise AtlasError("expected a symmetric covariance")
    diag = c.diagonal()
    if float(diag.min()) < 0.0:
        raise AtlasError(f"expected non-negative variances, got {diag.tolist()}")
    c = c.copy()
    c[_DIAG, _DIAG] = np.maximum(diag, _FLOORS)
    return c[_ROWS, _COLS].tolist()


def covariance_21_from_enu_flu(cov_enu_flu: np.ndarray) -> list[float]:
    """``covariance_upper_triangle(covariance_ned_frd(cov))`` in one gather: J is a signed
    permutation, so each NED/FRD triangle entry is one ENU/FLU entry times a sign (tested equal,
    errors included). The publishing hot path."""
    c = np.asarray(cov_enu_flu, dtype=float)
    if c.shape != (6, 6):
        raise AtlasError(f"expected a covariance of shape (6, 6), got shape {c.shape}")
    if not _finite(c):
        raise AtlasError("expected a finite covariance, got NaN or inf")
    flat = c.reshape(36)
    upper, lower = flat[_TRI_FROM_ENU] * _TRI_SIGN, flat[_TRI_FROM_ENU_T] * _TRI_SIGN
    scale = max(float(np.abs(flat).max()), 1e-300)
    if float(np.abs(upper - lower).max()) > 1e-9 * scale:
        raise AtlasError("expected a symmetric covariance")
    diag = upper[_TRI_DIAG]
    if float(diag.min()) < 0.0:
        raise AtlasError(f"expected non-negative variances, got {diag.tolist()}")
    upper[_TRI_DIAG] = np.maximum(diag, _FLOORS)
    return upper.tolist()


def _signed_permutation(J: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    perm = np.abs(J).argmax(axis=1)
    return perm, J[np.arange(len(J)), perm]


_PERM, _SIGN = _signed_permutation(_J_NED_FRD_ENU_FLU)
_TRI_FROM_ENU = _PERM[_ROWS] * 6 + _PERM[_COLS]  # (J C J^T)[r, c] = s_r s_c C[perm_r, perm_c]
_TRI_FROM_ENU_T = _PERM[_COLS] * 6 + _PERM[_ROWS]
_TRI_SIGN = _SIGN[_ROWS] * _SIGN[_COLS]
_TRI_DIAG = np.flatnonzero(_ROWS == _COLS)


def _finite(a: np.ndarray) -> bool:
    """Whether every element is finite (one reduction: a NaN or an infinity makes the sum non-finite;
    so do values near the float's limit, which no pose or covariance has)."""
    return math.isfinite(float(a.sum()))


def quality_percent(sigma_m: float) -> int:
    """ODOMETRY.quality from sigma: 100 at <= 1 cm, falling logarithmically to 1 at >= 50 cm; 0 unknown."""
    if not math.isfinite(sigma_m) or sigma_m <= 0:
        return 0
    q = 100.0 * (1.0 - math.log10(max(sigma_m, 0.01) / 0.01) / math.log10(50.0))
    return int(np.clip(round(q), 1, 100))


def _covariance_21(sigma_m: float | None, covariance_enu_flu: np.ndarray | None) -> list[float]:
    if covariance_enu_flu is not None:
        return covariance_21_from_enu_flu(covariance_enu_flu)
    if sigma_m is None:
        raise AtlasError("expected a sigma or a 6x6 covariance for the pose, got neither")
    return covariance_upper_triangle(covariance_from_sigma(sigma_m))


def quality_from_covariance(cov: np.ndarray) -> int:
    """ODOMETRY.quality (percent) of a pose with a 6x6 covariance (x y z first, m^2): the mapping of
    :func:`quality_percent` applied to the position's standard deviation along its worst direction
    (the square root of the largest eigenvalue of the 3x3 position block). 0 (unknown) for a
    covariance that is not finite or not positive semi-definite; never -1 (failed) for a pose."""
    c = np.asarray(cov, dtype=float)
    if c.shape != (6, 6) or not _finite(c):
        return 0
    worst = float(np.linalg.eigvalsh(0.5 * (c[:3, :3] + c[:3, :3].T))[-1])
    return quality_percent(math.sqrt(worst)) if worst > 0.0 else 0
