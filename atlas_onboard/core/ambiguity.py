"""Planar-pose ambiguity: which of IPPE's two solutions agrees with the current estimate.

A square marker seen nearly face-on, small or far has two poses that reproject its four corners
almost equally well (IPPE returns both; their error ratio is MarkerData's ``ambiguity_ratio``). The two
share nearly the same position and differ by a rotation, roughly a mirror of the marker's tilt about
the line of sight, so a wrong pick ("flip") is tens of degrees off in attitude and, after eq. 1 inverts
the marker's pose, swings the observer around the marker by range x angle.

The current estimates of the observer and observed entities predict the marker's pose in the sensor
frame (eq. 1 read backwards):

    T_sensor_marker^pred = T_entity_sensor^-1 * T_world_observer^-1 * T_world_observed * T_observed_marker

Rule. Each solution i gets the squared distance to the prediction normalised by the per-axis standard
deviations of the prediction's error (``sigma_rad`` in attitude, ``sigma_m`` in position)::

    r_i^2 = (theta_i / sigma_rad)^2 + (|p_i - p_pred| / sigma_m)^2

with theta_i the angle of R_pred^-1 R_i. For the true solution r^2 is chi-square with 6 degrees of
freedom. The nearer solution is chosen when both hold:

1. it is consistent with the prediction: ``r_near^2 <= gate_r2`` (default 22.46, the 0.999 quantile
   of chi-square(6)); otherwise both are far (the estimate is wrong, or the detection is) -> BOTH_FAR;
2. it is decisively nearer: ``r_far^2 - r_near^2 >= 2 ln(min_likelihood_ratio)`` (default 1000, so
   13.8): under the same Gaussian model the nearer is at least that many times as likely. Two
   solutions closer to each other than about 3.7 sigma cannot pass -> TOO_CLOSE.

Rotation distance is what separates IPPE flips; position rarely does, but it keeps a prediction that
puts the marker in the wrong place from deciding anything (rule 1). Without a prediction nothing is
decided (NO_PREDICTION).

Cover. A pair no prediction decides (TOO_CLOSE, NO_PREDICTION) whose two solutions lie within the
detection's covariance C of each other, ``d^T C^-1 d <= cover_r2`` with d the other solution's offset
``[dp, dtheta]`` (default 22.46, chi-square(6) at 0.999), is one measurement the corners cannot split:
seen face on, the two are mirror tilts of one noisy view, the truth often between them. It is used as
the two solutions' equal mixture, moment-matched: the pose halfway (``d / 2`` along the chosen one's
error vector) with covariance ``C + d d^T / 4`` (each solution one sigma from it along d). A pair
farther apart (a tilted tag's flip: the truth at one of them, the mixture's mean on neither) is still
refused. Pure: numpy and scipy only.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.errors import GeometryError

AMBIGUITY_THRESHOLD = 0.5
"""Above this ratio (chosen over other IPPE reprojection error) the chosen solution may be the flip:
the listener resolves such an observation with the estimates, or rejects it."""
GATE_R2 = 22.46
"""chi-square(6) at 0.999: the nearer solution must lie within this normalised squared distance."""
MIN_LIKELIHOOD_RATIO = 1000.0
"""The nearer solution must be at least this many times as likely as the other."""
COVER_R2 = 22.46
"""chi-square(6) at 0.999: an undecided pair this close in the detection's covariance is covered, not refused."""


class Verdict(StrEnum):
    """The outcome of :func:`resolve` (the value names the listener's counter)."""

    PRIMARY = "primary"  # the detector's chosen solution agrees with the prediction
    ALT = "alt"  # the other solution does: the chosen one was the flip
    NO_PREDICTION = "no_prediction"  # no estimate of the observer or of the observed entity
    BOTH_FAR = "both_far"  # neither solution is consistent with the prediction
    TOO_CLOSE = "too_close"  # both about equally close: the prediction cannot tell them apart

    @property
    def decided(self) -> bool:
        return self in (Verdict.PRIMARY, Verdict.ALT)


