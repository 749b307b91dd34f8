"""Detection in worker processes, for a node given more than one core (``nodes.<entity>.cores``).

A camera's frames go to its workers in turn (:class:`atlas_onboard.detector.inorder.InOrder`); each
worker process holds a detector of its own, made from a picklable spec, so each detector sees every
N-th frame of its camera. Its markers are predicted from the newest frame any of the camera's workers
has searched, shared on the camera's track board (:mod:`atlas_onboard.detector.tracks`), or else from its
own previous frame. Processes, not threads: most of a frame's work (the per-marker refit, pose and
checks) is Python that holds the interpreter lock; only the library's search and OpenCV's calls release it.

Workers are forked from a server process that imported the detector and made the AprilTag library's
detector once (``forkserver``, :mod:`atlas_onboard.detector.forkserver_preload`): no worker inherits the
node's threads or locks, and the imported modules' pages and the library's decoding tables are shared
between workers.
"""

from __future__ import annotations

import math
import mmap
import multiprocessing
import os
import signal
import threading
from collections import Counter
from dataclasses import dataclass, replace
from multiprocessing import reduction
from multiprocessing.connection import Connection
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, RefineConfig, SensorConfig, WorldConfig
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.refine.sampling import PerMarkerSchedule
from atlas_onboard.core.shutter import BodyRate, BodyVelocity
from atlas_onboard.detector.backends import apriltag_families
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.forkserver_preload import FAMILIES_ENV
from atlas_onboard.detector.tracks import BoardSlot, SharedTracks, TrackBoard
from atlas_onboard.errors import AtlasError


class FrameDetector(Protocol):
    """What a camera needs of its detector (:class:`atlas_onboard.detector.pipeline.Detector`)."""

    counters: Counter[str]
    shared: SharedTracks | None  # the camera's track board (:mod:`.tracks`), set by the worker

    def detect(
        self,
        gray: NDArray[np.uint8],
        capture_time_us: int,
        R_prev_now: Rotation | None = None,
        body_rate: BodyRate | None = None,
        body_velocity: BodyVelocity | None = None,
        attitude: Rotation | None = None,
    ) -> list[MarkerData]: ...

    def take_status(self) -> list[str]: ...

    def map_pose_changed(self, marker_id: int) -> None: ...


class DetectorSpec(Protocol):
    """Makes a camera's detector in a worker process (picklable)."""

    def build(self) -> FrameDetector: ...


@dataclass(frozen=True)
class CameraDetectorSpec:
    """The detector ``atlas-onboard run`` makes for a camera (with live map refinement's per-marker images
    when ``refine`` is given)."""

    sensor: SensorConfig
    world: WorldConfig
    calibration: Calibration
    decimate: float = 2.0
    refine: RefineConfig | None = None

    def apriltag_families(self) -> str:
        """The AprilTag families its detector's library detector has (those of the markers it looks for)."""
        wanted = {m.id: m.family for m in self.world.markers.values() if m.entity != self.sensor.entity}
        return " ".join(apriltag_families(wanted))

    def build(self) -> FrameDetector:
        from atlas_onboard.detector.pipeline import Detector

        per_marker = None
        if self.refine is not None:
            world_ids = frozenset(m.id for m in self.world.entity(WORLD).markers)
            per_marker = PerMarkerSchedule(world_ids, round(self.refine.per_marker_period_s * 1e6))
        return Detector(self.sensor, self.world, self.calibration, decimate=self.decimate, per_marker=per_marker)


@dataclass(frozen=True)
class Job:
    """One frame for a worker: its place in the camera's sequence, its image, stamp, the camera's
    orientation (R_level_camera, from the autopilot's attitude) and the autopilot's body rate at its
    capture."""

    seq: int
    gray: NDArray[np.uint8]
    capture_time_us: int
    attitude: Rotation | None = None
    body_rate: BodyRate | None = None
    body_velocity: BodyVelocity | None = None


@dataclass(frozen=True)
class Outcome:
    """A worker's answer to a :class:`Job`: the detections, the worker detector's counters so far, its
    STATUSTEXT lines since the last answer, and the one-line error of a frame it refused (AtlasError)."""

    seq: int
    found: list[MarkerData]
    counters: dict[str, int]
    status: list[str]
    error: str = ""


