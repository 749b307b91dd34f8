"""The simulated cameras inside a node: at each frame time a worker takes the ground truth, finds the
markers in view (:class:`atlas_onboard.sim.world.SimWorld`), and reports them as a detector would, either
from geometry with a noise model (pixel noise on the corners, posed by the real detector's pose stage:
:func:`geometric_detector`) or by running the real detector on the frame the camera would see
(:func:`rendered_detector`, images of :mod:`atlas_onboard.sim.camera`); or the node's own camera worker
replays the run's frames as an image folder (:class:`SimReplayWorker`).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from atlas_onboard.config import RefineConfig, SensorConfig, WorldConfig
from atlas_onboard.core.attitude import CameraTurn
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.detector.camera import CameraWorker
from atlas_onboard.detector.motion import body_rate_at, body_velocity_at
from atlas_onboard.detector.sources import ImageFolder, ReplayClock
from atlas_onboard.detector.workers import CameraDetectorSpec
from atlas_onboard.sim.camera import FrameRenderer, frames_path
from atlas_onboard.sim.context import SimContext
from atlas_onboard.sim.world import Intrinsics, Sighting, SimWorld
from atlas_onboard.worker import Deliver, SensorWorker

_logger = logging.getLogger(__name__)

NOISE_PX = 0.3  # corner noise of the geometric detector, pixels


@dataclass(frozen=True)
class FrameHandler:
    """What a simulated camera does with each frame: ``detect(t, sightings, info)`` gives its observations;
    ``needs_truth``: whether it needs the ground truth's sightings (a renderer draws frame j from its index
    alone); ``map_pose_changed(marker_id)``: the node's map moved a world marker (a real detector's, which
    stops correcting its sightings by the file's pose; geometry has none)."""

    detect: Callable[[float, list[Sighting], dict[str, object]], list[MarkerData]]
    needs_truth: bool = True
    map_pose_changed: Callable[[int], None] | None = None


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
        if self.detect.map_pose_changed is not None:
            self.detect.map_pose_changed(marker_id)

    def _skip(self, missed: int) -> None:
        self.skipped += missed

    def _run(self, deliver: Deliver) -> None:
        # when behind, the frames whose time has passed are dropped (counted), never queued
        for epoch, index, t in self.context.ticks(self._stop, 1.0 / self.fps, self._skip):
            self.frames += 1
            # Ground truth only when the detector needs it (not for images rendered before the run).
            truth = self.sim.truth(t) if self.detect.needs_truth else {}
            sightings = self.sim.sightings(self.sensor.id, truth, t) if truth else []
            info: dict[str, object] = {"truth": truth, "epoch": epoch, "index": index}
            if self.attitude_at is not None:  # the autopilot's, as a real camera's (CameraWorker)
                info["R_prev_now"] = self._turn.since_last(self.attitude_at(round((epoch + t) * 1e6)))
            info["body_rate"] = body_rate_at(self.rate_at, round((epoch + t) * 1e6))
            info["body_velocity"] = body_velocity_at(self.velocity_at, round((epoch + t) * 1e6))
            try:
                found = self.detect.detect(t, sightings, info)
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

        assert sensor.camera is not None and sensor.camera.calibration is not None
        camera = replace(sensor.camera, source=str(folder), replay=context.replay)
        spec = CameraDetectorSpec(sensor, world, load_calibration(camera.calibration), 2.0, refine)
        super().__init__(sensor.name, camera, spec.build())
        self.context = context

    def _run(self, deliver: Deliver) -> None:
        epoch = self.context.wait_epoch(self._stop)
        if epoch is None or self._stop.wait(max(epoch - time.time(), 0.0)):
            return
        clock = ReplayClock(paced=True, start_us=round(epoch * 1e6))
        self.counts["opened"] += 1
        self._consume(ImageFolder(Path(self.camera.source), self.camera.fps, self.context.replay, clock), deliver)


