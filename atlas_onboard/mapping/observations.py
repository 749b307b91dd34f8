"""The map's input: every frame of every input (recordings, videos, image folders) searched for the
world file's world markers (step 1 of :mod:`atlas_onboard.mapping.build`).

``decimate`` 1 (the default) searches every frame whole at full resolution; ``decimate`` 2 searches as
the node does (:class:`~atlas_onboard.detector.pipeline.Detector`): where the previous frame's markers
are predicted, the regions of black-white contrast, and now and then the whole image decimated, the
corners fitted at full resolution either way. It finds the same markers at the same corners in
consecutive frames, but with many markers in view, as a mapping flight has them, it costs more than the
whole-frame search (``benchmarks/bench_map.py``), so it is not the default. Ids the world file does not
list, and an id seen twice in one frame (two places more than a marker apart), are counted either way;
a duplicated id is dropped from that frame."""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import WORLD, SensorConfig, WorldConfig
from atlas_onboard.config.settings import READOUT_BOTTOM_UP
from atlas_onboard.core.shutter import RowClock
from atlas_onboard.detector.backends import Detection, MarkerFinder
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.calibration import load as load_calibration
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.search import MAX_REGION_DECIMATE
from atlas_onboard.detector.sources import IMAGE_SUFFIXES, SourceError
from atlas_onboard.errors import AtlasError
from atlas_onboard.recording.format import RecordingError, is_recording, read_frames, read_info


class MapError(AtlasError):
    """A map that cannot be built from the input; the message says why in one line."""


_MAP_ENTITY = "map camera"  # no entity of a world file has a space in its name: every marker is another's


class _SeeingFinder(MarkerFinder):
    """The finder the tracker searches with, noting in each frame the ids the world file does not list
    and the ids one search found at two places (``unknown``, ``twice``; cleared by the caller)."""

    def __init__(self, wanted: dict[int, str], decimate: float, extra: tuple[float, ...]) -> None:
        super().__init__(wanted, decimate, extra=extra)
        self.unknown: set[int] = set()
        self.twice: set[int] = set()

    def find(self, gray: NDArray[np.uint8], decimate: float | None = None) -> list[Detection]:
        out = []
        for backend in self.backends:
            found = backend.detect(gray, decimate)
            self.twice |= _duplicated(found)
            for d in found:
                if self.wanted.get(d.marker_id) == d.family:
                    out.append(d)
                else:
                    self.unknown.add(d.marker_id)
        return out


def _map_sensor() -> SensorConfig:
    return SensorConfig("map", 0, _MAP_ENTITY, RigidTransform.identity())


def _duplicated(found: list[Detection]) -> set[int]:
    """Ids one search found at two places more than a marker's side apart."""
    centres: dict[int, list[NDArray[np.float64]]] = {}
    out = set()
    for d in found:
        c = np.asarray(d.corners_px, dtype=float).reshape(4, 2)
        side = float(np.linalg.norm(c[0] - c[1]))
        if any(np.linalg.norm(other - c.mean(axis=0)) > side for other in centres.get(d.marker_id, [])):
            out.add(d.marker_id)
        centres.setdefault(d.marker_id, []).append(c.mean(axis=0))
    return out


@dataclass(frozen=True)
class FrameInfo:
    """One input frame that showed at least one marker."""

    source: int  # index of the input
    index: int  # frame number within its input
    capture_time_us: int
    lens: int  # index into the inputs' lenses
    q_level_body_wxyz: tuple[float, float, float, float] | None = None


@dataclass
class Observations:
    """Every marker detection of the inputs.

    Attributes:
        frames: the frames that showed markers; lenses: one calibration per input.
        obs_frame, obs_marker_id: (N,) frame (index into ``frames``) and marker id of each detection.
        corners_px: (N, 4, 2) raw corners (distorted pixels, OpenCV order).
        sources: a name per input; mountings: the camera's pose on the body per input (or None).
        duplicates: per marker id, how many frames showed it more than once.
        unknown: per id of a marker the world file does not list (in a family it uses), how many frames
            showed it.
        detect_s: time spent reading and detecting.
    """

    frames: list[FrameInfo] = field(default_factory=list)
    lenses: list[Calibration] = field(default_factory=list)
    sources: list[str] = field(default_factory=list)
    mountings: list[NDArray[np.float64] | None] = field(default_factory=list)
    obs_frame: list[int] = field(default_factory=list)
    obs_marker_id: list[int] = field(default_factory=list)
    corners_px: list[NDArray[np.float64]] = field(default_factory=list)
    duplicates: Counter[int] = field(default_factory=Counter)
    unknown: Counter[int] = field(default_factory=Counter)
    frames_read: int = 0
    detect_s: float = 0.0
    clocks: list[RowClock | None] = field(default_factory=list)  # per input: its rolling shutter, or None


def _row_clock(path: Path, world: WorldConfig) -> RowClock | None:
    """A recording's rolling shutter, from its sensor's camera in the world file (None: not one)."""
    if not is_recording(path):
        return None
    info = read_info(path)
    sensor = world.sensors.get(info.sensor_id)
    if sensor is None or sensor.camera is None or sensor.camera.readout_ms <= 0:
        return None
    cam = sensor.camera
    return RowClock(cam.readout_ms * 1e-3, info.calibration.height, cam.readout_order == READOUT_BOTTOM_UP)


