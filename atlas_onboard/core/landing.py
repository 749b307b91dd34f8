"""Precision landing: whether to tell the autopilot where the landing target is, and in which form.

The target is a point on any entity of the graph (a pad of markers in the world, a rover, another
drone): ``T_target_point`` places it in the entity's body frame (identity: the entity's origin). Its
pose relative to the drone comes from the graph's two world poses, each with its 6x6 covariance in
the convention of :mod:`atlas_onboard.core.covariance` (``[dp in world, dtheta about the body's
axes]``), taken as independent.

What each autopilot takes (LANDING_TARGET, read from their sources):

- PX4 v1.16 (``mavlink_receiver.cpp``): with ``position_valid=1`` only MAV_FRAME_LOCAL_NED, ``x y z``
  the target's position in the vehicle's local NED frame, ``q`` its orientation (w, x, y, z). The
  node's world, turned to NED, is that frame when PX4 fuses the node's pose as its position, yaw and
  height (what ``params`` writes);
- ArduPilot, ``PLND_TYPE=1`` (``AC_PrecLand_MAVLink``/``_Companion``): with ``position_valid=1``
  MAV_FRAME_BODY_FRD, ``x y z`` the target relative to the vehicle in its body axes, and
  ``distance > 0`` (the vector is divided by it); the angles ``angle_x = atan(y / z)``,
  ``angle_y = atan(-x / z)`` carry the same line of sight (``(-tan(angle_y), tan(angle_x), 1)``).

Never a stale, extrapolated or too uncertain target: the decision says why not (:class:`Verdict`).
Everything here is pure: the time is an argument.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.core import frames
from atlas_onboard.core.covariance import skew


class Verdict(StrEnum):
    """Whether a LANDING_TARGET goes out, and if not, why."""

    SEND = "send"
    NO_TARGET = "no_target"  # the graph has no pose of the target entity
    NO_OWN_POSE = "no_own_pose"  # nor of the drone
    STALE = "stale"  # the newest observation behind the relative pose is older than max_age_s
    EXTRAPOLATED = "extrapolated"  # a pose predicted past its newest observation
    UNCERTAIN = "uncertain"  # the landing point's largest horizontal position sigma exceeds max_sigma_m
    NOT_BELOW = "not_below"  # ArduPilot takes only a target below the vehicle (a downward line of sight)


@dataclass(frozen=True, slots=True)
class PoseSample:
    """One entity's world pose as the graph gives it.

    ``p_world_m`` (3,) m and ``q_world_xyzw`` (4,) in the world ENU / body FLU; ``covariance`` (6, 6)
    ``[dp world, dtheta body]`` (None: ``sigma_m`` on every position axis and no attitude error);
    ``stamp_us`` the time the pose is for, ``observed_us`` the capture time of the newest observation
    behind it (the same unless a filter predicted it); ``exact`` for a pose that is known, not observed
    (the world's own frame): it never goes stale; ``velocity_m_s`` (3,) world, when a filter knows it.
    """

    p_world_m: NDArray[np.float64]
    q_world_xyzw: NDArray[np.float64]
    covariance: NDArray[np.float64] | None
    sigma_m: float
    stamp_us: int
    observed_us: int
    exact: bool = False
    velocity_m_s: NDArray[np.float64] | None = None


@dataclass(frozen=True, slots=True)
class Limits:
    """When a target is good enough to land on."""

    max_age_s: float
    max_sigma_m: float


@dataclass(frozen=True, slots=True)
class RelativeTarget:
    """The landing point relative to the drone: ``p_drone_m`` (3,) in the drone's body FLU axes, m;
    ``R_drone_point`` its orientation; ``covariance`` (6, 6) ``[dp drone axes, dtheta point axes]``;
    ``observed_us`` the capture time of the older of the two poses' newest observations (None when
    both are exact)."""

    p_drone_m: NDArray[np.float64]
    R_drone_point: Rotation
    covariance: NDArray[np.float64]
    observed_us: int | None
    extrapolated: bool


@dataclass(frozen=True, slots=True)
class Px4Target:
    """PX4's fields: the point in the vehicle's local NED frame (m) and its FRD orientation (w, x, y, z)."""

    x_m: float
    y_m: float
    z_m: float
    q_wxyz: tuple[float, float, float, float]


@dataclass(frozen=True, slots=True)
class ArduPilotTarget:
    """ArduPilot's fields: the point in the vehicle's body FRD axes (m), its distance (m, > 0) and the
    line-of-sight angles (rad) of the same vector."""

    x_m: float
    y_m: float
    z_m: float
    distance_m: float
    angle_x_rad: float
    angle_y_rad: float


@dataclass(frozen=True, slots=True)
class Decision:
    """What to send (``px4`` and ``ardupilot`` set only with :attr:`Verdict.SEND`), and the figures behind
    it: ``age_s`` of the older observation, ``sigma_m`` the landing point's largest horizontal position
    sigma including the motion since (velocity times age), ``time_usec`` the message's stamp (the capture
    time the relative pose is for)."""

    verdict: Verdict
    age_s: float = math.nan
    sigma_m: float = math.nan
    time_usec: int = 0
    px4: Px4Target | None = None
    ardupilot: ArduPilotTarget | None = None


def relative_target(drone: PoseSample, target: PoseSample, T_target_point: RigidTransform) -> RelativeTarget:
    """The landing point (``T_target_point`` in the target's body frame) relative to the drone, with its
    first-order covariance: ``p = R_d^T (p_t + R_t o - p_d)``; errors ``dp = R_d^T dp_t - R_d^T dp_d +
    [p]x dtheta_d - R_d^T R_t [o]x dtheta_t`` and ``dtheta = R_tp^T (dtheta_t - R_rel^T dtheta_d)``."""
    R_d = Rotation.from_quat(drone.q_world_xyzw).as_matrix()
    R_t = Rotation.from_quat(target.q_world_xyzw).as_matrix()
    o = T_target_point.translation
    R_tp = T_target_point.rotation.as_matrix()
    p = R_d.T @ (target.p_world_m + R_t @ o - drone.p_world_m)
    R_rel = R_d.T @ R_t  # target body in drone body
    C_d, C_t = _covariance(drone), _covariance(target)
    # Jacobians of [dp (drone axes), dtheta (point axes)] by [dp_d, dtheta_d] and by [dp_t, dtheta_t].
    J_d = np.zeros((6, 6))
    J_d[:3, :3] = -R_d.T
    J_d[:3, 3:] = skew(p)
    J_d[3:, 3:] = -R_tp.T @ R_rel.T
    J_t = np.zeros((6, 6))
    J_t[:3, :3] = R_d.T
    J_t[:3, 3:] = -R_rel @ skew(o)
    J_t[3:, 3:] = R_tp.T
    C = J_d @ C_d @ J_d.T + J_t @ C_t @ J_t.T
    observed = [s.observed_us for s in (drone, target) if not s.exact]
    extrapolated = any(s.stamp_us > s.observed_us for s in (drone, target) if not s.exact)
    return RelativeTarget(p, Rotation.from_matrix(R_rel @ R_tp), 0.5 * (C + C.T), min(observed, default=None),
                          extrapolated)  # fmt: skip


def decide(
    drone: PoseSample | None,
    target: PoseSample | None,
    T_target_point: RigidTransform,
    now_us: int,
    limits: Limits,
) -> Decision:
    """Whether a LANDING_TARGET may go out at ``now_us`` (the clock the poses' stamps are on), and its
    fields for PX4 and ArduPilot. The motion since the capture time widens the uncertainty when the
    target's velocity is known (``|v| * age``, in quadrature): it is never extrapolated."""
    if target is None:
        return Decision(Verdict.NO_TARGET)
    if drone is None:
        return Decision(Verdict.NO_OWN_POSE)
    rel = relative_target(drone, target, T_target_point)
    if rel.extrapolated:
        return Decision(Verdict.EXTRAPOLATED)
    age_s = 0.0 if rel.observed_us is None else max(0.0, (now_us - rel.observed_us) * 1e-6)
    finite = bool(np.all(np.isfinite(rel.covariance)) and np.all(np.isfinite(rel.p_drone_m)))
    sigma = horizontal_sigma_m(rel.covariance[:3, :3], Rotation.from_quat(drone.q_world_xyzw)) if finite else math.nan
    if target.velocity_m_s is not None and not target.exact:
        sigma = math.hypot(sigma, float(np.linalg.norm(target.velocity_m_s)) * age_s)
    stamp = now_us if rel.observed_us is None else rel.observed_us
    if age_s > limits.max_age_s:
        return Decision(Verdict.STALE, age_s, sigma, stamp)
    if not sigma <= limits.max_sigma_m:  # NaN too: an unknown uncertainty is not small enough
        return Decision(Verdict.UNCERTAIN, age_s, sigma, stamp)
    ardupilot = ardupilot_fields(rel.p_drone_m)
    if ardupilot is None:
        return Decision(Verdict.NOT_BELOW, age_s, sigma, stamp)
    px4 = px4_fields(drone, rel)
    return Decision(Verdict.SEND, age_s, sigma, stamp, px4, ardupilot)


def horizontal_sigma_m(C_drone: NDArray[np.float64], R_world_drone: Rotation) -> float:
    """The largest standard deviation of a position covariance (drone axes, (3, 3) m^2) over the world's
    horizontal directions: where the autopilots centre (each descends on its own height)."""
    R = R_world_drone.as_matrix()
    C = (R @ C_drone @ R.T)[:2, :2]
    return math.sqrt(max(float(np.linalg.eigvalsh(C).max()), 0.0))


def px4_fields(drone: PoseSample, rel: RelativeTarget) -> Px4Target:
    """The landing point in the local NED frame (the world's, turned): the drone's world position plus the
    relative vector in world axes, and the point's FRD orientation in NED."""
    R_wd = Rotation.from_quat(drone.q_world_xyzw)
    p_world = drone.p_world_m + R_wd.apply(rel.p_drone_m)
    T = frames.enu_flu_to_ned_frd(RigidTransform.from_components(p_world, R_wd * rel.R_drone_point))
    x, y, z = (float(v) for v in T.translation)
    qx, qy, qz, qw = T.rotation.as_quat(canonical=True)
    return Px4Target(x, y, z, (float(qw), float(qx), float(qy), float(qz)))


def ardupilot_fields(p_drone_flu_m: NDArray[np.float64]) -> ArduPilotTarget | None:
    """The landing point relative to the vehicle in body FRD axes, its distance and line-of-sight angles;
    None when it is not below the vehicle (FRD z <= 0: ArduPilot refuses a vector that does not point
    along its downward camera's approach)."""
    x, y, z = (float(v) for v in frames.R_FLU_FRD.inv().apply(np.asarray(p_drone_flu_m, dtype=float)))
    if z <= 0.0:
        return None
    return ArduPilotTarget(x, y, z, math.sqrt(x * x + y * y + z * z), math.atan(y / z), math.atan(-x / z))


def _covariance(s: PoseSample) -> NDArray[np.float64]:
    if s.exact:
        return np.zeros((6, 6))
    if s.covariance is not None:
        return np.asarray(s.covariance, dtype=float)
    C = np.zeros((6, 6))
    C[:3, :3] = np.eye(3) * s.sigma_m**2
    return C
