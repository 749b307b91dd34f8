"""Simulated sensors inside a node process: the ``sim`` camera source, the shared start time, and the
motion-capture system.

A node started by ``atlas-onboard sim`` (through :mod:`atlas_onboard.sim.launch`, which registers the
``sim`` camera source) finds the scenario in the ``ATLAS_SIM`` environment variable (JSON: scenario,
seed, epoch_file, duration_s, frames_dir, geometric). Its simulated sensors wait until the runner
writes the start time (UNIX seconds) to ``epoch_file``, then produce data stamped on the wall clock, so
every process of the run shares one timeline with the ground truth.
"""

from __future__ import annotations

import json
import logging
import os
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, NodeConfig, SensorConfig, WorldConfig
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.errors import AtlasError
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.world import SimWorld
from atlas_onboard.worker import Deliver, SensorWorker

_logger = logging.getLogger(__name__)

SIM_ENV = "ATLAS_SIM"
SIM_KIND = scenarios.SIM_KIND
"""The ``camera.source`` of a simulated camera (and of the motion-capture system's world sensor)."""


@dataclass(frozen=True)
class SimContext:
    """The simulation a node belongs to."""

    scenario: scenarios.Scenario
    seed: int
    epoch_file: Path
    duration_s: float
    frames_dir: Path | None = None  # the cameras' pre-rendered images, if the runner made them
    geometric: bool = False  # no images: corners from the geometry plus noise
    replay: str = ""  # a replay mode: the cameras read the frames' image folders (sim.runner.replay_folder)

    @classmethod
    def from_env(cls) -> SimContext:
        raw = os.environ.get(SIM_ENV)
        if not raw:
            raise AtlasError(
                f"camera source 'sim' needs the {SIM_ENV} environment variable: run it from `atlas-onboard sim`"
            )
        try:
            doc = json.loads(raw)
            return cls(
                scenarios.get(doc["scenario"]),
                int(doc.get("seed", 0)),
                Path(doc["epoch_file"]),
                float(doc["duration_s"]),
                Path(doc["frames_dir"]) if doc.get("frames_dir") else None,
                bool(doc.get("geometric", False)),
                str(doc.get("replay") or ""),
            )
        except (ValueError, KeyError, TypeError) as exc:
            raise AtlasError(f"{SIM_ENV}: expected JSON with scenario, epoch_file and duration_s ({exc})") from None

    def wait_epoch(self, stop: threading.Event) -> float | None:
        """The run's start time (UNIX s), waiting for the runner to write it; None if stopped first."""
        while not stop.is_set():
            try:
                return float(self.epoch_file.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                stop.wait(0.02)
        return None

    def ticks(
        self, stop: threading.Event, period_s: float, on_late: Callable[[int], None] | None = None
    ) -> Iterator[tuple[float, int, float]]:
        """The run's clock for a periodic sensor: ``(epoch, k, t)`` for k = 0, 1, ..., each yielded when
        the wall clock reaches ``epoch + t`` (t = k period_s, s from the run's start), until ``stop``.
        With ``on_late``, ticks whose time passed more than a period ago are dropped, never queued,
        and their number handed to it."""
        epoch = self.wait_epoch(stop)
        if epoch is None:
            return
        k = 0
        while not stop.is_set():
            t = k * period_s
            wait = epoch + t - time.time()
            if wait > 0:
                stop.wait(wait)
                continue
            if on_late is not None and wait < -period_s:
                missed = int(-wait / period_s)
                on_late(missed)
                k += missed
                continue
            yield epoch, k, t
            k += 1


class MocapWorker(SensorWorker):
    """The paper's OptiTrack: observes the rigid-body marker of every drone at a fixed rate, with noise.

    It reports like any sensor, as MarkerData of the mocap "sensor" (its optical frame is the world
    frame), so the rest of the system treats it as a very good camera.
    """

    def __init__(self, context: SimContext, world: WorldConfig, sensor_id: int) -> None:
        super().__init__()
        self.name = "mocap"
        self.context = context
        self.sim = SimWorld(context.scenario, world)
        self.sensor = world.sensors[sensor_id]
        self.mocap = context.scenario.mocap
        if self.mocap is None:
            raise AtlasError(f"scenario {context.scenario.name} has no motion-capture system")
        self.markers = [m for m in world.markers.values() if m.entity in context.scenario.drones]
        self.sent = 0

    def counters(self) -> dict[str, int]:
        return {"observations": self.sent}

    def _run(self, deliver: Deliver) -> None:
        assert self.mocap is not None
        rng = np.random.default_rng(self.context.seed + 1000)
        T_world_sensor = self.sensor.T_entity_sensor  # the mocap frame, on the world entity
        for epoch, _, t in self.context.ticks(self._stop, 1.0 / self.mocap.rate_hz):
            truth = self.sim.truth(t)
            frame = []
            for m in self.markers:
                T = T_world_sensor.inv() * truth[m.entity] * m.T_entity_marker
                p = T.translation + rng.normal(0.0, self.mocap.sigma_m, 3)
                r = T.rotation * Rotation.from_rotvec(rng.normal(0.0, np.radians(self.mocap.sigma_deg), 3))
                x, y, z, w = r.as_quat()
                frame.append(
                    MarkerData(
                        sensor_id=self.sensor.id,
                        marker_id=m.id,
                        sigma_m=self.mocap.sigma_m,
                        p_sensor_marker_m=(float(p[0]), float(p[1]), float(p[2])),
                        q_sensor_marker_wxyz=(float(w), float(x), float(y), float(z)),
                        capture_time_us=round((epoch + t) * 1e6),
                    )
                )
            if frame:
                deliver(frame)
                self.sent += len(frame)


def sim_camera(world: WorldConfig, config: NodeConfig, sensor: SensorConfig) -> SensorWorker:
    """The worker of a sensor whose ``camera.source`` is ``sim``: the scenario's motion-capture system
    for its world sensor, else a simulated camera (rendered images through the real detector, or
    corners from the geometry plus noise)."""
    from atlas_onboard.sim.camera import (
        SimCameraWorker,
        SimReplayWorker,
        camera_seed,
        geometric_detector,
        rendered_detector,
    )

    context = SimContext.from_env()
    mocap = context.scenario.mocap
    if mocap is not None and config.entity == WORLD and sensor.name == mocap.sensor:
        return MocapWorker(context, world, sensor.id)
    seed = camera_seed(context.seed, sensor.id)
    if context.replay and context.frames_dir is not None:
        from atlas_onboard.sim.runner import replay_folder

        folder = replay_folder(context.frames_dir, sensor.id)
        if folder.is_dir():
            return SimReplayWorker(context, world, sensor, folder, config.refine)
    if context.geometric:
        intr = SimWorld(context.scenario, world).cameras[sensor.id][1]
        detect = geometric_detector(context, sensor, intr, seed)
    else:
        detect = rendered_detector(context, world, sensor, seed, config.refine)
    return SimCameraWorker(context, world, sensor, detect)
