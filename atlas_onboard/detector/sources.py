"""Camera sources: where a camera's frames come from, each stamped with its capture time (the thread
that detects in them is :class:`atlas_onboard.detector.camera.CameraWorker`).

Sources: a V4L2 device (index or path, with width, height, fps and fourcc), a video file, a folder of
images (in name order; a number in the name that looks like a time stamp is used as its file time),
a recording (a directory written by ``record`` or ``run --record``: its frames at their recorded
capture stamps), or an RTSP/HTTP URL through OpenCV. Live sources stamp the capture time minus the
configured fixed latency. File sources stamp each frame with its file time mapped onto the wall clock
at the moment the first frame is read (not when the source is opened: listing a large folder or
opening a video takes a while), and play in one of two modes (``camera.replay``):

- ``realtime`` (the default for a video file): like a camera, paced on the file's own time; a frame
  whose time has passed before it could be read is skipped, and a frame the detector had no time for
  is dropped (both counted), so the stamps stay as fresh as a live camera's;
- ``every_frame`` (the default for an image folder): every frame, in order, paced no faster than its
  file time; a slow detector falls behind, and its stamps grow old (the node reports that).

A source that fails or stops delivering raises :class:`SourceError`; the worker reopens it.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.config import REPLAY_EVERY_FRAME, REPLAY_REALTIME, CameraConfig
from atlas_onboard.errors import AtlasError
from atlas_onboard.recording.format import RecordingError, is_recording, read_frames, read_info

_logger = logging.getLogger(__name__)

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm"}


class SourceError(AtlasError):
    """A camera source that cannot be opened or read."""


@dataclass
class Frame:
    gray: NDArray[np.uint8]
    capture_time_us: int


class Source:
    """Base: ``frames()`` yields frames until the source ends or fails (then raises SourceError).

    ``live``: a device or stream, reopened when it stops. ``keeps_newest``: the worker keeps only the
    newest frame and drops the others (a live camera, or a file replayed in real time); otherwise it
    detects every frame in order. ``skipped`` counts the frames a real-time replay passed over
    because their time had gone by before they could be read."""

    live = True
    keeps_newest = True
    skipped = 0

    def frames(self) -> Iterator[Frame]:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass


def _gray(img: NDArray[np.uint8]) -> NDArray[np.uint8]:
    return img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def default_replay(source: str) -> str:
    """The replay mode of a file source whose camera block names none: an image folder is a set of
    stills that a user wants each of (``every_frame``); a video file is a recorded camera stream,
    played as the camera delivered it (``realtime``)."""
    if is_recording(Path(source)):
        return REPLAY_REALTIME  # a recorded camera stream
    return REPLAY_EVERY_FRAME if Path(source).is_dir() else REPLAY_REALTIME


class ReplayClock:
    """File time mapped onto the wall clock at the moment the replay starts (the first frame read).

    ``start()`` is called just before the first frame is read; ``stamp_us(file_s)`` is then the wall
    time (us) of a frame ``file_s`` seconds into the file, and ``wait(file_s)`` sleeps until it is due
    (returns at once when ``paced`` is False). ``behind(file_s)``: that time has already passed."""

    def __init__(
        self,
        paced: bool,
        start_us: int | None = None,
        wall_us: Callable[[], int] = lambda: time.time_ns() // 1000,
        monotonic_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self.paced = paced
        self._start_us = start_us
        self._wall_us = wall_us
        self._monotonic_s = monotonic_s
        self.start_us = 0
        self._t0_s = 0.0

    def start(self) -> None:
        self.start_us = self._wall_us() if self._start_us is None else self._start_us
        self._t0_s = self._monotonic_s()

    def stamp_us(self, file_s: float) -> int:
        return self.start_us + round(file_s * 1e6)

    def behind(self, file_s: float) -> bool:
        return self._monotonic_s() > self._t0_s + file_s

    def wait(self, file_s: float) -> None:
        if self.paced:
            time.sleep(max(self._t0_s + file_s - self._monotonic_s(), 0.0))


class ImageFolder(Source):
    """Images of a folder in name order. A frame's file time comes from a number of 10+ digits in
    its name (us, ms or s since the epoch by magnitude), relative to the first such name, else from
    its position at ``fps``."""

    live = False

    def __init__(self, path: Path, fps: float, replay: str, clock: ReplayClock) -> None:
        self.files = sorted(p for p in Path(path).iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self.files:
            raise SourceError(f"{path}: no images ({', '.join(sorted(IMAGE_SUFFIXES))})")
        self.fps = fps or 10.0
        self.keeps_newest = replay == REPLAY_REALTIME
        self.clock = clock
        self.skipped = 0

    @staticmethod
    def stamp_from_name(name: str) -> int | None:
        m = re.search(r"(\d{10,19})", name)
        if not m:
            return None
        v = int(m.group(1))
        digits = len(m.group(1))
        return v * 1_000_000 if digits <= 10 else v * 1000 if digits <= 13 else v if digits <= 16 else v // 1000

    def file_times_s(self) -> list[float]:
        """Each image's time in the file, seconds (from its name's stamp, else its position)."""
        named = [self.stamp_from_name(p.name) for p in self.files]
        first = next((s for s in named if s is not None), None)
        return [(s - first) / 1e6 if s is not None and first is not None else k / self.fps for k, s in enumerate(named)]

    def frames(self) -> Iterator[Frame]:
        times = self.file_times_s()
        self.clock.start()
        for k, (path, file_s) in enumerate(zip(self.files, times, strict=True)):
            # Real time: an image whose successor is already due is passed over unread, like a
            # camera's frame that nobody fetched in time.
            if self.keeps_newest and k + 1 < len(times) and self.clock.behind(times[k + 1]):
                self.skipped += 1
                continue
            self.clock.wait(file_s)
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise SourceError(f"{path}: not a readable image")
            yield Frame(img, self.clock.stamp_us(file_s))


class RecordingSource(Source):
    """A recording's frames (:mod:`atlas_onboard.recording.format`), each at its recorded capture
    stamp shifted to the replay's start: the node sees the flight's own frame timing."""

    live = False

    def __init__(self, path: Path, replay: str, clock: ReplayClock) -> None:
        try:
            self.info = read_info(path)
            self.records = list(read_frames(path, with_images=False))
        except RecordingError as exc:
            raise SourceError(str(exc)) from None
        if not self.records:
            raise SourceError(f"{path}: a recording without frames")
        self.path = Path(path)
        self.keeps_newest = replay == REPLAY_REALTIME
        self.clock = clock
        self.skipped = 0
        self.shift_us = 0

    def frames(self) -> Iterator[Frame]:
        first_us = self.records[0].capture_time_us
        times = [(r.capture_time_us - first_us) / 1e6 for r in self.records]
        self.clock.start()
        self.shift_us = self.clock.stamp_us(0.0) - first_us
        _logger.info(
            "replaying recording %s (%d frames, %s): recorded capture stamps shifted by %+d us",
            self.path, len(self.records), "realtime" if self.keeps_newest else "every frame", self.shift_us,
        )  # fmt: skip
        ext = "png" if self.info.image_format == "png" else "jpg"
        for k, (rec, file_s) in enumerate(zip(self.records, times, strict=True)):
            if self.keeps_newest and k + 1 < len(times) and self.clock.behind(times[k + 1]):
                self.skipped += 1
                continue
            self.clock.wait(file_s)
            img = cv2.imread(str(self.path / "frames" / f"{rec.index:06d}.{ext}"), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise SourceError(f"{self.path}: frame {rec.index}: not a readable image")
            yield Frame(img, self.clock.stamp_us(file_s))


class Capture(Source):
    """An OpenCV VideoCapture: V4L2 device, video file or stream URL."""

    def __init__(self, camera: CameraConfig, replay: str, clock: ReplayClock) -> None:
        src = camera.source
        self.live = not Path(src).is_file()
        self.keeps_newest = self.live or replay == REPLAY_REALTIME
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
        self.clock = clock
        self.skipped = 0
        self.latency_us = round(camera.latency_ms * 1000)
        self.name = src

    def frames(self) -> Iterator[Frame]:
        if not self.live:
            self.clock.start()
        k = 0
        while True:
            file_s = k / self.fps
            if not self.live and self.keeps_newest and self.clock.behind((k + 1) / self.fps):
                # Real time: the next frame is already due; this one is passed over undecoded.
                if not self.cap.grab():
                    return
                self.skipped += 1
                k += 1
                continue
            ok, img = self.cap.read()
            if not ok or img is None:
                if self.live:
                    raise SourceError(f"camera source {self.name!r} stopped delivering frames")
                return
            if self.live:
                stamp = int(time.time() * 1e6) - self.latency_us
            else:
                self.clock.wait(file_s)
                stamp = self.clock.stamp_us(file_s)
            k += 1
            yield Frame(_gray(img), stamp)

    def close(self) -> None:
        self.cap.release()


def open_source(camera: CameraConfig, fast: bool = False, start_us: int | None = None) -> Source:
    """The source a camera block describes (``sim`` is handled by the simulator). ``fast``: a file's
    every frame, unpaced (the detect command). ``start_us``: the wall time a file's first frame is
    stamped with (default: the wall clock when it is read)."""
    path = Path(camera.source)
    replay = REPLAY_EVERY_FRAME if fast else camera.replay or default_replay(camera.source)
    clock = ReplayClock(paced=not fast, start_us=start_us)
    if is_recording(path):
        return RecordingSource(path, replay, clock)
    if path.is_dir():
        return ImageFolder(path, camera.fps, replay, clock)
    return Capture(camera, replay, clock)
