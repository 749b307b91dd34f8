"""One camera: its own thread reads frames from the camera's source (:mod:`atlas_onboard.detector.sources`),
detects, and delivers MarkerData.

A source that fails or stops delivering is reopened with backoff; the worker reports it and keeps
running. A live camera's slow detector drops frames (counted); it never builds a queue.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter

from atlas_onboard.config import CameraConfig
from atlas_onboard.core.attitude import CameraTurn
from atlas_onboard.detector.motion import body_rate_at
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.sources import Frame, Source, SourceError, open_source
from atlas_onboard.errors import AtlasError
from atlas_onboard.recording.format import BackgroundRecorder
from atlas_onboard.worker import Deliver, SensorWorker

_logger = logging.getLogger(__name__)

BACKOFF_S = (0.5, 1.0, 2.0, 5.0)


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
        # ``run --record`` (recording.onboard): each detected frame goes to it after its observations.
        self.recorder: BackgroundRecorder | None = None
        self._turn: CameraTurn | None = None  # made when the autopilot's attitude is first there

    def counters(self) -> dict[str, int]:
        out = dict(self.counts) | {f"detector_{k}": v for k, v in self.detector.counters.items()}
        return out | (self.recorder.counters() if self.recorder is not None else {})

    def stop(self) -> None:
        super().stop()
        if self.recorder is not None:  # what is queued is written before the node's final counters
            from atlas_onboard.recording.onboard import finish

            finish(self.recorder, self.name)

    def map_pose_changed(self, marker_id: int) -> None:
        self.detector.map_pose_changed(marker_id)

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
        t_us = frame.capture_time_us
        R_prev_now = None
        if self.attitude_at is not None:
            if self._turn is None:
                self._turn = CameraTurn(self.detector.sensor.T_entity_sensor.rotation)
            R_prev_now = self._turn.since_last(self.attitude_at(t_us))
        body_rate = body_rate_at(self.rate_at, self.attitude_at, t_us)  # a rolling shutter's shear
        try:
            found = list(self.detector.detect(frame.gray, t_us, R_prev_now, body_rate))
            if found:
                deliver(found)
        except AtlasError as exc:  # e.g. frames of another size than the calibration
            self.counts["frame_errors"] += 1
            _logger.error("camera %s: %s", self.name, exc)
            return
        if self.recorder is not None:  # never blocks: a full queue drops the frame (counted)
            self.recorder.offer(frame.gray, frame.capture_time_us, found)

    def _consume(self, source: Source, deliver: Deliver) -> None:
        """Every frame, in order (a file replayed ``every_frame``, paced by the source unless fast), or
        (a live camera, a real-time replay) a reader thread keeps only the newest frame, so a slow
        detector skips frames (counted ``frames_dropped``), never queues."""
        if not source.keeps_newest:
            for frame in source.frames():
                if self._stop.is_set():
                    return
                self._detect(frame, deliver)
            return
        reader_error: list[SourceError] = []
        done = threading.Event()

        def read() -> None:
            skipped = 0
            try:
                for frame in source.frames():
                    if self._stop.is_set():
                        break
                    with self._lock:
                        if self._latest is not None:
                            self.counts["frames_dropped"] += 1
                        self._latest = frame
                        self.counts["frames_skipped"] += source.skipped - skipped
                        skipped = source.skipped
                    self._have.set()
            except SourceError as exc:
                reader_error.append(exc)
            finally:
                with self._lock:
                    self.counts["frames_skipped"] += source.skipped - skipped
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
