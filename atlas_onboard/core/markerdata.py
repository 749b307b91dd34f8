"""MarkerData: one marker seen by one sensor at one instant (the paper's Table 1, plus what a system needs).

The paper's record is ``id, sigma, pos, rot``: the marker's pose in the sensor frame and the sensor's
standard deviation. A running swarm also needs to know which sensor saw it, when the image was
captured, how trustworthy the PnP solution was, and where the record came from.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np


class Rejection(StrEnum):
    """Why an observation was dropped. Every reason has a counter in the listener and the node."""

    NON_FINITE = "non_finite"
    ZERO_QUATERNION = "zero_quaternion"
    BAD_SIGMA = "bad_sigma"
    UNKNOWN_SENSOR = "unknown_sensor"
    UNKNOWN_MARKER = "unknown_marker"
    OWN_MARKER = "own_marker"
    OUT_OF_RANGE = "out_of_range"
    BAD_QUALITY = "bad_quality"
    """A reprojection error that is negative or infinite, or an ambiguity ratio outside [0, 1]
    (NaN, unknown, is fine for both): a broken sender, whose record is not trusted."""
    STALE = "stale"
    DUPLICATE = "duplicate"
    OUTLIER = "outlier"
    AMBIGUOUS = "ambiguous"
    """The two planar solutions fit almost equally well and the record carries no usable other one."""
    BAD_COVARIANCE = "bad_covariance"
    """A detection covariance that is not 21 finite numbers making a positive definite 6x6 matrix
    (:meth:`MarkerData.rejection` checks the numbers and the variances, the listener the rest)."""
    AMBIGUITY_UNRESOLVED = "ambiguity_unresolved"
    """Ambiguous with both solutions, but the current estimates could not say which is right (no
    estimate of the observer or the observed entity, or both solutions far from the prediction, or
    both about as close to it: see :mod:`atlas_onboard.core.ambiguity`)."""
    ATTITUDE_MISMATCH = "attitude_mismatch"
    """Neither of a single tag's two solutions implies the tilt the autopilot reports (see
    :mod:`atlas_onboard.core.attitude`): the detection, not gravity, is wrong."""


MAX_RANGE_M = 1000.0
"""A marker reported farther than this from its sensor is absurd for an indoor swarm; rejected."""
_NAN3 = (math.nan, math.nan, math.nan)
_NAN4 = (math.nan, math.nan, math.nan, math.nan)
MAX_SIGMA_M = 100.0
"""A sigma beyond this says the measurement is worthless (or the sender is broken); rejected."""


@dataclass(frozen=True, slots=True)
class MarkerData:
    """A marker's pose in the sensor's optical frame (OpenCV: x right, y down, z forward).

    Attributes:
        sensor_id: numeric id of the observing sensor (unique in the world file).
        marker_id: id of the observed marker (unique in the world file).
        sigma_m: standard deviation of the measurement, metres (the paper's sigma), > 0.
        p_sensor_marker_m: marker centre in the sensor frame, metres, shape (3,).
        q_sensor_marker_wxyz: marker orientation in the sensor frame, w first as MAVLink sends it.
        capture_time_us: capture time of the image, microseconds on the observer's clock.
        reprojection_error_px: RMS reprojection error of the chosen PnP solution, pixels (nan: unknown).
        ambiguity_ratio: reprojection error of the chosen over the other planar solution, in [0, 1];
            near 1 means the two IPPE solutions fit equally well (a possible flip). nan: unknown.
        origin: system id of the node that produced it (0: this node).
        seq: the producer's sequence number (wraps at 2**16), used with origin to drop duplicates.
        p_sensor_marker_alt_m: the other planar (IPPE) solution's marker centre in the sensor frame,
            metres, shape (3,); all NaN when the producer has none.
        q_sensor_marker_alt_wxyz: the other planar solution's orientation, w first; all NaN when none.
        frame_remaining: how many more observations of the same image (same sensor and capture time)
            follow this one from its producer; 0 for the last one. A receiver evaluates a frame whole:
            a pose fused from part of a frame and the rest of the previous one would mix two instants.
        covariance: the detection's own 6x6 covariance, its upper triangle row by row (21 numbers, the
            order of MAVLink's covariance arrays), or empty when the producer has none. The 6-vector is
            ``[dp, dtheta]`` as everywhere in atlas-onboard (:mod:`atlas_onboard.core.covariance`): the
            marker centre's error in the sensor frame (m) and the marker's rotation error about its own
            axes (rad). It keeps what a scalar sigma loses: a far marker is placed precisely across
            the line of sight and poorly in depth and tilt, and its tilt and the camera's position
            seen from it are correlated. Without it the listener models the covariance from sigma.

    The other solution is auxiliary: the record stands on its primary solution. An alternative that is
    neither all finite nor all NaN (or has a zero quaternion, or is out of range) is unusable: the
    listener ignores it (and counts ``alt_ignored``) rather than rejecting the record, because the
    primary solution was validated on its own; without a usable alternative an ambiguous record is
    then rejected as ``ambiguous``, exactly as a record that never had one.
    """

    sensor_id: int
    marker_id: int
    sigma_m: float
    p_sensor_marker_m: tuple[float, float, float]
    q_sensor_marker_wxyz: tuple[float, float, float, float]
    capture_time_us: int
    reprojection_error_px: float = math.nan
    ambiguity_ratio: float = math.nan
    origin: int = 0
    seq: int = 0
    p_sensor_marker_alt_m: tuple[float, float, float] = _NAN3
    q_sensor_marker_alt_wxyz: tuple[float, float, float, float] = _NAN4
    frame_remaining: int = 0
    covariance: tuple[float, ...] = ()

    def rejection(self) -> Rejection | None:
        """The reason this record is invalid on its own (without a world file), or None if it is valid."""
        x, y, z = self.p_sensor_marker_m
        qw, qx, qy, qz = self.q_sensor_marker_wxyz
        if not _finite((x, y, z, qw, qx, qy, qz, self.sigma_m)):
            return Rejection.NON_FINITE
        if math.fsum((qw * qw, qx * qx, qy * qy, qz * qz)) < 1e-12:
            return Rejection.ZERO_QUATERNION
        if not 0.0 < self.sigma_m <= MAX_SIGMA_M:
            return Rejection.BAD_SIGMA
        if math.sqrt(x * x + y * y + z * z) > MAX_RANGE_M:
            return Rejection.OUT_OF_RANGE
        err, ratio = self.reprojection_error_px, self.ambiguity_ratio
        if not (math.isnan(err) or 0.0 <= err < math.inf) or not (math.isnan(ratio) or 0.0 <= ratio <= 1.0):
            return Rejection.BAD_QUALITY
        if self.covariance and not _plausible_covariance(self.covariance):
            return Rejection.BAD_COVARIANCE
        return None

    def covariance_matrix(self) -> np.ndarray | None:
        """The detection covariance as a symmetric 6x6 array, or None when the record has none."""
        if not self.covariance:
            return None
        return upper_to_matrix(np.asarray(self.covariance, dtype=float))

    def q_sensor_marker_xyzw(self) -> np.ndarray:
        """The quaternion in scipy's order (x, y, z, w)."""
        w, x, y, z = self.q_sensor_marker_wxyz
        return np.array([x, y, z, w])

    def alt_state(self) -> AltState:
        """Whether the record carries the other planar solution, and whether it is usable."""
        values = (*self.p_sensor_marker_alt_m, *self.q_sensor_marker_alt_wxyz)
        if all(math.isnan(v) for v in values):
            return AltState.ABSENT
        if not all(math.isfinite(v) for v in values):
            return AltState.INVALID  # partly NaN, or infinite
        if math.fsum(v * v for v in self.q_sensor_marker_alt_wxyz) < 1e-12:
            return AltState.INVALID
        if math.sqrt(math.fsum(v * v for v in self.p_sensor_marker_alt_m)) > MAX_RANGE_M:
            return AltState.INVALID
        return AltState.VALID

    def q_sensor_marker_alt_xyzw(self) -> np.ndarray:
        """The other solution's quaternion in scipy's order (x, y, z, w)."""
        w, x, y, z = self.q_sensor_marker_alt_wxyz
        return np.array([x, y, z, w])


_UPPER = np.triu_indices(6)
_FULL_FROM_UPPER = np.zeros((6, 6), dtype=int)
_FULL_FROM_UPPER[_UPPER] = np.arange(21)
_FULL_FROM_UPPER.T[_UPPER] = np.arange(21)


def upper_to_matrix(upper: np.ndarray) -> np.ndarray:
    """Symmetric 6x6 matrices from their upper triangles row by row, shape (..., 21) -> (..., 6, 6)."""
    return np.asarray(upper, dtype=float)[..., _FULL_FROM_UPPER]


def matrix_to_upper(C: np.ndarray) -> tuple[float, ...]:
    """The upper triangle of a 6x6 matrix, row by row (MAVLink's covariance order)."""
    return tuple(float(v) for v in np.asarray(C, dtype=float)[_UPPER])


_DIAGONAL = (0, 6, 11, 15, 18, 20)  # the variances' places in the upper triangle


def _plausible_covariance(upper: tuple[float, ...]) -> bool:
    """21 finite numbers with positive variances: what a record can be checked for on its own, in
    plain Python. Whether they make a positive definite matrix the listener checks for a whole batch
    at once (one numpy call: on every received record, a 6x6 factorisation costs tens of microseconds)."""
    if len(upper) != 21 or not all(upper[i] > 0.0 for i in _DIAGONAL):
        return False
    return _finite(upper)


def _finite(values: tuple[float, ...]) -> bool:
    """Whether every number is finite: one sum where that is finite (NaN and inf propagate through
    it), one test per number only where the sum is not (it may overflow from finite terms)."""
    return math.isfinite(sum(values)) or all(math.isfinite(v) for v in values)


class AltState(StrEnum):
    """What a record says about the other planar solution."""

    ABSENT = "absent"  # all NaN: the producer had none (joint solves, non-planar, older senders)
    VALID = "valid"  # all finite, non-zero quaternion, within MAX_RANGE_M
    INVALID = "invalid"  # anything else: ignored (the record stands on its primary solution)
