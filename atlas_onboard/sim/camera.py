"""The images a simulated camera takes: :class:`FrameRenderer` draws frame j of a camera from the ground
truth with the scenario's optics, :func:`prerender` renders a run's frames before it starts on all cores,
:func:`frames_path` and :func:`replay_folder` say where a run keeps them, :func:`camera_seed` each camera's
noise seed. The workers that turn them into observations inside a node are :mod:`atlas_onboard.sim.workers`.
"""

from __future__ import annotations

import itertools
import math
import multiprocessing as mp
import os
import threading
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import SensorConfig, WorldConfig, load_world
from atlas_onboard.config.settings import READOUT_BOTTOM_UP
from atlas_onboard.sim.scenario import Scenario
from atlas_onboard.sim.world import SimWorld

SUPERSAMPLE = 3  # rendered cameras: samples per pixel along each axis


def camera_seed(run_seed: int, sensor_id: int) -> int:
    """The seed of one camera's images (pixel noise) in a run."""
    return run_seed * 1000 + sensor_id


def frames_path(directory: Path, sensor_id: int) -> Path:
    """Where a run keeps the pre-rendered images of one camera (an ``.npy`` array frames x rows x cols)."""
    return directory / f"frames-{sensor_id}.npy"


def replay_folder(frames_dir: Path, sensor_id: int) -> Path:
    """The image folder of a camera's pre-rendered frames (one PNG a frame, in name order)."""
    return frames_dir / f"replay-{sensor_id}"


class FrameRenderer:
    """The image a simulated camera takes at frame index j (time j / fps): the markers it sees, with
    the scenario's optics (lens distortion, pixel noise, motion blur), rendered from ground truth.

    Timing is the camera settings' (the world file's, as the node reads them): the frame's time is the
    mid-exposure of its middle row; with ``readout_ms`` each row is exposed at its own instant
    (:meth:`row_times`) and drawn with the camera's pose then; the blur covers ``exposure_ms``, or the
    optics' ``exposure_s`` where the settings leave it at 0."""

    def __init__(self, scenario: Scenario, world: WorldConfig, sensor: SensorConfig, seed: int) -> None:
        from atlas_onboard.detector.render import Camera, prepare

        self.sim = SimWorld(scenario, world)
        self.sensor = sensor
        self.seed = seed
        self.intr = self.sim.cameras[sensor.id][1]
        self.cam = Camera(
            self.intr.width_px, self.intr.height_px, self.intr.camera_matrix, np.array(self.intr.distortion)
        )
        self.optics = scenario.optics_of(sensor.entity, sensor.name)
        assert sensor.camera is not None
        self.fps = sensor.camera.fps if sensor.camera.fps > 0 else 30.0
        self.readout_s = sensor.camera.readout_ms / 1000.0
        self.bottom_up = sensor.camera.readout_order == READOUT_BOTTOM_UP
        self.exposure_s = (
            sensor.camera.exposure_ms / 1000.0 if sensor.camera.exposure_ms > 0 else self.optics.exposure_s
        )
        self._M_entity_sensor = sensor.T_entity_sensor.as_matrix()
        prepare(self.cam, SUPERSAMPLE)  # the renderer's per-camera tables, before the first frame
        self.room = None
        if scenario.room is not None:
            from atlas_onboard.sim.room import RoomRenderer

            self.room = RoomRenderer(scenario.room, world, sensor, self.intr, self.optics.noise_sigma)

    def row_times(self, t: float) -> NDArray[np.float64]:
        """The mid-exposure instant (s) of each image row of the frame stamped ``t``: row r at
        ``t + (r_from_first / (height - 1) - 0.5) * readout``, the first row read first."""
        h = self.intr.height_px
        from_first = np.arange(h, dtype=float)[::-1] if self.bottom_up else np.arange(h, dtype=float)
        return t + (from_first / max(h - 1, 1) - 0.5) * self.readout_s

    def sensor_poses(self, times: NDArray[np.float64]) -> NDArray[np.float64]:
        """The camera's optical frame in the world (len(times), 4, 4) at ``times`` (s), vibration included."""
        p, q = self.sim.truth_series(self.sensor.entity, times)
        M = np.tile(np.eye(4), (len(times), 1, 1))
        M[:, :3, :3] = Rotation.from_quat(q).as_matrix()
        M[:, :3, 3] = p
        return M @ self._M_entity_sensor

    def __call__(self, index: int) -> NDArray[np.uint8]:
        from atlas_onboard.detector.render import MarkerView, render

        t = index / self.fps
        sensor, dt = self.sensor, 1e-3
        if self.room is not None:
            return self._in_room(t)
        truth = self.sim.truth(t)
        sightings = self.sim.sightings(sensor.id, truth, t)
        views = [MarkerView(s.marker.family, s.marker.id, s.marker.size_m, s.T_sensor_marker) for s in sightings]
        if self.readout_s > 0 and views:  # each row with the camera's pose at its instant
            rows_sensor_world = np.linalg.inv(self.sensor_poses(self.row_times(t)))
            views = [
                replace(
                    v,
                    rows=rows_sensor_world @ truth[s.marker.entity].as_matrix() @ s.marker.T_entity_marker.as_matrix(),
                )
                for v, s in zip(views, sightings, strict=True)
            ]
        # Motion blur: how far the image of the marker centres moves during the exposure.
        blur = (0.0, 0.0)
        if sightings and self.exposure_s > 0:
            later = self.sim.truth(t + dt, {sensor.entity} | {s.marker.entity for s in sightings})
            M_later_sensor = np.linalg.inv(later[sensor.entity].as_matrix() @ self._M_entity_sensor)
            shifts = []
            for s in sightings:
                M_marker = later[s.marker.entity].as_matrix() @ s.marker.T_entity_marker.as_matrix()
                a = self.intr.project(s.T_sensor_marker.translation[None, :])[0]
                b = self.intr.project((M_later_sensor @ M_marker)[None, :3, 3])[0]
                shifts.append((b - a) * self.exposure_s / dt)
            blur = tuple(np.mean(shifts, axis=0))  # type: ignore[assignment]
        return render(
            self.cam,
            views,
            seed=self.seed + index + 1,
            noise_sigma=self.optics.noise_sigma,
            blur_px=blur,
            supersample=SUPERSAMPLE,
        )

    def _in_room(self, t: float) -> NDArray[np.uint8]:
        """The frame at ``t`` rendered by the scenario's room (every marker, world-space floor)."""
        assert self.room is not None
        half = self.exposure_s / 2.0
        M = {}
        for k, tk in enumerate((t, t - half, t + half)):
            truth = self.sim.truth(tk, None if k == 0 else {self.sensor.entity})
            M[k] = truth[self.sensor.entity].as_matrix() @ self._M_entity_sensor
            if k == 0:
                entities = {name: T.as_matrix() for name, T in truth.items()}
        seed = self.seed * 100_003 + round(t * self.fps) + 1
        rows = None
        if self.readout_s > 0:
            from atlas_onboard.sim.room import RowPoses

            times = self.row_times(t)
            poses = self.sensor_poses(np.concatenate([times, times - half, times + half]))
            rows = RowPoses(*np.split(poses, 3))
        return self.room.render(M[0], M[1], M[2], entities, seed, rows)