def geometric_detector(context: SimContext, sensor: SensorConfig, intrinsics: Intrinsics, seed: int) -> FrameHandler:
    """Observations from the true corners plus pixel noise (``NOISE_PX`` per axis, independent, in the
    distorted image), posed by the real detector's pose stage for such corners (no image): undistorted
    with their noise carried through the undistortion's Jacobian (:mod:`atlas_onboard.detector.pose`), then
    :func:`atlas_onboard.detector.marker_poses.solve_markers` (IPPE, Levenberg-Marquardt, sigma, covariance
    and the other planar solution) and :func:`atlas_onboard.detector.records.marker_data`, as
    :class:`atlas_onboard.detector.pipeline` does with the corners its edge fit refines."""
    from atlas_onboard.detector import pose
    from atlas_onboard.detector.marker_poses import solve_markers
    from atlas_onboard.detector.records import marker_data

    K = intrinsics.camera_matrix
    dist = np.asarray(intrinsics.distortion, dtype=float)

    def detect(t: float, sightings: list[Sighting], info: dict[str, object]) -> list[MarkerData]:
        if not sightings:
            return []
        capture_us = round((float(info["epoch"]) + t) * 1e6)  # type: ignore[arg-type]
        # Noise drawn per frame and marker: a frame skipped in one run leaves every other frame's the same.
        seen = np.concatenate(
            [s.corners_px + np.random.default_rng([seed, round(t * 1e6), s.marker.id]).normal(0.0, NOISE_PX, (4, 2))
             for s in sightings]
        )  # fmt: skip
        ideal = pose.undistort(seen, K, dist, False).reshape(-1, 4, 2)
        stretch = pose.undistortion_jacobian(seen, K, dist, False)
        stretches = [None if stretch is None else stretch[4 * k : 4 * k + 4] for k in range(len(sightings))]
        poses = solve_markers(
            list(ideal),
            [s.marker.size_m for s in sightings],
            K,
            [NOISE_PX] * len(sightings),
            stretches,
            [NOISE_PX] * len(sightings),  # the corners' noise is known: as an edge fit's measured one
            [_corner_covariance(a) for a in stretches],
        )
        out = []
        for s, mp in zip(sightings, poses, strict=True):
            if mp is None:
                continue
            alt = (mp.p_alt_m, mp.q_alt_xyzw) if mp.p_alt_m is not None and mp.q_alt_xyzw is not None else None
            out.append(marker_data(sensor.id, s.marker.id, mp.p_m, mp.q_xyzw, mp.sigma_m, mp.reprojection_error_px,
                                   mp.ambiguity, capture_us, alt, mp.covariance))  # fmt: skip
        return out

    return FrameHandler(detect)


def _corner_covariance(stretch: NDArray[np.float64] | None) -> NDArray[np.float64]:
    """(8, 8) covariance, in undistorted pixels, of four corners with independent noise ``NOISE_PX`` per axis in
    the image: each corner's ``NOISE_PX^2 A A^T`` with ``A`` its undistortion Jacobian (identity without one)."""
    cov = np.zeros((8, 8))
    for k in range(4):
        A = np.eye(2) if stretch is None else stretch[k]
        cov[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = NOISE_PX**2 * (A @ A.T)
    return cov


def rendered_detector(
    context: SimContext, world: WorldConfig, sensor: SensorConfig, seed: int, refine: RefineConfig | None = None
) -> FrameHandler:
    """Run the real detector on the frame the camera would see: the run's pre-rendered image of that
    instant when there is one (:func:`prerender`), otherwise rendered now. ``refine``: the node refines
    the map (the detector reports some images marker by marker, as a real camera's does)."""
    from atlas_onboard.detector.calibration import load as load_calibration

    assert sensor.camera is not None and sensor.camera.calibration is not None
    detector = CameraDetectorSpec(sensor, world, load_calibration(sensor.camera.calibration), 2.0, refine).build()
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
            info.get("body_velocity"),  # type: ignore[arg-type]
        )

    return FrameHandler(detect, needs_truth=False, map_pose_changed=detector.map_pose_changed)
