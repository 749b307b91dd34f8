"""A simulated camera inside a node: at each frame time it takes the ground truth, finds the markers in
view (:class:`atlas_onboard.sim.world.SimWorld`), and reports them as a detector would.

This module produces observations from geometry with a noise model (pixel noise on the corners,
solved by PnP) rather than from rendered images; :mod:`atlas_onboard.detector` renders and detects.
"""

from __future__ import annotations

import itertools
import logging
import math
import multiprocessing as mp
import os
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import RefineConfig, SensorConfig, WorldConfig, load_world
from atlas_onboard.config.settings import READOUT_BOTTOM_UP
from atlas_onboard.core.attitude import CameraTurn
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.detector.camera import CameraWorker
from atlas_onboard.detector.motion import body_rate_at
from atlas_onboard.detector.sources import ImageFolder, ReplayClock
from atlas_onboard.node_refine import sampled
from atlas_onboard.sim.scenarios import Scenario
from atlas_onboard.sim.sources import SimContext
from atlas_onboard.sim.world import Sighting, SimWorld
from atlas_onboard.worker import Deliver, SensorWorker

_logger = logging.getLogger(__name__)

NOISE_PX = 0.3  # corner noise of the geometric detector, pixels
SUPERSAMPLE = 3  # rendered cameras: samples per pixel along each axis
FrameHandler = Callable[[float, list[Sighting], dict[str, object]], list[MarkerData]]


class SimCameraWorker(SensorWorker):
    """Frames at the camera's rate on the run's timeline; one thread; late frames are skipped (counted)."""

    def __init__(self, context: SimContext, world: WorldConfig, sensor: SensorConfig, detect: FrameHandler) -> None:
        super().__init__()
        self.name = sensor.name
        self.context = context
        self.sim = SimWorld(context.scenario, world)
        self.sensor = sensor
        self.intrinsics = self.sim.cameras[sensor.id][1]
        self.fps = sensor.camera.fps if sensor.camera is not None and sensor.camera.fps > 0 else 30.0
        self.detect = detect
        self._turn = CameraTurn(sensor.T_entity_sensor.rotation)
        self.frames = 0
        self.skipped = 0
        self.detections = 0

    def counters(self) -> dict[str, int]:
        return {"frames": self.frames, "frames_skipped": self.skipped, "detections": self.detections}

    def map_pose_changed(self, marker_id: int) -> None:
        forward = getattr(self.detect, "map_pose_changed", None)  # a rendered camera's detector; geometry has none
        if forward is not None:
            forward(marker_id)

    def _skip(self, missed: int) -> None:
        self.skipped += missed

    def _run(self, deliver: Deliver) -> None:
        # when behind, the frames whose time has passed are dropped (counted), never queued
        for epoch, index, t in self.context.ticks(self._stop, 1.0 / self.fps, self._skip):
            self.frames += 1
            # Ground truth only when the detector needs it (not for images rendered before the run).
            truth = self.sim.truth(t) if getattr(self.detect, "needs_truth", True) else {}
            sightings = self.sim.sightings(self.sensor.id, truth, t) if truth else []
            info: dict[str, object] = {"truth": truth, "epoch": epoch, "index": index}
            if self.attitude_at is not None:  # the autopilot's, as a real camera's (CameraWorker)
                info["R_prev_now"] = self._turn.since_last(self.attitude_at(round((epoch + t) * 1e6)))
            info["body_rate"] = body_rate_at(self.rate_at, round((epoch + t) * 1e6))
            try:
                found = self.detect(t, sightings, info)
            except Exception:  # a detector bug must not kill the camera thread; the frame is lost
                _logger.exception("camera %s: detection failed", self.name)
                continue
            if found:
                self.detections += len(found)
                deliver(list(found))


class SimReplayWorker(CameraWorker):
    """A camera whose ``camera.source`` is an image folder of the run's frames, replayed in the run's
    replay mode by the node's own camera worker and file source (:mod:`atlas_onboard.detector.sources`).
    Its file time is mapped onto the wall clock at the run's epoch (a replay started by hand starts when
    its first image is read), so that its stamps are on the run's timeline."""

    def __init__(
        self, context: SimContext, world: WorldConfig, sensor: SensorConfig, folder: Path, refine: RefineConfig | None
    ) -> None:
        from atlas_onboard.detector.calibration import load as load_calibration
        from atlas_onboard.detector.pipeline import Detector

        assert sensor.camera is not None and sensor.camera.calibration is not None
        camera = replace(sensor.camera, source=str(folder), replay=context.replay)
        detector = sampled(Detector(sensor, world, load_calibration(camera.calibration), decimate=2.0), world, refine)
        super().__init__(sensor.name, camera, detector)
        self.context = context

    def _run(self, deliver: Deliver) -> None:
        epoch = self.context.wait_epoch(self._stop)
        if epoch is None or self._stop.wait(max(epoch - time.time(), 0.0)):
            return
        clock = ReplayClock(paced=True, start_us=round(epoch * 1e6))
        self.counts["opened"] += 1
        self._consume(ImageFolder(Path(self.camera.source), self.camera.fps, self.context.replay, clock), deliver)


