"""Simulated sensors inside a node process: the ``sim`` camera source (:func:`sim_camera`) and the
motion-capture system.

A node started by ``atlas-onboard sim`` (through :mod:`atlas_onboard.sim.launch`, which registers the
``sim`` camera source) finds the scenario in the ``ATLAS_SIM`` environment variable
(:class:`~atlas_onboard.sim.context.SimContext`). Its simulated sensors wait until the runner
writes the start time (UNIX seconds) to ``epoch_file``, then produce data stamped on the wall clock, so
every process of the run shares one timeline with the ground truth.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, NodeConfig, SensorConfig, WorldConfig
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.errors import AtlasError
from atlas_onboard.sim.camera import camera_seed, replay_folder
from atlas_onboard.sim.context import SimContext
from atlas_onboard.sim.workers import SimCameraWorker, SimReplayWorker, geometric_detector, rendered_detector
from atlas_onboard.sim.world import SimWorld
from atlas_onboard.worker import Deliver, SensorWorker

_logger = logging.getLogger(__name__)


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
    context = SimContext.from_env()
    mocap = context.scenario.mocap
    if mocap is not None and config.entity == WORLD and sensor.name == mocap.sensor:
        return MocapWorker(context, world, sensor.id)
    seed = camera_seed(context.seed, sensor.id)
    if context.replay and context.frames_dir is not None:
        folder = replay_folder(context.frames_dir, sensor.id)
        if folder.is_dir():
            return SimReplayWorker(context, world, sensor, folder, config.refine)
    if context.geometric:
        intr = SimWorld(context.scenario, world).cameras[sensor.id][1]
        detect = geometric_detector(context, sensor, intr, seed)
    else:
        detect = rendered_detector(context, world, sensor, seed, config.refine)
    return SimCameraWorker(context, world, sensor, detect)
