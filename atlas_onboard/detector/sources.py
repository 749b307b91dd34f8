"""Camera sources and the camera worker: frames in, MarkerData out, one thread per camera.

Sources: a V4L2 device (index or path, with width, height, fps and fourcc), a video file, a folder of
images (in name order; a number in the name that looks like a time stamp is used as such), or an
RTSP/HTTP URL through OpenCV. File sources are paced at their frame rate unless ``fast``, and stamp
each frame from its position in the file; live sources stamp the capture time minus the configured
fixed latency. A source that fails or stops delivering is reopened with backoff; the worker reports
it and keeps running. A slow detector drops frames (counted); it never builds a queue.
"""

from __future__ import annotations

import logging
import re
import threading
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.config import CameraConfig
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.errors import AtlasError
from atlas_onboard.worker import Deliver, SensorWorker

_logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm"}
BACKOFF_S = (0.5, 1.0, 2.0, 5.0)


class SourceError(AtlasError):
    """A camera source that cannot be opened or read."""


@dataclass
class Frame:
    gray: NDArray[np.uint8]
    capture_time_us: int


class Source:
    """Base: ``frames()`` yields frames until the source ends or fails (then raises SourceError)."""

    live = True

    def frames(self) -> Iterator[Frame]:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass


def _gray(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


class ImageFolder(Source):
    """Images of a folder in name order; stamps from a number of 10+ digits in the name (us, ms or s
    since the epoch by magnitude), else from the position at ``fps``."""

    live = False

    def __init__(self, path: Path, fps: float, fast: bool, start_us: int) -> None:
        self.files = sorted(p for p in Path(path).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise SourceError(f"{path}: no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        self.fps = fps or 10.0
        self.fast = fast
        self.start_us = start_us

    @staticmethod
    def stamp_from_name(name: str) -> int | None:
        m = re.search(r"(\d{10,19})", name)
        if not m:
            return None
        v = int(m.group(1))
        digits = len(m.group(1))
        return v * 1_000_000 if digits <= 10 else v * 1000 if digits <= 13 else v if digits <= 16 else v // 1000

    def frames(self) -> Iterator[Frame]:
        t0 = time.monotonic()
        for k, path in enumerate(self.files):
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise SourceError(f"{path}: not a readable image")
            if not self.fast:
                time.sleep(max(t0 + k / self.fps - time.monotonic(), 0.0))
            stamp = self.stamp_from_name(path.name)
            yield Frame(img, stamp if stamp is not None else self.start_us + round(k * 1e6 / self.fps))


class Capture(Source):
    """An OpenCV VideoCapture: V4L2 device, video file or stream URL."""

    def __init__(self, camera: CameraConfig, fast: bool, start_us: int) -> None:
        src = camera.source
        self.live = not Path(src).is_file()
        index = int(src) if src.isdigit() else None
        self.cap = cv2.VideoCapture(index if index is not None else src)
        if not self.cap.isOpened():
            raise SourceError(f"camera source {src!r}: cannot be opened")
        if camera.fourcc:
            self.cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*camera.fourcc))
        if camera.width_px:
            self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, camera.width_px)
            self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, camera.height_px)
        if camera.fps:
            self.cap.set(cv2.CAP_PROP_FPS, camera.fps)
        self.fps = self.cap.get(cv2.CAP_PROP_FPS) or camera.fps or 30.0
        self.fast = fast
        self.start_us = start_us
        self.latency_us = round(camera.latency_ms * 1000)
        self.name = src

    def frames(self) -> Iterator[Frame]:
        t0 = time.monotonic()
        k = 0
        while True:
            ok, img = self.cap.read()
            if not ok or img is None:
                if self.live:
                    raise SourceError(f"camera source {self.name!r} stopped delivering frames")
                return
            if self.live:
                stamp = int(time.time() * 1e6) - self.latency_us
            else:
                stamp = self.start_us + round(k * 1e6 / self.fps)
                if not self.fast:
                    time.sleep(max(t0 + k / self.fps - time.monotonic(), 0.0))
            k += 1
            yield Frame(_gray(img), stamp)

    def close(self) -> None:
        self.cap.release()


