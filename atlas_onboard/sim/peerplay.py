"""Peers played to a solo node (:mod:`atlas_onboard.sim.solo`) on its peer link: an honest leader that
sends its camera's views, and liars that forge them, for tests and benchmarks of what a node trusts.

Two set-ups of the ``relay`` scenario: ``own``, drone_a's node (its own camera over the floor tags),
to which a world camera (sensor ``WORLD_CAMERA``, run by the world's node, whose system id anyone on
an unsigned mesh can forge) reports drone_a's back marker; ``relay``, drone_b's node, whose camera sees
only drone_a's back marker, with drone_a's views of the floor tags played here as its node would send
them (the truth, fresh stamps, 15 a second).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from atlas_onboard.config import WorldConfig, load_world
from atlas_onboard.core.markerdata import MarkerData, matrix_to_upper
from atlas_onboard.sim.runner import WORLD_NODE_SYSTEM_ID
from atlas_onboard.sim.solo import Radio, SoloNode, forged_view, start_solo
from atlas_onboard.sim.world import SimWorld

SCENARIO = "relay"
WORLD_CAMERA = 90
LEADER, LEADER_SYSTEM_ID, LEADER_SENSOR = "drone_a", 1, 1
LEADER_MARKER = 50  # on drone_a's back: what drone_b sees, and what the world camera reports
FLOOR_MARKERS = (0, 1, 2, 3, 4, 5)
LEADER_RATE_HZ = 15.0
SETUPS = {"own": "drone_a", "relay": "drone_b"}


def add_world_camera(doc: dict[str, Any]) -> None:
    """A world camera above the room that no simulated camera feeds (its views are played), and the
    world's node that runs it, so that its observations bind to that node's system id."""
    world = doc["entities"].setdefault("world", {}) or {}
    doc["entities"]["world"] = world
    world.setdefault("sensors", []).append(
        {"name": "ceiling", "id": WORLD_CAMERA, "pose": {"pos": [2.5, 0.0, 3.0], "rpy_deg": [0, 90, 0]}}
    )
    doc["nodes"]["world"] = {"system_id": WORLD_NODE_SYSTEM_ID}


def start(setup: str, seconds: float) -> SoloNode:
    """The node of ``setup`` (``own`` or ``relay``), not yet started (:meth:`SoloNode.start_scenario`)."""
    edit = add_world_camera if setup == "own" else None
    return start_solo(SCENARIO, seconds, entity=SETUPS[setup], edit=edit)


@dataclass
class Sender:
    """Sends ``make(now_s)``'s observations as ``system_id`` every ``period_s`` from ``t0_s`` to
    ``t1_s`` (wall clock), in its own thread; counts what it sent."""

    node: SoloNode
    system_id: int
    period_s: float
    make: Callable[[float], Sequence[MarkerData]]
    sent: int = 0

    def __post_init__(self) -> None:
        self.radio = Radio(self.node.peer_port)
        self.world = load_world(self.node.world_file)
        self.fp = self.world.fingerprint()
        self.stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = 0

    def run_between(self, t0_s: float, t1_s: float) -> None:
        self._thread = threading.Thread(target=self._run, args=(t0_s, t1_s), daemon=True)
        self._thread.start()

    def _run(self, t0_s: float, t1_s: float) -> None:
        time.sleep(max(0.0, t0_s - time.time()))
        next_s = t0_s
        while not self.stop.is_set() and time.time() < t1_s:
            mds = list(self.make(time.time()))
            for i, md in enumerate(mds):
                self._seq = (self._seq + 1) & 0xFFFF
                md = replace(md, frame_remaining=len(mds) - 1 - i)
                self.radio.send(self.radio.observation(md, self.fp, self.system_id, seq=self._seq))
                self.sent += 1
            next_s += self.period_s
            time.sleep(max(0.0, next_s - time.time()))

    def join(self) -> None:
        self.stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        self.radio.close()


def nearest_floor_marker(sim_world: SimWorld, t_s: float) -> int:
    """The floor tag nearest below the leader at scenario time ``t_s`` (the one its camera sees best)."""
    p = sim_world.truth(t_s)[LEADER].translation
    world = sim_world.world
    return min(
        FLOOR_MARKERS, key=lambda m: float(np.linalg.norm(world.markers[m].T_entity_marker.translation[:2] - p[:2]))
    )


def views(
    node: SoloNode,
    sensor: int,
    markers: Callable[[float], Sequence[int]],
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
    sigma_m: float = 0.002,
    covariance: np.ndarray | None = None,
    ahead_s: float = 0.0,
) -> Callable[[float], list[MarkerData]]:
    """What ``sensor`` would report of ``markers(t)`` if the leader stood ``offset_m`` off (0: the
    truth), with the claimed ``sigma_m`` and 6x6 ``covariance`` (None: none), stamped ``ahead_s``
    after now."""
    world: WorldConfig = load_world(node.world_file)
    sim_world = SimWorld(node.scenario)
    upper = matrix_to_upper(covariance) if covariance is not None else ()

    def make(now_s: float) -> list[MarkerData]:
        t = now_s - node.epoch_s
        stamp = int((now_s + ahead_s) * 1e6)
        return [
            replace(forged_view(world, sim_world, LEADER, sensor, m, t, offset_m, sigma_m, stamp), covariance=upper)
            for m in markers(t)
        ]

    return make


def honest_leader(node: SoloNode) -> Sender:
    """drone_a's node as drone_b hears it: its camera's view of the nearest floor tag, the truth."""
    sim_world = SimWorld(node.scenario)
    make = views(node, LEADER_SENSOR, lambda t: (nearest_floor_marker(sim_world, t),))
    return Sender(node, LEADER_SYSTEM_ID, 1.0 / LEADER_RATE_HZ, make)
