"""The node's landing target: after each evaluation, a LANDING_TARGET to the autopilot when the decision
(:mod:`atlas_onboard.core.landing`) allows one, at most ``rate_hz``, each for a newer observation than
the last (a repeated pose would reach the autopilot as a new measurement of an old position).

The node calls :meth:`LandingOutput.update` with the graph's result (poses at their capture times,
never the EKF's predictions); this module owns the setting, the rate, the counts and the log lines.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np
from scipy.spatial.transform import RigidTransform

from atlas_onboard.config import WORLD, LandingConfig, NodeConfig, WorldConfig
from atlas_onboard.core import frames
from atlas_onboard.core.ekfbank import EkfBank
from atlas_onboard.core.graph import EntityPose, GraphResult
from atlas_onboard.core.landing import Decision, Limits, PoseSample, Verdict, decide
from atlas_onboard.errors import AtlasError
from atlas_onboard.mavlink.landing import ardupilot_landing_target_fields, px4_landing_target_fields

_logger = logging.getLogger(__name__)

NS = 1_000_000_000
# The world's frame in itself: exact, never stale.
WORLD_POSE = PoseSample(np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), None, 0.0, 0, 0, exact=True)


def landing_point(config: LandingConfig, world: WorldConfig) -> RigidTransform:
    """``T_target_point``: the landing point in the target's internal frame (ENU world, FLU body): the
    marker's pose times ``point_m`` in its frame, or ``point_m`` in the file's axes turned to the internal ones."""
    point = (0.0, 0.0, 0.0) if config.point_m is None else config.point_m
    if config.marker is not None:
        return world.markers[config.marker].T_entity_marker * RigidTransform.from_translation(point)
    if config.target == WORLD:
        R = frames.R_ENU_NED if world.world_convention is frames.WorldConvention.NED else None
    else:
        R = frames.R_FLU_FRD if world.body_convention is frames.BodyConvention.FRD else None
    return RigidTransform.from_translation(point if R is None else R.apply(point))


def pose_sample(pose: EntityPose | None, velocity_m_s: np.ndarray | None = None) -> PoseSample | None:
    """The decision's view of a graph pose (a world pose; a pose relative to another entity is none),
    with the entity's world velocity when a filter knows it."""
    if pose is None or pose.frame != WORLD:
        return None
    return PoseSample(
        p_world_m=pose.p_world_m,
        q_world_xyzw=pose.q_world_xyzw,
        covariance=pose.covariance,
        sigma_m=pose.sigma_m,
        stamp_us=pose.capture_time_us,
        observed_us=pose.capture_time_us,
        exact=pose.name == WORLD,
        velocity_m_s=velocity_m_s if velocity_m_s is not None else pose.velocity_m_s,
    )


class LandingLink(Protocol):
    """Where LANDING_TARGET goes: the node's autopilot link."""

    def send_landing_target(self, fields: dict[str, Any]) -> None: ...


def landing_output(config: NodeConfig, world: WorldConfig, link: LandingLink) -> LandingOutput | None:
    """The node's landing output, when it has a ``landing`` section and an autopilot."""
    if config.landing is None or config.autopilot is None:
        return None
    return LandingOutput(config.landing, config.entity, world, link.send_landing_target)


class LandingOutput:
    """Sends LANDING_TARGET for one node (``send`` takes the message's fields)."""

    def __init__(
        self, config: LandingConfig, entity: str, world: WorldConfig, send: Callable[[dict[str, Any]], None]
    ) -> None:
        self.config = config
        self.entity = entity
        self.send = send
        self.limits = Limits(config.max_age_s, config.max_sigma_m)
        self.T_target_point = landing_point(config, world)
        self.counts: Counter[str] = Counter()  # verdicts, "sent", "repeat" (no newer observation), "encode_errors"
        self.last: Decision | None = None
        self._next_ns = 0
        self._last_stamp_us = -1
        self._sending = False

    def update(
        self, result: GraphResult | None, now_ns: int, wall_us: int, ekf: EkfBank | None = None
    ) -> Decision | None:
        """After an evaluation: decide at ``wall_us`` (the clock of the poses' stamps) and send when due.
        With the node's ``ekf`` (``fusion.filter: ekf``), the target's filter is fed too and its velocity
        widens the uncertainty by the motion since capture; positions stay the graph's. Returns the
        decision taken (None when not due: the rate)."""
        if result is None:
            return None
        if ekf is not None and self.config.target != WORLD:
            ekf.update(result, wall_us, only=self.config.target)  # every evaluation: the filter misses none
        if now_ns < self._next_ns:
            return None
        drone = pose_sample(result.poses.get(self.entity))
        if self.config.target == WORLD:
            target = WORLD_POSE
        else:
            target = pose_sample(result.poses.get(self.config.target), _velocity(ekf, self.config.target, wall_us))
        d = decide(drone, target, self.T_target_point, wall_us, self.limits)
        self.last = d
        self.counts[d.verdict.value] += 1
        self._say(d)
        if d.verdict is not Verdict.SEND:
            return d
        if d.time_usec <= self._last_stamp_us:
            self.counts["repeat"] += 1
            return d
        try:
            fields = _fields(self.config.autopilot, d)
        except AtlasError as exc:
            self.counts["encode_errors"] += 1
            _logger.debug("landing target not encoded: %s", exc)
            return d
        if fields is None:
            return d
        self.send(fields)
        self.counts["sent"] += 1
        self._last_stamp_us = d.time_usec
        self._next_ns = now_ns + round(NS / self.config.rate_hz)
        return d

    def _say(self, d: Decision) -> None:
        """One log line when the target starts or stops going out."""
        sending = d.verdict is Verdict.SEND
        if sending != self._sending:
            self._sending = sending
            if sending:
                _logger.info(
                    "%s: landing target %s goes out (sigma %.3f m)", self.entity, self.config.target, d.sigma_m
                )
            else:
                _logger.warning(
                    "%s: no landing target: %s (age %.2f s, sigma %.3f m)",
                    self.entity, d.verdict.value, d.age_s, d.sigma_m,
                )  # fmt: skip


def _fields(autopilot: str, d: Decision) -> dict[str, Any] | None:
    """The message's fields in the form ``autopilot`` takes (None without them: not a SEND decision)."""
    if autopilot == "px4" and d.px4 is not None:
        p = d.px4
        return px4_landing_target_fields(d.time_usec, p.x_m, p.y_m, p.z_m, p.q_wxyz)
    if autopilot == "ardupilot" and d.ardupilot is not None:
        a = d.ardupilot
        return ardupilot_landing_target_fields(
            d.time_usec, a.x_m, a.y_m, a.z_m, a.distance_m, a.angle_x_rad, a.angle_y_rad
        )
    return None


def _velocity(ekf: EkfBank | None, name: str, wall_us: int) -> np.ndarray | None:
    """``name``'s world velocity from the node's EKF (None without a filter or an estimate)."""
    if ekf is None:
        return None
    filtered = ekf.pose(name, wall_us)
    return None if filtered is None or filtered.frame != WORLD else filtered.velocity_m_s