def open_source(camera: CameraConfig, fast: bool = False, start_us: int | None = None) -> Source:
    """The source a camera block describes (``sim`` is handled by the simulator)."""
    start = int(time.time() * 1e6) if start_us is None else start_us
    path = Path(camera.source)
    if path.is_dir():
        return ImageFolder(path, camera.fps, fast, start)
    return Capture(camera, fast, start)


class CameraWorker(SensorWorker):
    """One camera: its own thread reads frames, detects, and delivers MarkerData (node.Camera)."""

    def __init__(self, name: str, camera: CameraConfig, detector: Detector, fast: bool = False) -> None:
        super().__init__()
        self.name = name
        self.camera = camera
        self.detector = detector
        self.fast = fast
        self.counts: Counter[str] = Counter()
        self._latest: Frame | None = None
        self._lock = threading.Lock()
        self._have = threading.Event()

    def counters(self) -> dict[str, int]:
        return dict(self.counts) | {f"detector_{k}": v for k, v in self.detector.counters.items()}

    def take_status(self) -> list[str]:
        """The detector's STATUSTEXT lines since the last call (thread-safe: a list swap)."""
        return self.detector.take_status()

    def _run(self, deliver: Deliver) -> None:
        backoff = 0
        while not self._stop.is_set():
            try:
                source = open_source(self.camera, self.fast)
            except SourceError as exc:
                self.counts["open_errors"] += 1
                _logger.warning("camera %s: %s; retrying", self.name, exc)
                self._stop.wait(BACKOFF_S[min(backoff, len(BACKOFF_S) - 1)])
                backoff += 1
                continue
            backoff = 0
            self.counts["opened"] += 1
            try:
                self._consume(source, deliver)
                if not source.live:
                    if self._stop.is_set():  # asked to stop, not out of frames
                        _logger.info("camera %s: stopped", self.name)
                    else:
                        _logger.info("camera %s: end of %s", self.name, self.camera.source)
                    return
            except SourceError as exc:
                self.counts["source_failures"] += 1
                _logger.warning("camera %s: %s; reopening", self.name, exc)
            finally:
                source.close()

    def _detect(self, frame: Frame, deliver: Deliver) -> None:
        self.counts["frames"] += 1
        try:
            found = list(self.detector.detect(frame.gray, frame.capture_time_us))
            if found:
                deliver(found)
        except AtlasError as exc:  # e.g. frames of another size than the calibration
            self.counts["frame_errors"] += 1
            _logger.error("camera %s: %s", self.name, exc)

    def _consume(self, source: Source, deliver: Deliver) -> None:
        """Files: every frame, in order (paced by the source unless fast). Live sources: a reader
        thread keeps only the newest frame, so a slow detector skips frames (counted), never queues."""
        if not source.live:
            for frame in source.frames():
                if self._stop.is_set():
                    return
                self._detect(frame, deliver)
            return
        reader_error: list[SourceError] = []
        done = threading.Event()

        def read() -> None:
            try:
                for frame in source.frames():
                    if self._stop.is_set():
                        break
                    with self._lock:
                        if self._latest is not None:
                            self.counts["frames_dropped"] += 1
                        self._latest = frame
                    self._have.set()
            except SourceError as exc:
                reader_error.append(exc)
            finally:
                done.set()
                self._have.set()

        reader = threading.Thread(target=read, name=f"camera-{self.name}-read", daemon=True)
        reader.start()
        while not self._stop.is_set():
            self._have.wait(0.1)
            with self._lock:
                frame, self._latest = self._latest, None
                self._have.clear()
            if frame is None:
                if done.is_set():
                    break
                continue
            self._detect(frame, deliver)
        reader.join(timeout=1.0)
        if reader_error:
            raise reader_error[0]