def geometric_detector(context: SimContext, sensor: SensorConfig, intrinsics: object, seed: int) -> FrameHandler:
    """Observations from the true corners plus pixel noise, solved by IPPE PnP (no image)."""
    import cv2

    from atlas_onboard.core.markerdata import matrix_to_upper
    from atlas_onboard.detector.pose import CornerFit, pose_covariance
    from atlas_onboard.sim.world import marker_corners

    rng = np.random.default_rng(seed)
    K = intrinsics.camera_matrix  # type: ignore[attr-defined]
    dist = np.asarray(intrinsics.distortion, dtype=float)  # type: ignore[attr-defined]

    def detect(t: float, sightings: list[Sighting], info: dict[str, object]) -> list[MarkerData]:
        epoch = float(info["epoch"])  # type: ignore[arg-type]
        out = []
        for s in sightings:
            obj = marker_corners(s.marker.size_m)
            img = s.corners_px + rng.normal(0.0, NOISE_PX, (4, 2))
            ok, rvecs, tvecs, errs = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
            if not ok or not len(rvecs):
                continue
            r = Rotation.from_rotvec(np.asarray(rvecs[0]).ravel())
            p = np.asarray(tvecs[0]).ravel()
            e = np.asarray(errs).ravel()
            x, y, z, w = r.as_quat()
            side_px = float(np.mean(np.linalg.norm(np.roll(img, -1, axis=0) - img, axis=1)))
            # Range error of a square seen at side_px pixels with corner noise of NOISE_PX.
            sigma = max(0.001, float(np.linalg.norm(p)) * 2.0 * NOISE_PX / max(side_px, 1.0))
            cov = pose_covariance(CornerFit(r.as_matrix(), p, obj, K), NOISE_PX, float(e[0]) if len(e) else math.nan)
            out.append(
                MarkerData(
                    sensor_id=sensor.id,
                    marker_id=s.marker.id,
                    sigma_m=sigma,
                    p_sensor_marker_m=(float(p[0]), float(p[1]), float(p[2])),
                    q_sensor_marker_wxyz=(float(w), float(x), float(y), float(z)),
                    capture_time_us=round((epoch + t) * 1e6),
                    reprojection_error_px=float(e[0]) if len(e) else float("nan"),
                    ambiguity_ratio=float(e[0] / e[1]) if len(e) > 1 and e[1] > 0 else float("nan"),
                    **_alt_fields(rvecs, tvecs),
                    covariance=matrix_to_upper(cov) if cov is not None else (),
                )
            )
        return out

    return detect


def camera_seed(run_seed: int, sensor_id: int) -> int:
    """The seed of one camera's images (pixel noise) in a run."""
    return run_seed * 1000 + sensor_id


def frames_path(directory: Path, sensor_id: int) -> Path:
    """Where a run keeps the pre-rendered images of one camera (an ``.npy`` array frames x rows x cols)."""
    return directory / f"frames-{sensor_id}.npy"


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


def rendered_detector(
    context: SimContext, world: WorldConfig, sensor: SensorConfig, seed: int, refine: RefineConfig | None = None
) -> FrameHandler:
    """Run the real detector on the frame the camera would see: the run's pre-rendered image of that
    instant when there is one (:func:`prerender`), otherwise rendered now. ``refine``: the node refines
    the map (the detector reports some images marker by marker, as a real camera's does)."""
    from atlas_onboard.detector.calibration import load as load_calibration
    from atlas_onboard.detector.pipeline import Detector

    assert sensor.camera is not None and sensor.camera.calibration is not None
    detector = sampled(
        Detector(sensor, world, load_calibration(sensor.camera.calibration), decimate=2.0), world, refine
    )
    frames: NDArray[np.uint8] | None = None
    if context.frames_dir is not None and frames_path(context.frames_dir, sensor.id).exists():
        frames = np.load(frames_path(context.frames_dir, sensor.id), mmap_mode="r")
    # The live renderer (its tables take a moment and some memory) only where there are no frames.
    renderer = FrameRenderer(context.scenario, world, sensor, seed) if frames is None else None

    def render_now(index: int) -> NDArray[np.uint8]:
        nonlocal renderer
        if renderer is None:  # past the pre-rendered frames (a run longer than planned)
            renderer = FrameRenderer(context.scenario, world, sensor, seed)
        return renderer(index)

    def detect(t: float, sightings: list[Sighting], info: dict[str, object]) -> list[MarkerData]:
        epoch = float(info["epoch"])  # type: ignore[arg-type]
        index = int(info["index"])  # type: ignore[call-overload]
        img = np.array(frames[index]) if frames is not None and index < len(frames) else render_now(index)
        return detector.detect(
            img,
            round((epoch + t) * 1e6),
            info.get("R_prev_now"),
            info.get("body_rate"),  # type: ignore[arg-type]
        )

    detect.needs_truth = False  # type: ignore[attr-defined]  # it renders from the index alone
    detect.map_pose_changed = detector.map_pose_changed  # type: ignore[attr-defined]
    return detect


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
    elif "forkserver" in methods:
        context = mp.get_context("forkserver")
        context.set_forkserver_preload([__name__])
    else:
        context = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=min(len(jobs), os.cpu_count() or 1), mp_context=context) as ex:
        list(ex.map(_render_frames, jobs))
    return total


def _alt_fields(rvecs: Sequence[np.ndarray], tvecs: Sequence[np.ndarray]) -> dict[str, tuple[float, ...]]:
    """MarkerData's fields of IPPE's other solution, as the real detector fills them (none: NaN)."""
    if len(rvecs) < 2:
        return {}
    x, y, z, w = Rotation.from_rotvec(np.asarray(rvecs[1]).ravel()).as_quat()
    p = np.asarray(tvecs[1], dtype=float).ravel()
    return {
        "p_sensor_marker_alt_m": (float(p[0]), float(p[1]), float(p[2])),
        "q_sensor_marker_alt_wxyz": (float(w), float(x), float(y), float(z)),
    }