@dataclass(frozen=True)
class _SharedJob:
    """A :class:`Job` on the pipe whose image is in the worker's frame buffer: the job with an empty
    image, and the image's shape."""

    job: Job
    shape: tuple[int, ...]


@dataclass(frozen=True)
class _FrameBuffer:
    """The worker's frame buffer is now the memory (``size`` bytes) whose descriptor follows on the pipe."""

    size: int


@dataclass(frozen=True)
class _Board:
    """The camera's track board (:class:`~atlas_onboard.detector.tracks.TrackBoard` of ``slots``) is the
    memory whose descriptor follows on the pipe; the worker posts in ``slot``."""

    slots: int
    slot: int


@dataclass(frozen=True)
class BoardPlace:
    """A worker's place on its camera's track board: the board's descriptor (the camera's), its slots,
    and the worker's slot."""

    fd: int
    slots: int
    slot: int


_NO_IMAGE = np.empty((0, 0), np.uint8)


def serve(conn: Connection, spec: DetectorSpec) -> None:
    """A worker process's loop: a :class:`Job` in, an :class:`Outcome` out; an int is a world marker whose
    pose the node's map changed; None or a closed pipe ends it. Any other exception ends the process
    (the camera restarts it, counted)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the process group: the node stops us
    import cv2

    cv2.setNumThreads(1)  # the workers are the parallelism; OpenCV's own threads would compete with them
    detector = spec.build()
    conn.send(READY)
    frames: mmap.mmap | None = None
    while True:
        try:
            msg = conn.recv()
            if isinstance(msg, _FrameBuffer):
                fd = reduction.recv_handle(conn)
                frames = mmap.mmap(fd, msg.size)
                os.close(fd)
                continue
            if isinstance(msg, _Board):
                fd = reduction.recv_handle(conn)
                detector.shared = BoardSlot(TrackBoard.attach(fd, msg.slots), msg.slot)
                os.close(fd)
                continue
        except (EOFError, OSError):
            return
        if msg is None:
            return
        if isinstance(msg, int):
            detector.map_pose_changed(msg)
            continue
        if isinstance(msg, _SharedJob):  # copied out: the node writes the next frame there once answered
            image = np.frombuffer(frames, np.uint8, count=math.prod(msg.shape)).reshape(msg.shape)  # type: ignore[arg-type]
            msg = replace(msg.job, gray=image.copy())
        error = ""
        try:
            found = list(
                detector.detect(
                    msg.gray, msg.capture_time_us, None, msg.body_rate, msg.body_velocity, attitude=msg.attitude
                )
            )
        except AtlasError as exc:  # e.g. frames of another size than the calibration
            found, error = [], str(exc)
        conn.send(Outcome(msg.seq, found, dict(detector.counters), detector.take_status(), error))


READY = "ready"  # a worker's first message: its detector is made
_CONTEXT_LOCK = threading.Lock()


def _context(families: str) -> multiprocessing.context.BaseContext:
    """The forkserver context, its server preloading the detector and the library detector of
    ``families`` (AprilTag families; the first worker's, when the server starts)."""
    ctx = multiprocessing.get_context("forkserver")
    with _CONTEXT_LOCK:
        if families and FAMILIES_ENV not in os.environ:
            os.environ[FAMILIES_ENV] = families  # the server's environment: read by its preload
        ctx.set_forkserver_preload(
            ["atlas_onboard.detector.workers", "atlas_onboard.detector.pipeline",
             "atlas_onboard.detector.forkserver_preload"]
        )  # fmt: skip
    return ctx


class WorkerDiedError(Exception):
    """The worker process ended (killed, or an exception) or its pipe broke."""


class ProcessWorker:
    """One worker process and its pipe. Not thread-safe for receiving; sends are locked (the camera's
    thread sends frames, the node's loop map changes).

    A frame's image goes through memory the node and the worker share (an anonymous file whose
    descriptor is passed on the pipe, Linux's ``memfd``), not through the pipe: the worker has at most
    one frame in flight (:mod:`atlas_onboard.detector.inorder`), so one buffer, written before the job
    is sent and copied out by the worker, serves every frame. Where there is no ``memfd`` the image is
    pickled on the pipe."""

    def __init__(self, spec: DetectorSpec, name: str, board: BoardPlace | None = None) -> None:
        self.spec = spec
        self.name = name
        self.board = board
        self._send_lock = threading.Lock()
        self._frames: mmap.mmap | None = None  # the shared buffer, and its descriptor
        self._frames_fd = -1
        self._frames_told = False  # whether this process has been sent the buffer
        self._start()

    def _start(self) -> None:
        families = self.spec.apriltag_families() if isinstance(self.spec, CameraDetectorSpec) else ""
        ctx = _context(families)
        parent, child = ctx.Pipe()
        self.process = ctx.Process(target=serve, args=(child, self.spec), name=self.name, daemon=True)
        self.process.start()
        child.close()
        self.conn = parent
        self._frames_told = False
        if self.board is not None:
            try:
                self.conn.send(_Board(self.board.slots, self.board.slot))
                reduction.send_handle(self.conn, self.board.fd, self.process.pid)
            except OSError:
                pass  # the process is gone already: the next frame's send finds it and restarts it

    def send(self, msg: Job | int) -> None:
        """Raises :class:`WorkerDiedError` when the process is gone."""
        try:
            with self._send_lock:
                if isinstance(msg, Job) and self._share(msg.gray.nbytes):
                    np.copyto(
                        np.frombuffer(self._frames, np.uint8, count=msg.gray.size).reshape(msg.gray.shape), msg.gray
                    )  # type: ignore[arg-type]
                    self.conn.send(_SharedJob(replace(msg, gray=_NO_IMAGE), msg.gray.shape))
                else:
                    self.conn.send(msg)
        except (OSError, ValueError) as exc:
            raise WorkerDiedError(str(exc)) from None

    def _share(self, nbytes: int) -> bool:
        """Whether a frame of ``nbytes`` goes through the shared buffer (grown, and the process told of
        it, as needed); False where there is no ``memfd``."""
        if self._frames is None or len(self._frames) < nbytes:
            self._close_frames()
            try:
                fd = os.memfd_create(f"atlas-onboard-{self.name}", os.MFD_CLOEXEC)
            except (AttributeError, OSError):  # not Linux, or refused: the pipe carries the image
                return False
            os.ftruncate(fd, nbytes)
            self._frames, self._frames_fd, self._frames_told = mmap.mmap(fd, nbytes), fd, False
        if not self._frames_told:
            self.conn.send(_FrameBuffer(len(self._frames)))
            reduction.send_handle(self.conn, self._frames_fd, self.process.pid)
            self._frames_told = True
        return True

    def _close_frames(self) -> None:
        if self._frames is not None:
            self._frames.close()
            os.close(self._frames_fd)
            self._frames, self._frames_fd = None, -1

    def result(self, timeout_s: float) -> Outcome | None:
        """The answer to the job sent, or None if not there within ``timeout_s``; raises
        :class:`WorkerDiedError` when the process ended."""
        try:
            while self.conn.poll(timeout_s):
                out = self.conn.recv()
                if isinstance(out, Outcome):
                    return out
                if out != READY:
                    raise WorkerDiedError(f"unexpected answer {type(out).__name__}")
        except (EOFError, OSError) as exc:
            raise WorkerDiedError(str(exc) or "pipe closed") from None
        if not self.process.is_alive():
            raise WorkerDiedError(f"exit code {self.process.exitcode}")
        return None

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait until the worker has made its detector (its first message); False if it has not within
        ``timeout_s`` or died (the camera's collector then restarts it)."""
        try:
            return self.conn.poll(timeout_s) and self.conn.recv() == READY
        except (EOFError, OSError):
            return False

    def restart(self) -> None:
        """Kill the process (if it still runs) and start a new one with a fresh detector."""
        self._end(0.0)
        self._start()

    def close(self) -> None:
        """Ask the process to end; killed if it has not within a second."""
        try:
            with self._send_lock:
                self.conn.send(None)
        except (OSError, ValueError):
            pass
        self._end(1.0)
        with self._send_lock:
            self._close_frames()

    def _end(self, wait_s: float) -> None:
        self.process.join(wait_s)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(1.0)
        self.conn.close()
