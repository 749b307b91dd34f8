"""A landing flown closed loop in a real-time run (``atlas-onboard sim --scenario land-pad``).

The runner's :class:`Flight` is the landing drone's airframe and flight controller: a thread steps its
:class:`~atlas_onboard.sim.lander.Lander` on the LANDING_TARGETs the drone's simulated autopilot receives
from the node, knowing its own position as the autopilot's EKF would (the last vision pose received,
carried on by the motion since it arrived), and writes each state to the run's flight file. Every
process of the run reads the drone's truth from that file (:class:`~atlas_onboard.sim.trajectories.Flown`):
the cameras that see the drone, and the scoring. States are computed ``AHEAD_S`` before the wall clock
reaches them, so a frame never waits for its truth (the vehicle answers a target that much later: a
control latency).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pymavlink.dialects.v20 import common as mavlink

from atlas_onboard.config import LandingConfig
from atlas_onboard.core import frames
from atlas_onboard.sim import trajectories as tj
from atlas_onboard.sim.autopilot import SimAutopilot
from atlas_onboard.sim.lander import Lander, LanderSettings, Phase, ground_below
from atlas_onboard.sim.scenario import Landing, Scenario
from atlas_onboard.sim.world import SimWorld

FLIGHT_HZ = 200.0  # the vehicle's states per second
AHEAD_S = 0.02  # each state is computed this long before its time comes on the wall clock


@dataclass(frozen=True)
class LandingScore:
    """How a landing went: the touchdown's horizontal distance from the true landing point (None: it did
    not land), when (s since the start), the LANDING_TARGETs the autopilot received, how many of them
    were older than the node's ``max_age_s`` when they arrived, the aborts and the messages refused."""

    entity: str
    touchdown_m: float | None
    touchdown_s: float | None
    targets: int
    stale_targets: int
    aborts: int
    refused: int


class Flight:
    """The landing drone of a run, flown on what its autopilot receives (see the module's docstring)."""

    def __init__(self, scenario: Scenario, autopilot: SimAutopilot, max_duration_s: float) -> None:
        assert scenario.landing is not None
        self.landing: Landing = scenario.landing
        self.autopilot = autopilot
        flown = scenario.trajectories[self.landing.entity]
        assert isinstance(flown, tj.Flown) and flown.path is not None, "bind the scenario to the run first"
        self.flown = flown
        form = self.landing.form
        moving = scenario.trajectories.get(self.landing.target) is not None
        settings = LanderSettings(form, moving_target=moving and form == "ardupilot",
                                  lost_timeout_s=1.0 if form == "px4" else 2.0)  # fmt: skip
        self.lander = Lander(settings, np.array(flown.start_m, dtype=float), np.radians(flown.start_yaw_deg))
        self.max_age_s = LandingConfig(self.landing.target, form, self.landing.marker).max_age_s
        self.world = SimWorld(scenario)
        self._marker = self.world.world.markers[self.landing.marker]
        self._rows = int((max_duration_s + 2.0) * FLIGHT_HZ)
        self._table = tj.flight_table(flown.path, rows=self._rows)
        self._n = 0
        self._write(0.0)
        flown.states()  # mapped in this process now: the scoring reads it after the run's directory is gone
        self._seen = 0  # LANDING_TARGETs taken from the autopilot so far
        self.touchdown_s: float | None = None
        self._epoch_s = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="sim-flight", daemon=True)

    def start(self, epoch_s: float) -> Flight:
        self._epoch_s = epoch_s
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self._table.flush()

    def landed_for(self, now_s: float) -> float:
        """Seconds since touchdown at run time ``now_s`` (0 before it)."""
        return 0.0 if self.touchdown_s is None else max(now_s - self.touchdown_s, 0.0)

    def deck(self, t_s: float) -> NDArray[np.float64]:
        """The true landing point at ``t_s`` (world ENU)."""
        truth = self.world.truth(t_s, (self.landing.target,))
        return (truth[self.landing.target] * self._marker.T_entity_marker).translation

    def score(self) -> LandingScore:
        """The landing as it went (after :meth:`stop`)."""
        targets = list(self.autopilot.landing_targets)
        stale = sum(arrival - int(f["time_usec"]) * 1e-6 > self.max_age_s for arrival, f in targets)
        error = None
        if self.lander.touchdown_m is not None and self.touchdown_s is not None:
            error = float(np.linalg.norm(self.lander.touchdown_m[:2] - self.deck(self.touchdown_s)[:2]))
        return LandingScore(self.landing.entity, error, self.touchdown_s, len(targets), stale, self.lander.aborts,
                            self.lander.refused)  # fmt: skip

    def _run(self) -> None:
        k = 1
        while not self._stop.is_set() and k < self._rows:
            t = k / FLIGHT_HZ
            wait = self._epoch_s + t - AHEAD_S - time.time()
            if wait > 0:
                self._stop.wait(wait)
                continue
            self._take_targets()
            self.lander.step(t, 1.0 / FLIGHT_HZ, self._own_position(t), ground_below(self.lander.p_m, self.deck(t)))
            if self.lander.phase is Phase.LANDED and self.touchdown_s is None:
                self.touchdown_s = t
            self._write(t)
            k += 1

    def _take_targets(self) -> None:
        """Hand the LANDING_TARGETs that arrived since the last step to the vehicle, at their arrival."""
        new = self.autopilot.landing_targets[self._seen :]
        self._seen += len(new)
        for arrival, fields in new:
            # A body-frame target is added to where the vehicle was when it was measured (AC_PrecLand's
            # inertial history, PLND_LAG set to the latency).
            measured = int(fields["time_usec"]) * 1e-6 - self._epoch_s
            self.lander.on_target(fields, arrival - self._epoch_s, self._own_position(measured))

    def _own_position(self, t_s: float) -> NDArray[np.float64]:
        """The autopilot's estimate of its position at run time ``t_s``: the last vision pose received, fused
        at its capture time (``usec``: its EKF's delay parameter set to the link's latency) and carried on by
        the true motion since (its IMU); the truth before any."""
        received = self.autopilot.received
        truth_now = self.flown.pose(np.array([t_s]))[0][0]
        if not received:
            return truth_now
        last = received[-1]
        then = self.flown.pose(np.array([last.usec * 1e-6 - self._epoch_s]))[0][0]
        return frames.R_ENU_NED.apply(np.asarray(last.xyz_m, dtype=float)) + truth_now - then

    def _write(self, t_s: float) -> None:
        """Append the vehicle's state at ``t_s`` to the flight file (the row, then the count: readers in
        other processes never see a row half written)."""
        lander = self.lander
        row = [t_s, *lander.p_m, lander.yaw_rad, *lander.v_m_s, 0.0]
        self._table[self._n + 1] = row
        self._n += 1
        self._table[0, 0] = self._n


def autopilot_type(scenario: Scenario, name: str) -> int:
    """The autopilot drone ``name`` flies with: ArduPilot where it lands in ArduPilot's form, else PX4."""
    ls = scenario.landing
    ardupilot = ls is not None and ls.entity == name and ls.form == "ardupilot"
    return mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA if ardupilot else mavlink.MAV_AUTOPILOT_PX4