def _input_frames(
    path: Path, calibration: Path | None, fps: float
) -> tuple[Calibration, NDArray[np.float64] | None, Iterator[tuple[int, NDArray[np.uint8], int, tuple | None]]]:
    """The lens, the camera's mounting (4x4 T_body_camera, or None) and the frames of one input."""
    if is_recording(path):
        info = read_info(path)
        mount = None
        if info.p_body_camera_m is not None and info.q_body_camera_wxyz is not None:
            w, x, y, z = info.q_body_camera_wxyz
            mount = np.eye(4)
            mount[:3, :3] = Rotation.from_quat([x, y, z, w]).as_matrix()
            mount[:3, 3] = info.p_body_camera_m
        frames = ((f.index, f.gray, f.capture_time_us, f.q_level_body_wxyz) for f in read_frames(path))
        return info.calibration, mount, frames
    if path.is_dir() and not any(path.iterdir()):
        raise MapError(f"{path}: empty directory (no recording, no images)")
    if calibration is None:
        raise MapError(f"{path}: not a recording; a video or image folder needs --calibration")
    cal = load_calibration(calibration)
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise MapError(f"{path}: no recording ({'recording.json'}) and no images in it")

        def folder() -> Iterator[tuple[int, NDArray[np.uint8], int, None]]:
            for k, f in enumerate(files):
                img = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
                if img is None:
                    raise MapError(f"{f}: not a readable image")
                yield k, img, round(k * 1e6 / fps), None

        return cal, None, folder()
    if not path.is_file():
        raise MapError(f"{path}: no such file or directory")

    def video() -> Iterator[tuple[int, NDArray[np.uint8], int, None]]:
        cap = cv2.VideoCapture(str(path))
        if not cap.isOpened():
            raise MapError(f"{path}: not a readable video, image folder or recording")
        rate = cap.get(cv2.CAP_PROP_FPS) or fps
        k = 0
        try:
            while True:
                ok, img = cap.read()
                if not ok or img is None:
                    break
                gray = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
                yield k, gray, round(k * 1e6 / rate), None
                k += 1
        finally:
            cap.release()

    return cal, None, video()


def collect(
    inputs: list[Path],
    world: WorldConfig,
    calibration: Path | None = None,
    fps: float = 30.0,
    stride: int = 1,
    progress: Callable[[str], None] | None = None,
    decimate: float = 1.0,
) -> Observations:
    """Detect the world file's world markers in every ``stride``-th frame of every input, whole at full
    resolution (``decimate`` 1) or as the node does (``decimate`` 2, tracking)."""
    t0 = time.perf_counter()
    wanted = {m.id: m.family for m in world.markers.values() if m.entity == WORLD}
    if not wanted:
        raise MapError("the world file has no markers on the world entity to map")
    # Every configured id is searched (a drone's marker seen by chance is not taken for another).
    wanted_all = {m.id: m.family for m in world.markers.values()}
    obs = Observations()
    for s, path in enumerate(inputs):
        path = Path(path)
        try:
            cal, mount, frames = _input_frames(path, calibration, fps)
            obs.lenses.append(cal)
            obs.sources.append(str(path))
            obs.mountings.append(mount)
            finder = _SeeingFinder(wanted_all, max(decimate, 1.0), (MAX_REGION_DECIMATE,) if decimate > 1.0 else ())
            tracker = None
            if decimate > 1.0:
                tracker = Detector(_map_sensor(), world, cal, decimate=decimate)
                tracker.finder = tracker.search.finder = finder  # the node's search, seeing every id
            n = 0
            for k, gray, stamp, q in frames:
                n += 1
                if (n - 1) % stride:
                    continue
                cal.check_size(gray.shape[1], gray.shape[0], str(path))
                finder.unknown.clear()
                finder.twice.clear()
                found = tracker.find(gray) if tracker is not None else finder.find(gray, 1.0)
                for mid in finder.unknown:
                    obs.unknown[mid] += 1
                for mid in finder.twice & set(wanted):
                    obs.duplicates[mid] += 1
                dets = [d for d in found if d.marker_id in wanted and d.marker_id not in finder.twice]
                if not dets:
                    continue
                obs.frames.append(FrameInfo(s, k, stamp, s, q))
                for d in dets:
                    obs.obs_frame.append(len(obs.frames) - 1)
                    obs.obs_marker_id.append(d.marker_id)
                    obs.corners_px.append(np.asarray(d.corners_px, dtype=float).reshape(4, 2))
            obs.frames_read += n
        except (RecordingError, SourceError) as exc:
            raise MapError(str(exc)) from None
        if n == 0:
            raise MapError(f"{path}: no frames")
        obs.clocks.append(_row_clock(path, world))
        if progress:
            progress(f"{path}: {n} frames read, {sum(1 for f in obs.frames if f.source == s)} with markers")
    obs.detect_s = time.perf_counter() - t0
    return obs