def _render_frames(args: tuple[str, Path, int, int, Path, int, int, int]) -> None:
    from atlas_onboard.sim import scenarios

    scenario, world_file, sensor_id, seed, path, start, stop, first = args
    world = load_world(world_file)
    renderer = FrameRenderer(scenarios.get(scenario), world, world.sensors[sensor_id], seed)
    frames = np.load(path, mmap_mode="r+")
    for j in range(start, stop):
        frames[j] = renderer(first + j)
    frames.flush()


def prerender(
    scenario: Scenario, world_file: Path, run_seed: int, duration_s: float, directory: Path, start_s: float = 0.0
) -> int:
    """Render every frame of the run's cameras before it starts, on all cores, into ``directory``
    (the frames from ``start_s`` into the scenario: frame j is the camera's frame at ``start_s + j / fps``).

    A real drone's camera delivers its images for free; rendering them while the run goes would
    charge the node's processor for work the drone never does, and on a small machine make the
    figures depend on its speed. Returns the number of frames rendered."""
    world = load_world(world_file)
    jobs = []
    total = 0
    for sensor_id in SimWorld(scenario, world).cameras:
        sensor = world.sensors[sensor_id]
        assert sensor.camera is not None
        if sensor.camera.source != "sim":
            continue
        fps = sensor.camera.fps if sensor.camera.fps > 0 else 30.0
        n = math.floor(duration_s * fps) + 2
        shape = (n, sensor.camera.height_px, sensor.camera.width_px)
        path = frames_path(directory, sensor_id)
        np.lib.format.open_memmap(path, mode="w+", dtype=np.uint8, shape=shape).flush()
        workers = os.cpu_count() or 1
        bounds = np.linspace(0, n, workers + 1).astype(int)
        seed = camera_seed(run_seed, sensor_id)
        first = round(start_s * fps)
        jobs += [
            (scenario.name, world_file, sensor_id, seed, path, int(a), int(b), first)
            for a, b in itertools.pairwise(bounds)
        ]
        total += n
    if not jobs:
        return 0
    # Fork when this process has no other thread (fast, nothing to import again); otherwise fork from a
    # fork server that has this module imported (forking a process with threads is unsafe; spawning
    # workers imports everything again for each render), or spawn where there is none.
    methods = mp.get_all_start_methods()
    if threading.active_count() == 1 and "fork" in methods:
        context = mp.get_context("fork")
        if scenario.room is not None:  # the room's textures made once here, for every forked worker
            from atlas_onboard.sim.room import atlas

            atlas(scenario.room)
    elif "forkserver" in methods:
        context = mp.get_context("forkserver")
        context.set_forkserver_preload([__name__])
    else:
        context = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(len(jobs), os.cpu_count() or 1), mp_context=context) as ex:
        list(ex.map(_render_frames, jobs))
    return total