@dataclass(frozen=True, slots=True)
class Resolution:
    """A verdict with the normalised squared distances of both solutions (nan without a prediction)."""

    verdict: Verdict
    r2_primary: float
    r2_alt: float


def predict_sensor_marker(
    T_world_observer: RigidTransform,
    T_observer_sensor: RigidTransform,
    T_world_observed: RigidTransform,
    T_observed_marker: RigidTransform,
) -> RigidTransform:
    """The marker's pose in the sensor frame that the estimates predict (eq. 1 read backwards)."""
    return (T_world_observer * T_observer_sensor).inv() * T_world_observed * T_observed_marker


def prediction_sigmas(
    range_m: float | NDArray[np.float64],
    observation_sigma_m: float | NDArray[np.float64],
    observer_sigma_m: float | NDArray[np.float64],
    observed_sigma_m: float | NDArray[np.float64],
    observer_attitude_sigma_rad: float | NDArray[np.float64],
    observed_attitude_sigma_rad: float | NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-axis standard deviations (attitude in rad, position in m) of a solution's distance to the
    prediction: both estimates' errors plus the observation's own.

    The observation's sigma is that of the camera's position relative to the marker, dominated by
    range x attitude error for an ambiguous (near face-on) marker, so its attitude part is taken as
    ``observation_sigma_m / range_m``. The observer's attitude error moves the predicted marker by
    range x angle. Shapes broadcast; every input >= 0, ``range_m`` > 0.
    """
    rng = np.asarray(range_m, dtype=float)
    obs = np.asarray(observation_sigma_m, dtype=float)
    att_a = np.asarray(observer_attitude_sigma_rad, dtype=float)
    att_b = np.asarray(observed_attitude_sigma_rad, dtype=float)
    sigma_rad = np.sqrt(att_a**2 + att_b**2 + (obs / rng) ** 2)
    sigma_m = np.sqrt(
        np.asarray(observer_sigma_m, dtype=float) ** 2
        + np.asarray(observed_sigma_m, dtype=float) ** 2
        + obs**2
        + (rng * att_a) ** 2
    )
    return sigma_rad, sigma_m


@dataclass(frozen=True, slots=True)
class Poses:
    """N poses of a marker in the sensor frame: positions ``p_m`` (N, 3) in metres, x-first quaternions
    ``q_xyzw`` (N, 4)."""

    p_m: NDArray[np.float64]
    q_xyzw: NDArray[np.float64]

    def distances_to(self, other: Poses) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Each pose's rotation angle (rad) and distance (m) from ``other``'s pose of the same index."""
        theta = (Rotation.from_quat(other.q_xyzw).inv() * Rotation.from_quat(self.q_xyzw)).magnitude()
        return theta, np.linalg.norm(np.asarray(self.p_m) - other.p_m, axis=-1)


def resolve_arrays(
    primary: Poses,
    alt: Poses,
    pred: Poses,
    sigma_rad: float | NDArray[np.float64],
    sigma_m: float | NDArray[np.float64],
    gate_r2: float = GATE_R2,
    min_likelihood_ratio: float = MIN_LIKELIHOOD_RATIO,
) -> tuple[list[Verdict], NDArray[np.float64], NDArray[np.float64]]:
    """The rule of this module for N observations at once (one scipy call per step): which of the
    ``primary`` and ``alt`` solutions agrees with the prediction ``pred`` (all in the sensor frame);
    ``sigma_rad`` and ``sigma_m`` scalars or shape (N,), > 0. Returns the verdicts and r^2 of both solutions.
    """
    theta_a, d_a = primary.distances_to(pred)
    theta_b, d_b = alt.distances_to(pred)
    s_rad = np.asarray(sigma_rad, dtype=float)
    s_m = np.asarray(sigma_m, dtype=float)
    r2_a = np.atleast_1d((theta_a / s_rad) ** 2 + (d_a / s_m) ** 2)
    r2_b = np.atleast_1d((theta_b / s_rad) ** 2 + (d_b / s_m) ** 2)
    margin = 2.0 * math.log(min_likelihood_ratio)
    verdicts = []
    for a, b in zip(r2_a.tolist(), r2_b.tolist(), strict=True):
        near, far = (a, b) if a <= b else (b, a)
        if not near <= gate_r2:  # also catches NaN
            verdicts.append(Verdict.BOTH_FAR)
        elif far - near < margin:
            verdicts.append(Verdict.TOO_CLOSE)
        else:
            verdicts.append(Verdict.PRIMARY if a <= b else Verdict.ALT)
    return verdicts, r2_a, r2_b


def resolve(
    T_primary: RigidTransform,
    T_alt: RigidTransform,
    T_pred: RigidTransform | None,
    sigma_rad: float,
    sigma_m: float,
    gate_r2: float = GATE_R2,
    min_likelihood_ratio: float = MIN_LIKELIHOOD_RATIO,
) -> Resolution:
    """Which of two T_sensor_marker solutions agrees with the predicted ``T_pred`` (None: no estimate).

    ``sigma_rad`` and ``sigma_m``: per-axis standard deviations of the prediction's error (see
    :func:`prediction_sigmas`), > 0. The rule is the module's.
    """
    if not (sigma_rad > 0.0 and sigma_m > 0.0):
        raise GeometryError(f"expected sigma_rad > 0 and sigma_m > 0, got {sigma_rad!r} rad, {sigma_m!r} m")
    if T_pred is None:
        return Resolution(Verdict.NO_PREDICTION, math.nan, math.nan)

    def one(T: RigidTransform) -> Poses:
        return Poses(T.translation[None], T.rotation.as_quat()[None])

    verdicts, r2_a, r2_b = resolve_arrays(
        one(T_primary), one(T_alt), one(T_pred), sigma_rad, sigma_m, gate_r2, min_likelihood_ratio
    )
    return Resolution(verdicts[0], float(r2_a[0]), float(r2_b[0]))


@dataclass(frozen=True, slots=True)
class Cover:
    """N undecided pairs as their equal mixture (see the module's Cover): which are close enough
    (``close``, (N,) bool, and ``r2``, each pair's ``d^T C^-1 d``) and, for every pair, the halfway pose
    ``pose`` in the sensor frame and its covariance ``covariance`` (N, 6, 6), meaningful where close."""

    close: NDArray[np.bool_]
    r2: NDArray[np.float64]
    pose: Poses
    covariance: NDArray[np.float64]


def cover(primary: Poses, alt: Poses, C: NDArray[np.float64], cover_r2: float = COVER_R2) -> Cover:
    """The module's Cover of N pairs of T_sensor_marker solutions, ``C`` (N, 6, 6) the detection's
    covariance of ``primary`` (core.covariance convention: dp in the sensor frame, dtheta about the
    marker's axes), taken for both solutions (the two fit the same corners). A covariance that is not
    positive definite closes nothing."""
    R_a = Rotation.from_quat(primary.q_xyzw)
    d = np.concatenate(
        [np.asarray(alt.p_m, dtype=float) - primary.p_m, (R_a.inv() * Rotation.from_quat(alt.q_xyzw)).as_rotvec()],
        axis=-1,
    ).reshape(-1, 6)
    C = np.asarray(C, dtype=float).reshape(-1, 6, 6)
    r2 = np.full(len(d), np.inf)
    for k in range(len(d)):  # a singular one alone keeps inf
        try:
            r2[k] = float(d[k] @ np.linalg.solve(C[k], d[k]))
        except np.linalg.LinAlgError:
            pass
    close = (r2 >= 0.0) & (r2 <= cover_r2)  # NaN and a negative form (indefinite C) close nothing
    half = d / 2.0
    mid_q = (R_a * Rotation.from_rotvec(half[:, 3:])).as_quat()
    pose = Poses(np.asarray(primary.p_m, dtype=float).reshape(-1, 3) + half[:, :3], mid_q.reshape(-1, 4))
    return Cover(close, r2, pose, C + half[:, :, None] * half[:, None, :])
