"""The node's output side: evaluating the graph, the autopilot's pose (the EKF's, if enabled), fused poses
to peers, telemetry and the lateness report (the loop and the intake are in :mod:`atlas_onboard.node`)."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import AutopilotConfig, NodeConfig, WorldConfig, defaults
from atlas_onboard.core.attitude import BodyPose, constrain_body_tilt
from atlas_onboard.core.ekf import MANOEUVRE_ACCEL_SIGMA, MANOEUVRE_ATTITUDE_SIGMA_RAD, MANOEUVRE_TIME_S, EkfSettings
from atlas_onboard.core.ekfbank import EkfBank
from atlas_onboard.core.graph import EntityPose, GraphResult
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.publisher import Publisher
from atlas_onboard.core.records import PoseState, Telemetry
from atlas_onboard.node.landing import landing_output
from atlas_onboard.node.ports import Transport
from atlas_onboard.node.schedule import Changes, near_entities
from atlas_onboard.node.setup import WorldBlocks
from atlas_onboard.service.state import ResetCounterStore

_logger = logging.getLogger(__name__)

NS = 1_000_000_000
PREDICT_NS = 20_000_000  # with the EKF, publish its prediction to now at least every 20 ms
TELEMETRY_NS = NS  # graphable values to the ground station once a second


# An own camera's observation is late when it is older, as the loop takes it, than this beyond the
# smallest age seen (the pipeline's fixed delay; under a simulator or a test, the offset of its
# clock): beyond what the autopilots compensate (PX4 EKF2_EV_DELAY <= 300 ms; ArduPilot marks vision
# older than 300 ms unhealthy). It is still used, its pose published, stamped with its capture time.
LATE_S = 0.3
LATE_REPORT_NS = 10 * NS  # at most one log line and one STATUSTEXT about lateness per 10 s
LATE_STREAK = 3  # said once this many images in a row were late (one late image is a hiccup, not a lag)


@dataclass
class Stats:
    local_observations: int = 0
    peer_observations: int = 0
    evaluations: int = 0
    autopilot_sent: int = 0
    fused_sent: int = 0
    superseded: int = 0  # parked peer observations replaced by a newer one of the same edge before use
    late_observations: int = 0  # own camera's observations older than LATE_S when taken (still used)


class NodeOutput:
    """The node's output side, a collaborator of :class:`atlas_onboard.node.loop.Node`: it evaluates the graph
    the node hands it (:meth:`attach`, again on reload) and sends what follows to the autopilot, the peers
    and the ground station. It owns the publisher, the EKF, the last result and its own timers."""

    def __init__(
        self,
        config: NodeConfig,
        blocks: WorldBlocks,
        transport: Transport,
        stats: Stats,
        changes: Changes,
        *,
        clock: Callable[[], int],
        wall: Callable[[], int],
    ) -> None:
        self.config = config
        self.transport = transport
        self.stats = stats
        self.changes = changes  # when the graph is to be evaluated (the node marks what it accepts)
        self.clock = clock
        self.wall = wall
        ap = config.autopilot
        ap_default = defaults(AutopilotConfig)
        self.publisher = Publisher(
            config.entity,
            rate_hz=ap.rate_hz if ap else ap_default["rate_hz"],
            fused_rate_hz=config.fused_rate_hz,
            reset_jump_m=ap.reset_jump_m if ap else ap_default["reset_jump_m"],
            reset_gap_s=blocks.world.fusion.edge_timeout_s,  # lost means no observation for this long
        )
        self._reset_store = ResetCounterStore(config.state_dir, config.entity)
        self.publisher.reset_counter = self._reset_store.initial(self.wall())  # a restart is a reset
        self.last_result: GraphResult | None = None
        self.near: frozenset[str] | None = None  # entities whose observations are evaluated at once
        self._last_publish_ns = 0
        self._next_telemetry_ns = 0
        self._telemetry_since = (0, 0)  # (monotonic ns, local observations) at the last telemetry
        self._latency_sum_ms, self._latency_n = 0.0, 0
        self._next_late_report_ns = 0
        self._min_age_us: int | None = None  # the smallest age of an own observation seen (see LATE_S)
        self._late_streak = 0  # own images in a row with a late observation
        history = transport.attitude if config.autopilot is not None else None
        self._up_at = history.up_at if history is not None else None
        self.attach(blocks)

    def attach(self, blocks: WorldBlocks) -> None:
        """The world, graph and listener to evaluate (at start and on reload); a fresh EKF for the world."""
        self.world, self.graph, self.listener = blocks.world, blocks.graph, blocks.listener
        self.ekf = make_ekf(blocks.world)
        self.landing = landing_output(self.config, blocks.world, self.transport)

    def start(self) -> None:
        self._telemetry_since = (self.clock(), 0)

    def next_prediction_ns(self) -> int | None:
        """When the EKF's prediction to now is next due (None without the EKF or a result)."""
        if self.ekf is None or self.last_result is None:
            return None
        return self._last_publish_ns + PREDICT_NS

    def check_lateness(self, accepted_local: Sequence[MarkerData]) -> None:
        """Counts the own observations of a batch that are late (see ``LATE_S``) and reports a streak."""
        wall_us = self.wall() // 1000
        late, oldest_us = 0, 0
        for md in accepted_local:
            age_us = wall_us - md.capture_time_us
            if self._min_age_us is None or age_us < self._min_age_us:
                self._min_age_us = age_us
            if age_us - self._min_age_us > LATE_S * 1e6:
                late, oldest_us = late + 1, max(oldest_us, age_us - self._min_age_us)
        if late:
            self.stats.late_observations += late
            self._late_streak += 1
            if self._late_streak >= LATE_STREAK:
                self._report_late(oldest_us / 1e6)
        elif accepted_local:
            self._late_streak = 0

    def _report_late(self, age_s: float) -> None:
        """Own observations arrive ``age_s`` later than the promptest did (a file replayed every frame, a
        detector that cannot keep up): counted always, said at most every ``LATE_REPORT_NS`` in the log
        and as a STATUSTEXT. They are used all the same: a pose stamped with its capture time is valid."""
        now = self.clock()
        if now < self._next_late_report_ns:
            return
        self._next_late_report_ns = now + LATE_REPORT_NS
        _logger.warning(
            "%s: camera observations arrive %.2f s late (more than the autopilot compensates, %.1f s):"
            " the detector or a replay cannot keep up; poses still go out, stamped with their capture time",
            self.config.entity, age_s, LATE_S,
        )  # fmt: skip
        self.transport.send_status(f"atlas {self.config.entity}: vision {age_s:.1f} s late", 4)  # WARNING

    def evaluate_and_publish(self, now: int, own_first: bool = False) -> None:
        """What can give the autopilot a pose. With ``own_first`` (new observations that can move the
        own pose), only the own pose is evaluated when that is possible (see :meth:`evaluate`)."""
        expiry = self.graph.next_expiry_ns()
        expired = expiry is not None and now >= expiry
        if self.changes.due(now) or expired:
            self.evaluate(now, own_only=own_first and not expired)
            self.publish(now)
        elif self.last_result is not None:
            held = self.publisher.next_autopilot_ns()
            due_hold = held is not None and now >= held and self.publisher.has_pose
            if due_hold or (self.ekf is not None and now - self._last_publish_ns >= PREDICT_NS):
                self.publish(now)

    def duties(self, now: int) -> None:
        """Fused poses to peers and the ground station's telemetry, when due."""
        if self.publisher.fused_due(now) and self.last_result is not None:
            self.transport.send_fused(fused_poses(self.last_result), self.world)
            self.stats.fused_sent += 1
        if now >= self._next_telemetry_ns:
            self._next_telemetry_ns = now + TELEMETRY_NS
            self._send_telemetry(now)

    def evaluate(self, now: int, own_only: bool = False) -> None:
        """Evaluate the graph. With ``own_only``, and when the paper's BFS has placed the own entity
        (and no filter needs every entity's candidates), only the own pose and those it rests on are
        computed (the same pose as a full evaluation); the others keep their last poses and are
        evaluated together within ``COALESCE_NS``, unless the graph says those are still current."""
        partial = own_only and self.near is not None and self.ekf is None
        self.listener.forget_expired(now)
        result = self.graph.evaluate(now, target=self.config.entity if partial else None, previous=self.last_result)
        result = level_own(result, self.config.entity, self._up_at)
        if result.complete:
            self.changes.evaluated(now, complete=True)
        else:  # a full evaluation is not needed when it would give every other entity the pose it has
            self.changes.evaluated(now, complete=False, rest_unchanged=result.current)
        self.last_result = result
        if self.landing is not None:
            self.landing.update(result, now, self.wall() // 1000, self.ekf)
        bfs = self.world.fusion.path == "bfs"
        self.near = near_entities(self.config.entity, result.levels if bfs else None)
        self.listener.set_estimates(result.poses)
        self.stats.evaluations += 1
        if self.ekf is not None:
            self.ekf.update(result, self.wall() // 1000, only=self.config.entity)

    def publish(self, now: int) -> None:
        """The autopilot's pose from the last evaluation (the EKF's, predicted to now, if enabled)."""
        assert self.last_result is not None
        self._last_publish_ns = now
        result = self.last_result
        if self.ekf is not None:
            # The autopilot gets the filter's pose predicted to now (stamped now), at its rate.
            result = level_own(
                self.ekf.poses(result, self.wall() // 1000, only=self.config.entity), self.config.entity, self._up_at
            )
        out, status = self.publisher.autopilot(result, now)
        if status is not None:
            lost = status == "pose lost"
            _logger.log(logging.WARNING if lost else logging.INFO, "%s: %s", self.config.entity, status)
            self.transport.send_status(f"atlas {self.config.entity}: {status}", 4 if lost else 6)  # WARNING / INFO
            self.transport.set_pose_state(PoseState.LOST if lost else PoseState.ACTIVE)
        if out is not None and self.config.autopilot is not None:
            pose = out.pose
            _logger.debug("pose cap %d p %s n %d", pose.capture_time_us, pose.p_world_m, pose.n_observations)
            self.transport.send_autopilot(out)
            self.stats.autopilot_sent += 1
            self._reset_store.save(out.reset_counter)
            self._latency_sum_ms += (self.wall() // 1000 - pose.capture_time_us) / 1000.0
            self._latency_n += 1

    def _send_telemetry(self, now: int) -> None:
        """The ground station's graphable values over the period since the last call."""
        since_ns, since_local = self._telemetry_since
        self._telemetry_since = (now, self.stats.local_observations)
        period_s = (now - since_ns) / NS
        pose = self.last_result.poses.get(self.config.entity) if self.last_result is not None else None
        latency = self._latency_sum_ms / self._latency_n if self._latency_n else float("nan")
        self._latency_sum_ms, self._latency_n = 0.0, 0
        self.transport.send_telemetry(
            Telemetry(
                sigma_m=pose.sigma_m if pose is not None and self.publisher.has_pose else float("nan"),
                detections_hz=(self.stats.local_observations - since_local) / period_s if period_s > 0 else 0.0,
                latency_ms=latency,
            )
        )


def level_own(
    result: GraphResult, entity: str, up_at: Callable[[int], NDArray[np.float64] | None] | None
) -> GraphResult:
    """``result`` with ``entity``'s pose updated with its autopilot's up vector at its capture time
    (:func:`atlas_onboard.core.attitude.constrain_body_tilt`) when that pose rests on no own view of the
    world: a follower placed through its leader's marker, whose tilt (poorly seen in a face-on tag) swings
    its position over the range to that marker. A pose built on an own view already carries gravity
    (the listener's tilt constraint of each such tag) and is left as it is, as is one without an attitude."""
    pose = result.poses.get(entity)
    if up_at is None or pose is None or pose.own_view is not False or pose.covariance is None:
        return result
    up = up_at(pose.capture_time_us)
    if up is None:
        return result
    R = Rotation.from_quat(pose.q_world_xyzw).as_matrix()
    new = constrain_body_tilt(BodyPose(pose.p_world_m, R, pose.covariance), up)
    shrink = np.trace(new.covariance[:3, :3]) / max(float(np.trace(pose.covariance[:3, :3])), 1e-300)
    leveled = replace(
        pose,
        p_world_m=new.p_world_m,
        q_world_xyzw=Rotation.from_matrix(new.R_world_body).as_quat(),
        covariance=new.covariance,
        sigma_m=pose.sigma_m * math.sqrt(min(shrink, 1.0)),
    )
    return replace(result, poses={**result.poses, entity: leveled})


def fused_poses(result: GraphResult) -> list[EntityPose]:
    """What goes to peers and the GCS: every world pose, then (with ``relative_poses``) the pose of
    each entity of a group with no path to world relative to the group's first entity (its frame)."""
    poses = list(result.poses.values())
    for group in result.relative.values():
        poses += [p for p in group.values() if p.name != p.frame]
    return poses


def make_ekf(world: WorldConfig) -> EkfBank | None:
    f = world.fusion
    if f.filter != "ekf":
        return None
    # The attitude is held between updates (see EkfSettings.constant_rate): the autopilot's gyros
    # know the rates far better than a camera does.
    settings = EkfSettings(
        accel_noise=f.ekf_accel_noise,
        max_gap_s=f.ekf_max_predict_s,
        constant_rate=False,
        attitude_sigma_rad=MANOEUVRE_ATTITUDE_SIGMA_RAD,
        manoeuvre_accel_sigma=MANOEUVRE_ACCEL_SIGMA,
        manoeuvre_time_s=MANOEUVRE_TIME_S,
        estimate_accel=False,
    )
    return EkfBank(settings, max_predict_s=f.ekf_max_predict_s)
