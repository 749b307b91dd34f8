"""``run --record``: the running node records each of its cameras as it flies (docs/mapping.md).

Each camera gets a :class:`~atlas_onboard.recording.format.BackgroundRecorder` in a new directory
``DIR/<UTC time>-<entity>-<sensor>``: the camera thread offers each frame it detected, after its
observations went to the node, to a bounded queue; a writer thread encodes and writes it (OpenCV's
encoder and the file writes release the GIL). Nothing here can stop the node: a directory that cannot
be written, a full disk or the size cap ends the recording with one line in the log, and the node
flies on.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Protocol

from atlas_onboard.config import RecordConfig, WorldConfig
from atlas_onboard.recording.format import BackgroundRecorder, RecordingError, RecordingWriter, disk_free_bytes

_logger = logging.getLogger(__name__)

QUEUE_FRAMES = 8  # frames waiting for the writer, per camera: a quarter second at 30 fps
FREE_RESERVE_BYTES = 200_000_000  # never fill the disk: logs and the node's state need room too
CLOSE_TIMEOUT_S = 2.0  # at shutdown, the queue's frames get this long to be written (a hung disk is abandoned)

Attitude = Callable[[int], tuple[float, float, float, float] | None]


def bytes_under(directory: Path) -> int:
    """Bytes of the regular files under ``directory`` (0 if it does not exist)."""
    if not directory.is_dir():
        return 0
    total = 0
    for p in directory.rglob("*"):
        try:
            if p.is_file():
                total += p.stat().st_size
        except OSError:
            continue
    return total


def budget_bytes(record: RecordConfig) -> tuple[int, str]:
    """How many bytes this run may write under ``record.dir``, and what limits it (for the log)."""
    cap = int(record.max_mb * 1e6)
    used = bytes_under(record.dir)
    left = cap - used
    why = f"cap {record.max_mb:g} MB, {used / 1e6:.0f} MB already recorded"
    try:
        free = disk_free_bytes(record.dir if record.dir.is_dir() else _existing_parent(record.dir))
    except OSError:
        return left, why
    if free - FREE_RESERVE_BYTES < left:
        left = free - FREE_RESERVE_BYTES
        why = f"{free / 1e6:.0f} MB free on the disk, {FREE_RESERVE_BYTES / 1e6:.0f} MB kept free"
    return left, why


def _existing_parent(path: Path) -> Path:
    for p in (path, *path.parents):
        if p.is_dir():
            return p
    return Path("/")


class _Camera(Protocol):
    name: str  # a node's camera (one with a ``recorder`` attribute can be recorded)


def start(
    cameras: Sequence[_Camera],
    world: WorldConfig,
    entity: str,
    record: RecordConfig,
    attitude_at: Attitude | None = None,
    now_s: float | None = None,
) -> list[BackgroundRecorder]:
    """Give each camera that can be recorded (one with a ``recorder`` attribute: a real camera's
    worker) its recorder; returns them. Problems are logged in one line each, never raised."""
    recordable = [c for c in cameras if hasattr(c, "recorder")]
    for c in cameras:
        if not hasattr(c, "recorder"):
            _logger.warning("camera %s: this kind of camera cannot be recorded", c.name)
    if not recordable:
        return []
    left, why = budget_bytes(record)
    if left <= 0:
        _logger.error("not recording to %s: no room left (%s)", record.dir, why)
        return []
    stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime(time.time() if now_s is None else now_s))
    sensors = {s.name: s for s in world.entity(entity).sensors}
    recorders = []
    for cam in recordable:
        sensor = sensors[cam.name]  # type: ignore[attr-defined]
        camera = cam.calibration  # type: ignore[attr-defined]
        T = sensor.T_entity_sensor
        p, q = T.translation, T.rotation.as_quat()
        directory = record.dir / f"{stamp}-{entity}-{sensor.name}"
        try:
            writer = RecordingWriter(
                directory, camera, sensor_name=sensor.name, sensor_id=sensor.id, entity=entity,
                p_body_camera_m=(float(p[0]), float(p[1]), float(p[2])),
                q_body_camera_wxyz=(float(q[3]), float(q[0]), float(q[1]), float(q[2])),
                max_bytes=left // len(recordable), image_format=record.image_format,
            )  # fmt: skip
        except RecordingError as exc:
            _logger.error("camera %s not recorded: %s", sensor.name, exc)
            continue
        recorder = BackgroundRecorder(writer, QUEUE_FRAMES, attitude_at=attitude_at)
        cam.recorder = recorder  # type: ignore[attr-defined]
        recorders.append(recorder)
        _logger.info("camera %s: recording to %s (up to %.0f MB: %s)", sensor.name, directory, writer.max_bytes / 1e6,
                     why)  # fmt: skip
    return recorders


def finish(recorder: BackgroundRecorder, name: str) -> None:
    """Write what is queued and close the recording; one line saying what was recorded (never raises)."""
    try:
        recorder.close(CLOSE_TIMEOUT_S)
    except RecordingError as exc:
        if recorder.error is None:  # (a write error was said when it happened)
            _logger.error("camera %s: %s", name, exc)
    w = recorder.writer
    c = recorder.counters()
    _logger.info(
        "camera %s: recorded %d frames (%.1f MB) to %s; not recorded: %d (writer behind), %d (cap), %d (error)",
        name, w.frames_written, w.bytes_written / 1e6, w.directory, c["record_dropped_queue_full"],
        c["record_dropped_cap"], c["record_dropped_error"],
    )  # fmt: skip
