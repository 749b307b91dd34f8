"""One camera: its own thread reads frames from the camera's source (:mod:`atlas_onboard.detector.sources`),
detects, and delivers MarkerData.

A source that fails or stops delivering is reopened with backoff; the worker reports it and keeps
running. A live camera's slow detector drops frames (counted); it never builds a queue.

Given worker processes (``nodes.<entity>.cores`` above 1), the thread hands each frame to the next of
them and their results reach the node in capture order (:mod:`atlas_onboard.detector.inorder`); with
none, it detects each frame itself. A detector that raises is counted (``worker_restarts``) and the
camera goes on with the next frame.
"""

from __future__ import annotations

import logging
import os
import threading
from collections import Counter

from atlas_onboard.config import CameraConfig
from atlas_onboard.core.attitude import CameraTurn, camera_orientation
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.inorder import InOrder
from atlas_onboard.detector.motion import body_rate_at, body_velocity_at
from atlas_onboard.detector.sources import Frame, Source, SourceError, open_source
from atlas_onboard.detector.tracks import TrackBoard
from atlas_onboard.detector.workers import (
    BoardPlace,
    CameraDetectorSpec,
    FrameDetector,
    Job,
    Outcome,
    ProcessWorker,
)
from atlas_onboard.errors import AtlasError
from atlas_onboard.recording.format import BackgroundRecorder
from atlas_onboard.worker import Deliver, SensorWorker

_logger = logging.getLogger(__name__)

BACKOFF_S = (0.5, 1.0, 2.0, 5.0)
WORKER_READY_S = 60.0  # the most a camera waits for its worker processes' detectors before its first frame


