"""The recording format: what one camera of a node saw, written as it flies (docs/mapping.md).

A recording is a directory::

    recording.json      what the recording is: format, version, sensor, camera mounting, calibration file
    calibration.yaml    the camera's calibration (OpenCV FileStorage YAML)
    index.jsonl         one JSON object a frame: frame number, image file, capture stamp (us), the
                        autopilot's attitude (q_wxyz, local level frame, or null) and the MarkerData
                        the node's detector found in it
    frames/NNNNNN.png   the frames, grey, lossless (or .jpg when asked for)

The index is appended line by line and flushed, so a recording cut short (power lost, disk full) is
readable up to its last whole line. Disk use is bounded: past ``max_bytes`` further frames are
dropped (counted), never written.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import queue
import threading
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.detector.calibration import Calibration, CalibrationError, write_opencv
from atlas_onboard.detector.calibration import load as load_calibration
from atlas_onboard.errors import AtlasError, read_failure

_logger = logging.getLogger(__name__)

FORMAT = "atlas-onboard-recording"
VERSION = 1
META = "recording.json"
INDEX = "index.jsonl"
CALIBRATION = "calibration.yaml"


class RecordingError(AtlasError):
    """A recording that cannot be written or read; the message names the directory and the problem."""


@dataclass(frozen=True)
class RecordedFrame:
    """One frame of a recording.

    Attributes:
        index: the frame's number in the recording (0, 1, ...; gaps where frames were dropped).
        gray: (H, W) uint8 image.
        capture_time_us: capture stamp on the node's clock, microseconds.
        q_level_body_wxyz: the autopilot's attitude at capture (body FLU in a level frame whose yaw is
            arbitrary), or None when the recording has none.
        markers: what the node's detector reported for the frame.
    """

    index: int
    gray: NDArray[np.uint8]
    capture_time_us: int
    q_level_body_wxyz: tuple[float, float, float, float] | None
    markers: tuple[MarkerData, ...] = ()


@dataclass(frozen=True)
class RecordingInfo:
    """What ``recording.json`` says: the sensor, its mounting on the body (FLU, optical frame) and lens."""

    path: Path
    sensor_name: str
    sensor_id: int
    entity: str
    p_body_camera_m: tuple[float, float, float] | None
    q_body_camera_wxyz: tuple[float, float, float, float] | None
    calibration: Calibration
    image_format: str


def _markerdata_dict(md: MarkerData) -> dict[str, Any]:
    d = asdict(md)
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items()}


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, list):
        return [_json_safe(v) for v in value]
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    return value


class RecordingWriter:
    """Writes a recording frame by frame in the calling thread (see :class:`BackgroundRecorder`)."""

    def __init__(
        self,
        directory: Path,
        calibration: Calibration,
        *,
        sensor_name: str = "camera",
        sensor_id: int = 0,
        entity: str = "",
        p_body_camera_m: tuple[float, float, float] | None = None,
        q_body_camera_wxyz: tuple[float, float, float, float] | None = None,
        max_bytes: int = 2_000_000_000,
        image_format: str = "png",
    ) -> None:
        if image_format not in ("png", "jpg"):
            raise RecordingError(f"image format: expected png or jpg, got {image_format!r}")
        self.directory = Path(directory)
        self.max_bytes = max_bytes
        self.image_format = image_format
        self.bytes_written = 0
        self.frames_written = 0
        self.frames_dropped = 0
        self._next = 0
        try:
            if self.directory.exists() and any(self.directory.iterdir()):
                raise RecordingError(f"{self.directory}: exists and is not empty (a recording is never overwritten)")
            (self.directory / "frames").mkdir(parents=True, exist_ok=True)
            write_opencv(self.directory / CALIBRATION, calibration)
            meta = {
                "format": FORMAT, "version": VERSION,
                "sensor": {"name": sensor_name, "id": sensor_id, "entity": entity},
                "p_body_camera_m": list(p_body_camera_m) if p_body_camera_m is not None else None,
                "q_body_camera_wxyz": list(q_body_camera_wxyz) if q_body_camera_wxyz is not None else None,
                "calibration": CALIBRATION, "image_format": image_format,
            }  # fmt: skip
            (self.directory / META).write_text(json.dumps(meta, indent=1) + "\n", encoding="utf-8")
            self._index = open(self.directory / INDEX, "a", encoding="utf-8")
        except OSError as exc:
            raise self._os_error(exc) from None
        self.bytes_written = sum(p.stat().st_size for p in self.directory.iterdir() if p.is_file())

    def _os_error(self, exc: OSError) -> RecordingError:
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            return RecordingError(f"{self.directory}: disk full after {self.frames_written} frames (recording stopped)")
        return RecordingError(f"{self.directory}: cannot write: {exc.strerror or exc}")

    def write(
        self,
        gray: NDArray[np.uint8],
        capture_time_us: int,
        markers: tuple[MarkerData, ...] | list[MarkerData] = (),
        q_level_body_wxyz: tuple[float, float, float, float] | None = None,
    ) -> bool:
        """Append one frame; False if it was dropped because the recording reached ``max_bytes``."""
        index = self._next
        self._next += 1
        ext = ".png" if self.image_format == "png" else ".jpg"
        ok, buf = cv2.imencode(ext, gray, [cv2.IMWRITE_JPEG_QUALITY, 95] if ext == ".jpg" else [])
        if not ok:
            raise RecordingError(f"{self.directory}: frame {index}: cannot encode the image")
        line = json.dumps(
            _json_safe(
                {
                    "frame": index,
                    "file": f"frames/{index:06d}{ext}",
                    "capture_time_us": int(capture_time_us),
                    "q_level_body_wxyz": list(q_level_body_wxyz) if q_level_body_wxyz is not None else None,
                    "markers": [_markerdata_dict(m) for m in markers],
                }
            )
        )
        size = len(buf) + len(line) + 1
        if self.bytes_written + size > self.max_bytes:
            self.frames_dropped += 1
            return False
        try:
            (self.directory / "frames" / f"{index:06d}{ext}").write_bytes(buf.tobytes())
            self._index.write(line + "\n")
            self._index.flush()
        except OSError as exc:
            raise self._os_error(exc) from None
        self.bytes_written += size
        self.frames_written += 1
        return True

    def close(self) -> None:
        try:
            self._index.close()
        except OSError as exc:
            raise self._os_error(exc) from None


class BackgroundRecorder:
    """A writer thread behind a bounded queue: ``offer`` never blocks the caller (a node's camera
    thread); when the disk is slower than the camera, frames are dropped and counted.

    ``attitude_at(capture_time_us)``: the autopilot's attitude (q_wxyz, body FLU in a level frame) at a
    capture time, or None, asked in the writer thread for frames offered without one. Once the
    recording reached its size cap or failed, further frames are refused at once (counted), and each
    is said once in the log. (The writer thread is not given a lower priority: a thread preempted while
    it holds the GIL would stall the camera and the node's loop; encoding and writing release it.)"""

    def __init__(
        self,
        writer: RecordingWriter,
        queue_size: int = 30,
        *,
        attitude_at: Callable[[int], tuple[float, float, float, float] | None] | None = None,
    ) -> None:
        self.writer = writer
        self.queue: queue.Queue[tuple[Any, ...] | None] = queue.Queue(maxsize=queue_size)
        self.dropped_queue_full = 0
        self.refused = 0  # frames offered after the cap was reached or writing failed
        self.capped = False
        self.error: RecordingError | None = None
        self.attitude_at = attitude_at
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    def offer(self, gray: NDArray[np.uint8], capture_time_us: int, markers: Any = (), attitude: Any = None) -> bool:
        """Queue a frame for writing; False (counted) if the queue is full or the recording has stopped."""
        if self.error is not None or self.capped:
            self.refused += 1
            return False
        try:
            self.queue.put_nowait((gray, capture_time_us, tuple(markers), attitude))
        except queue.Full:
            self.dropped_queue_full += 1
            return False
        return True

    def counters(self) -> dict[str, int]:
        """What happened to the frames offered: written, dropped (writer behind), past the cap, failed."""
        return {
            "record_written": self.writer.frames_written,
            "record_dropped_queue_full": self.dropped_queue_full,
            "record_dropped_cap": self.writer.frames_dropped + (self.refused if self.capped else 0),
            "record_dropped_error": self.refused if self.error is not None else 0,
            "record_failed": int(self.error is not None),
        }

    def _run(self) -> None:
        while True:
            item = self.queue.get()
            if item is None:
                return
            if self.error is not None or self.capped:
                self.refused += 1
                continue
            gray, stamp, markers, attitude = item
            try:
                if attitude is None and self.attitude_at is not None:
                    attitude = self.attitude_at(stamp)
                if not self.writer.write(gray, stamp, markers, attitude):
                    self.capped = True
                    _logger.warning(
                        "%s: recording reached its cap of %.0f MB after %d frames; further frames are not recorded",
                        self.writer.directory, self.writer.max_bytes / 1e6, self.writer.frames_written,
                    )  # fmt: skip
            except RecordingError as exc:
                self.error = exc
                _logger.error("%s", exc)

    def close(self, timeout_s: float | None = None) -> None:
        """Write what is queued, stop the thread, close the files; raises the writer's error if any.
        With ``timeout_s``, a writer still busy after that long (a disk that hangs) is abandoned: what
        it wrote stays readable (the index is flushed line by line), and RecordingError says so."""
        try:
            self.queue.put(None, timeout=timeout_s)
        except queue.Full:
            pass
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            raise RecordingError(f"{self.writer.directory}: the writer did not finish in {timeout_s:g} s (abandoned)")
        try:
            self.writer.close()
        except RecordingError as exc:
            self.error = self.error or exc
        if self.error is not None:
            raise self.error


def is_recording(path: Path) -> bool:
    return Path(path).is_dir() and (Path(path) / META).is_file()


def read_info(path: Path) -> RecordingInfo:
    """The recording's description; RecordingError if it is not a readable recording."""
    path = Path(path)
    try:
        meta = json.loads((path / META).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: not a readable recording ({META}: {read_failure(exc)})") from None
    except json.JSONDecodeError:
        raise RecordingError(f"{path}: {META} is not valid JSON") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise RecordingError(f"{path}: {META} does not describe an atlas-onboard recording")
    if meta.get("version") != VERSION:
        raise RecordingError(f"{path}: recording version {meta.get('version')!r}, expected {VERSION}")
    try:
        cal = load_calibration(path / str(meta.get("calibration", CALIBRATION)))
    except CalibrationError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    sensor = meta.get("sensor") or {}
    p, q = meta.get("p_body_camera_m"), meta.get("q_body_camera_wxyz")
    return RecordingInfo(
        path, str(sensor.get("name", "camera")), int(sensor.get("id", 0)), str(sensor.get("entity", "")),
        tuple(float(v) for v in p) if p else None, tuple(float(v) for v in q) if q else None,  # type: ignore[arg-type]
        cal, str(meta.get("image_format", "png")),
    )  # fmt: skip


def _markerdata(d: dict[str, Any]) -> MarkerData:
    nan = float("nan")
    fields = {k: (tuple(nan if x is None else x for x in v) if isinstance(v, list) else (nan if v is None else v))
              for k, v in d.items()}  # fmt: skip
    return MarkerData(**fields)


def read_frames(path: Path, with_images: bool = True) -> Iterator[RecordedFrame]:
    """The recording's frames in order; RecordingError names the line or image that cannot be read.
    A last line cut short (the recording was interrupted) ends the recording."""
    path = Path(path)
    try:
        lines = (path / INDEX).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise RecordingError(f"{path}: cannot read {INDEX}: {read_failure(exc)}") from None
    for n, line in enumerate(lines, start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
            index, file, stamp = int(rec["frame"]), str(rec["file"]), int(rec["capture_time_us"])
            q = rec.get("q_level_body_wxyz")
            q = tuple(float(v) for v in q) if q else None
            markers = tuple(_markerdata(m) for m in rec.get("markers") or [])
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            if n == len(lines):
                _logger.warning("%s: last line of %s is cut short; ignored", path, INDEX)
                return
            raise RecordingError(f"{path}: {INDEX} line {n}: not a frame record ({exc})") from None
        gray = np.zeros((0, 0), np.uint8)
        if with_images:
            img = cv2.imread(str(path / file), cv2.IMREAD_GRAYSCALE)
            if img is None:
                raise RecordingError(f"{path}: {file}: not a readable image")
            gray = img
        yield RecordedFrame(index, gray, stamp, q, markers)  # type: ignore[arg-type]


def disk_free_bytes(path: Path) -> int:
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize
