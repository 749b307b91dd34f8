"""A simulated camera inside a node: at each frame time it takes the ground truth, finds the markers in
view (:class:`atlas_onboard.sim.world.SimWorld`), and reports them as a detector would.

This module produces observations from geometry with a noise model (pixel noise on the corners,
solved by PnP) rather than from rendered images; :mod:`atlas_onboard.detector` renders and detects.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.config import SensorConfig, WorldConfig
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.sim.sources import SimContext
from atlas_onboard.sim.world import Sighting, SimWorld
from atlas_onboard.worker import SensorWorker

_logger = logging.getLogger(__name__)

NOISE_PX = 0.3  # corner noise of the geometric detector, pixels
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
        self.frames = 0
        self.skipped = 0
        self.detections = 0

    def counters(self) -> dict[str, int]:
        return {"frames": self.frames, "frames_skipped": self.skipped, "detections": self.detections}

    def _run(self, deliver: Callable[[MarkerData], None]) -> None:
        epoch = self.context.wait_epoch(self._stop)
        if epoch is None:
            return
        period = 1.0 / self.fps
        k = 0
        while not self._stop.is_set():
            t = k * period
            wait = epoch + t - time.time()
            if wait > 0:
                self._stop.wait(wait)
                continue
            if wait < -period:  # we fell behind: drop the frames whose time has passed, never queue
                missed = int(-wait / period)
                self.skipped += missed
                k += missed
                continue
            k += 1
            self.frames += 1
            truth = self.sim.truth(t)
            sightings = self.sim.sightings(self.sensor.id, truth, t)
            try:
                found = self.detect(t, sightings, {"truth": truth, "epoch": epoch, "frame": k})
            except Exception:  # a detector bug must not kill the camera thread; the frame is lost
                _logger.exception("camera %s: detection failed", self.name)
                continue
            for md in found:
                self.detections += 1
                deliver(md)


def geometric_detector(context: SimContext, sensor: SensorConfig, intrinsics: object, seed: int) -> FrameHandler:
    """Observations from the true corners plus pixel noise, solved by IPPE PnP (no image)."""
    import cv2

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
                )
            )
        return out

    return detect


def rendered_detector(context: SimContext, world: WorldConfig, sensor: SensorConfig, seed: int) -> FrameHandler:
    """Render the frame the camera would see (noise, motion blur) and run the real detector on it."""
    from atlas_onboard.detector.calibration import load as load_calibration
    from atlas_onboard.detector.pipeline import Detector
    from atlas_onboard.detector.render import Camera, MarkerView, render

    assert sensor.camera is not None and sensor.camera.calibration is not None
    cal = load_calibration(sensor.camera.calibration)
    cam = Camera(cal.width_px, cal.height_px, cal.K, cal.dist)
    detector = Detector(sensor, world, cal, decimate=2.0)
    optics = context.scenario.optics_of(sensor.entity, sensor.name)
    sim = SimWorld(context.scenario, world)
    dt = 1e-3

    def detect(t: float, sightings: list[Sighting], info: dict[str, object]) -> list[MarkerData]:
        epoch = float(info["epoch"])  # type: ignore[arg-type]
        frame = int(info["frame"])  # type: ignore[call-overload]
        truth = info["truth"]
        views = [MarkerView(s.marker.family, s.marker.id, s.marker.size_m, s.T_sensor_marker) for s in sightings]
        # Motion blur: how far the image of the marker centres moves during the exposure.
        blur = (0.0, 0.0)
        if sightings and optics.exposure_s > 0:
            later = sim.truth(t + dt)
            shifts = []
            for s in sightings:
                T_later = (
                    (later[sensor.entity] * sensor.T_entity_sensor).inv()
                    * later[s.marker.entity]
                    * s.marker.T_entity_marker
                )
                a = sim.cameras[sensor.id][1].project(s.T_sensor_marker.translation[None, :])[0]
                b = sim.cameras[sensor.id][1].project(T_later.translation[None, :])[0]
                shifts.append((b - a) * optics.exposure_s / dt)
            blur = tuple(np.mean(shifts, axis=0))  # type: ignore[assignment]
        del truth
        img = render(cam, views, seed=seed + frame, noise_sigma=optics.noise_sigma, blur_px=blur, supersample=3)
        return detector.detect(img, round((epoch + t) * 1e6))

    return detect


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