class CameraWorker(SensorWorker):
    """One camera: its own thread reads frames, detects, and delivers MarkerData (node.Camera)."""

    def __init__(
        self,
        name: str,
        camera: CameraConfig,
        detector: FrameDetector | None,
        fast: bool = False,
        *,
        spec: CameraDetectorSpec | None = None,
        processes: int = 0,
    ) -> None:
        """``detector`` detects in this thread; or, with ``processes`` >= 1, ``spec`` makes the detector of
        each of that many worker processes (``detector`` None)."""
        super().__init__()
        if (processes >= 1) != (spec is not None and detector is None):
            raise ValueError("CameraWorker: a detector, or a spec with processes >= 1")
        self.name = name
        self.camera = camera
        self.detector = detector
        self.spec = spec
        self.processes = processes
        self.fast = fast
        self.counts: Counter[str] = Counter()
        self._pipeline: InOrder | None = None
        self._workers: list[ProcessWorker] = []
        self._deliver: Deliver | None = None
        self._board: int | None = None  # with worker processes: their track board's descriptor
        self._worker_counters: dict[int, dict[str, int]] = {}  # each worker's detector counters so far
        self._retired: Counter[str] = Counter()  # those of workers restarted
        self._status: list[str] = []
        self._status_lock = threading.Lock()
        self._latest: Frame | None = None
        self._lock = threading.Lock()
        self._have = threading.Event()
        # ``run --record`` (recording.onboard): each detected frame goes to it after its observations.
        self.recorder: BackgroundRecorder | None = None
        self._turn: CameraTurn | None = None  # made when the autopilot's attitude is first there

    @property
    def calibration(self) -> Calibration:
        """The camera's calibration (its detector's)."""
        return self.spec.calibration if self.spec is not None else self.detector.calibration  # type: ignore[union-attr]

    def counters(self) -> dict[str, int]:
        if self.detector is not None:
            detector = dict(self.detector.counters)
        else:
            total = Counter(self._retired)
            for c in list(self._worker_counters.values()):
                total.update(c)
            detector = dict(total)
        out = dict(self.counts) | {f"detector_{k}": v for k, v in detector.items()}
        if self._pipeline is not None:
            out |= dict(self._pipeline.counts)
        return out | (self.recorder.counters() if self.recorder is not None else {})

    def start(self, deliver: Deliver) -> None:
        if self.spec is not None:
            self._board = TrackBoard.create(self.processes, self.name)
            workers = [
                ProcessWorker(self.spec, f"detect-{self.name}-{i}", self._place(i)) for i in range(self.processes)
            ]
            self._workers = workers
            self._deliver = deliver
            self._pipeline = InOrder(workers, self._on_result, self._on_restart)
        super().start(deliver)

    def _place(self, i: int) -> BoardPlace | None:
        return None if self._board is None else BoardPlace(self._board, self.processes, i)

    def stop(self) -> None:
        super().stop()
        if self._pipeline is not None:
            self._pipeline.close()
        if self._board is not None:
            os.close(self._board)
            self._board = None
        if self.recorder is not None:  # what is queued is written before the node's final counters
            from atlas_onboard.recording.onboard import finish

            finish(self.recorder, self.name)

    def map_pose_changed(self, marker_id: int) -> None:
        if self._pipeline is not None:
            self._pipeline.map_pose_changed(marker_id)
        elif self.detector is not None:
            self.detector.map_pose_changed(marker_id)

    def take_status(self) -> list[str]:
        """The detector's STATUSTEXT lines since the last call (thread-safe: a list swap)."""
        if self.detector is not None:
            return self.detector.take_status()
        with self._status_lock:
            out, self._status = self._status, []
        return out

    def _run(self, deliver: Deliver) -> None:
        for worker in self._workers:  # their detectors made before the first frame, as this thread's is
            worker.wait_ready(WORKER_READY_S)
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
                if self._pipeline is not None:  # the last frames' results out before the end is said
                    self._pipeline.drain(self._stop)
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
        if self._pipeline is not None:
            self._submit(self._pipeline, frame)
            return
        self.counts["frames"] += 1
        t_us = frame.capture_time_us
        R_prev_now = None
        if self.attitude_at is not None:
            if self._turn is None:
                self._turn = CameraTurn(self.detector.sensor.T_entity_sensor.rotation)
            R_prev_now = self._turn.since_last(self.attitude_at(t_us))
        body_rate = body_rate_at(self.rate_at, t_us)  # a rolling shutter's shear
        body_velocity = body_velocity_at(self.velocity_at, t_us)
        try:
            found = list(self.detector.detect(frame.gray, t_us, R_prev_now, body_rate, body_velocity))
            if found:
                deliver(found)
        except AtlasError as exc:  # e.g. frames of another size than the calibration
            self.counts["frame_errors"] += 1
            _logger.error("camera %s: %s", self.name, exc)
            return
        except Exception:  # a bug must not end the camera's pose stream: counted, logged, next frame
            self.counts["worker_restarts"] += 1
            _logger.exception("camera %s: detection failed; going on with the next frame", self.name)
            return
        if self.recorder is not None:  # never blocks: a full queue drops the frame (counted)
            self.recorder.offer(frame.gray, frame.capture_time_us, found)

    def _submit(self, pipeline: InOrder, frame: Frame) -> None:
        """Hand the frame to the next worker in turn (waiting until it is free), with the camera's
        orientation at its capture (the worker turns its tracks by it, :mod:`.tracks`)."""
        t_us = frame.capture_time_us
        attitude = None
        if self.attitude_at is not None:
            attitude = camera_orientation(self.attitude_at(t_us), self.spec.sensor.T_entity_sensor.rotation)  # type: ignore[union-attr]
        body_rate = body_rate_at(self.rate_at, t_us)  # a rolling shutter's shear
        body_velocity = body_velocity_at(self.velocity_at, t_us)
        if pipeline.submit(frame.gray, t_us, attitude, self._stop, body_rate, body_velocity):
            self.counts["frames"] += 1

    def _on_result(self, job: Job, outcome: Outcome) -> None:
        """A frame's result, in capture order (the collector's thread)."""
        self._worker_counters[job.seq % self.processes] = outcome.counters
        if outcome.status:
            with self._status_lock:
                self._status += outcome.status
        if outcome.error:
            self.counts["frame_errors"] += 1
            _logger.error("camera %s: %s", self.name, outcome.error)
            return
        if outcome.found and self._deliver is not None:
            self._deliver(outcome.found)
        if self.recorder is not None:
            self.recorder.offer(job.gray, job.capture_time_us, outcome.found)

    def _on_restart(self, index: int) -> None:
        """Worker ``index`` was restarted: its counters so far stay counted."""
        self._retired.update(self._worker_counters.pop(index, {}))

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
            if self._pipeline is not None and not self._pipeline.wait_free(self._stop):
                break  # the newest frame is taken once a worker is free for it
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
