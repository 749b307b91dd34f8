"""A follower's estimator alone on a scenario's rendered frames (no processes, no load, no clocks):
each camera at its own rate, every observation arriving a fixed delay after its capture, the
follower's listener and graph evaluated at each arrival, a pose scored when its capture time is new
(what the publisher sends). The time alignment of its candidates shows here as it does live, without
what a loaded machine adds (frames skipped, late links)."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.listener import Listener
from atlas_onboard.node.output import level_own, make_ekf
from atlas_onboard.node.setup import make_graph
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.world import SimWorld

Frames = Callable[[int], NDArray[np.uint8]]  # frame index -> image (frame j at j / fps)


@dataclass(frozen=True)
class FollowerTrack:
    """The follower's poses: capture times (s), errors ``[dp, dtheta]`` (N, 6, world frame and body
    axes) against truth, their 6x6 covariances (N, 6, 6)."""

    capture_s: NDArray[np.float64]
    errors: NDArray[np.float64]
    covariances: NDArray[np.float64]

    @property
    def error_mm(self) -> NDArray[np.float64]:
        return np.linalg.norm(self.errors[:, :3], axis=1) * 1e3


def autopilot_up(sim: SimWorld, entity: str, seed: int = 0) -> Callable[[int], NDArray[np.float64]]:
    """``entity``'s autopilot's up vector (body frame) at a capture time (us), as the simulated autopilot
    measures its roll and pitch (:class:`atlas_onboard.sim.autopilot.SimAutopilot`'s defaults: a bias per
    run and a noise per sample, each per axis), for the offline estimator."""
    from atlas_onboard.core.attitude import up_in_body
    from atlas_onboard.sim.autopilot import SimAutopilot

    defaults = {f.name: f.default for f in dataclasses.fields(SimAutopilot)}
    bias = np.radians(np.random.default_rng(seed).normal(0.0, defaults["attitude_bias_deg"], 2))
    sigma = math.radians(defaults["attitude_noise_deg"])

    def up_at(t_us: int) -> NDArray[np.float64]:
        noise = np.random.default_rng((seed, t_us)).normal(0.0, sigma, 2) + bias
        R = sim.truth(t_us / 1e6, (entity,))[entity].rotation
        return up_in_body(R * Rotation.from_rotvec([noise[0], noise[1], 0.0]))

    return up_at


def run(
    scenario_name: str,
    follower: str,
    frames_of: Callable[[int], Frames],
    t0_s: float,
    t1_s: float,
    delay_s: float = 0.02,
    fusion: dict[str, Any] | None = None,
    up_at: Callable[[int], NDArray[np.float64] | None] | None = None,
    peer_delay_s: float = 0.0,
) -> FollowerTrack:
    """``follower``'s poses from ``t0_s`` to ``t1_s`` (frames from 0.5 s before ``t0_s``, to warm up),
    each camera's frames from ``frames_of(sensor_id)``, observations arriving ``delay_s`` after capture.
    ``up_at``: the follower's autopilot's up vector (body frame) at a capture time, as the node uses it
    (the listener's tilt checks, :func:`atlas_onboard.node.output.level_own`); None: no attitude.
    ``peer_delay_s``: what the other drones' observations take on top (their node and the link)."""
    from atlas_onboard.detector.pipeline import Detector

    scenario = scenarios.get(scenario_name)
    world = scenario.world()
    if fusion:
        world = dataclasses.replace(world, fusion=dataclasses.replace(world.fusion, **fusion))
    sim = SimWorld(scenario, world)
    events = []
    for sid, (sensor, intr) in sorted(sim.cameras.items()):
        assert sensor.camera is not None
        fps = sensor.camera.fps if sensor.camera.fps > 0 else 30.0
        det = Detector(sensor, world, intr.calibration(), decimate=2.0)
        frame = frames_of(sid)
        for j in range(max(math.floor((t0_s - 0.5) * fps), 0), math.floor(t1_s * fps)):
            t = j / fps
            late = delay_s + (peer_delay_s if sensor.entity != follower else 0.0)
            events.append((t + late, det.detect(np.asarray(frame(j)), round(t * 1e6))))
    events.sort(key=lambda e: e[0])
    graph = make_graph(world, follower)
    listener = Listener(world, graph)
    if up_at is not None:
        listener.set_attitude(follower, up_at)
    ekf = make_ekf(world)  # with ``filter: ekf``, the follower's pose as the node publishes it
    last, caps, errs, covs = -1, [], [], []
    for arrival, mds in events:
        now = round(arrival * 1e9)
        listener.accept_many([(md, now) for md in mds])
        result = level_own(graph.evaluate(now), follower, up_at)
        listener.set_estimates(result.poses)
        if ekf is not None:
            ekf.update(result, now // 1000, only=follower)
            result = level_own(ekf.poses(result, now // 1000, only=follower), follower, up_at)
        f = result.poses.get(follower)
        if f is None or f.capture_time_us <= last or f.covariance is None:
            continue
        last = f.capture_time_us
        tc = f.capture_time_us / 1e6
        if tc < t0_s:
            continue
        T = sim.truth(tc, (follower,))[follower]
        dtheta = (T.rotation.inv() * Rotation.from_quat(f.q_world_xyzw)).as_rotvec()
        caps.append(tc)
        errs.append(np.r_[f.p_world_m - T.translation, dtheta])
        covs.append(f.covariance)
    return FollowerTrack(np.array(caps), np.array(errs).reshape(-1, 6), np.array(covs).reshape(-1, 6, 6))
