"""Precision-landing scenarios, closed loop and faster than real time (for tests and benchmarks/bench_land.py).

The node's parts as they run in a node, without processes or clocks: the cameras' observations (true
corners plus pixel noise, solved by PnP with the detector's covariance: the simulator's geometric
detector) reach the listener and the landing drone's graph after a delay; after each evaluation the
node's :class:`~atlas_onboard.landing.LandingOutput` decides and builds LANDING_TARGET; each message
reaches the simulated autopilot's :class:`~atlas_onboard.sim.lander.Lander` a few milliseconds later,
which flies the drone; its true pose is what the cameras see next.

Scenarios (:mod:`atlas_onboard.sim.scenarios`, where `atlas-onboard sim` flies them in real time):

- ``land-pad``: a static pad of world tags seen by the drone's own downward camera (target: world,
  the pad's centre tag);
- ``land-rover``: a rover driving at 0.3 m/s that only a ceiling camera and a peer drone see; the
  landing drone has no camera (the ceiling camera places it by its top tag).

``gap`` hides every camera for an interval (the target lost): the count of messages sent while their
newest observation was older than ``max_age_s`` is the run's ``stale_sent``.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform

from atlas_onboard.config import LandingConfig
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.errors import AtlasError
from atlas_onboard.listener import Listener
from atlas_onboard.node.landing import LandingOutput
from atlas_onboard.node.setup import make_graph
from atlas_onboard.sim import scenarios
from atlas_onboard.sim import trajectories as tj
from atlas_onboard.sim.context import SimContext
from atlas_onboard.sim.lander import Lander, LanderSettings, Phase, ground_below
from atlas_onboard.sim.world import SimWorld

DRONE = "drone"
STEP_S = 1.0 / 120.0  # the vehicle's dynamics; the cameras run at their fps
OWN_DELAY_S = 0.03  # own camera: capture to the graph (detection)
PEER_DELAY_S = 0.06  # a ceiling camera's or a peer's: detection and the network
LINK_DELAY_S = 0.005  # the node to the autopilot


@dataclass
class LandingRun:
    """One landing: the touchdown error (m, horizontal; None if it did not land), the messages sent and
    how many of them were stale when sent (and, for comparison, how many a sender that repeats its last
    target at ``rate_hz`` would have sent stale), the aborts, and the decisions taken by verdict."""

    touchdown_error_m: float | None
    time_s: float
    sent: int
    stale_sent: int
    held_stale: int  # what a sender repeating its last target at rate_hz would have sent stale
    aborts: int
    verdicts: Counter[str]


def run(name: str, seed: int = 0, form: str | None = None, gap_s: tuple[float, float] | None = None,
        duration_s: float = 20.0, max_age_s: float = 0.3, max_sigma_m: float = 0.05) -> LandingRun:  # fmt: skip
    """Fly scenario ``name`` until touchdown (or ``duration_s``): see the module's docstring."""
    from atlas_onboard.sim.workers import geometric_detector

    landings = sorted(n for n, sc in scenarios.SCENARIOS.items() if sc.landing is not None)
    if name not in landings:
        raise AtlasError(f"unknown landing scenario {name!r} (choose from {', '.join(landings)})")
    scenario = scenarios.get(name)
    ls = scenario.landing
    assert ls is not None and ls.entity == DRONE
    start = scenario.trajectories[DRONE]
    assert isinstance(start, tj.Flown)
    form = form or ls.form
    world = scenario.world()
    sim = SimWorld(scenario, world)
    graph = make_graph(world, DRONE)
    listener = Listener(world, graph)
    # The autopilot's attitude (ATTITUDE, as the node gets it): the simulated vehicle flies level, so
    # world up is its body's z; it resolves a single tag's two solutions, as in a node.
    listener.set_attitude(DRONE, lambda _t_us: np.array([0.0, 0.0, 1.0]))
    config = LandingConfig(target=ls.target, autopilot=form, marker=ls.marker, max_age_s=max_age_s,
                           max_sigma_m=max_sigma_m)  # fmt: skip
    outbox: list[tuple[float, dict[str, object]]] = []
    now = [0.0]
    output = LandingOutput(config, DRONE, world, lambda f: outbox.append((now[0], f)))
    context = SimContext(scenario, seed, Path("/dev/null"), duration_s)
    cams = [(sensor, geometric_detector(context, sensor, intr, seed * 1009 + sid).detect) for sid, (sensor, intr) in
            sorted(sim.cameras.items())]  # fmt: skip
    fps = min(float(s.camera.fps) for s, _ in cams if s.camera is not None)
    moving = ls.target != "world"
    settings = LanderSettings(form, moving_target=moving and form == "ardupilot",
                              lost_timeout_s=1.0 if form == "px4" else 2.0)  # fmt: skip
    lander = Lander(settings, np.array(start.start_m, dtype=float), np.radians(start.start_yaw_deg))
    marker = world.markers[ls.marker]
    pending: list[tuple[float, list[MarkerData]]] = []
    history: list[tuple[float, NDArray[np.float64]]] = []  # the drone's true position by time
    estimate: tuple[float, NDArray[np.float64]] | None = None  # the node's own pose: capture time, position
    sent = stale = held = 0
    last_stamp_s: float | None = None  # the newest observation sent so far
    next_tick = 0.0
    next_frame = 0.0
    t = 0.0
    while t < duration_s and lander.phase is not Phase.LANDED:
        now[0] = t
        truth = sim.truth(t)
        truth[DRONE] = RigidTransform.from_components(lander.p_m, lander.attitude)
        history.append((t, lander.p_m.copy()))
        hidden = gap_s is not None and gap_s[0] <= t < gap_s[1]
        if t >= next_frame - 1e-9:
            next_frame += 1.0 / fps
            for sensor, detect in cams:
                if hidden:
                    continue
                mds = detect(t, sim.sightings(sensor.id, truth, t), {"epoch": 0.0})
                if mds:
                    delay = OWN_DELAY_S if sensor.entity == DRONE else PEER_DELAY_S
                    pending.append((t + delay, mds))
        due = [mds for at, mds in pending if at <= t]
        pending = [(at, mds) for at, mds in pending if at > t]
        if due:
            now_ns = round(t * 1e9)
            listener.accept_many([(md, now_ns) for mds in due for md in mds])
            result = graph.evaluate(now_ns)
            listener.set_estimates(result.poses)
            own = result.poses.get(DRONE)
            if own is not None:
                estimate = (own.capture_time_us * 1e-6, own.p_world_m.copy())
            before = len(outbox)
            output.update(result, now_ns, round(t * 1e6))
            for _, fields in outbox[before:]:
                sent += 1
                stale += _age_s(fields, t) > max_age_s
                last_stamp_s = t - _age_s(fields, t)
        if t >= next_tick:
            next_tick += 1.0 / config.rate_hz
            held += last_stamp_s is not None and t - last_stamp_s > max_age_s
        own_now = _own_position(estimate, history, lander.p_m)
        for _at, fields in [m for m in outbox if m[0] + LINK_DELAY_S <= t]:
            lander.on_target(fields, t, own_now)
        outbox[:] = [m for m in outbox if m[0] + LINK_DELAY_S > t]
        point = (truth[ls.target] * marker.T_entity_marker).translation
        lander.step(t, STEP_S, own_now, ground_below(lander.p_m, point))
        t += STEP_S
    error = None
    if lander.touchdown_m is not None:
        point = (sim.truth(t)[ls.target] * marker.T_entity_marker).translation
        error = float(np.linalg.norm(lander.touchdown_m[:2] - point[:2]))
    return LandingRun(error, t, sent, stale, held, lander.aborts, Counter(output.counts))


def _own_position(
    estimate: tuple[float, NDArray[np.float64]] | None,
    history: list[tuple[float, NDArray[np.float64]]],
    true_now: NDArray[np.float64],
) -> NDArray[np.float64]:
    """The autopilot's own position: the node's last pose, carried to now by the motion since its capture
    (its EKF fuses vision at the capture time and its IMU bridges the rest)."""
    if estimate is None:
        return true_now.copy()
    t_cap, p = estimate
    return p + (true_now - history[_nearest(history, t_cap)][1])


def _nearest(history: list[tuple[float, NDArray[np.float64]]], t: float) -> int:
    k = round((t - history[0][0]) / STEP_S)
    return min(max(k, 0), len(history) - 1)


def _age_s(fields: dict[str, object], t_s: float) -> float:
    """How old a LANDING_TARGET's observation is at ``t_s`` (its time_usec is the capture time)."""
    stamp = fields["time_usec"]
    return t_s - (stamp if isinstance(stamp, int) else 0) * 1e-6
