"""A camera's frames over N detection workers in turn, their results handed on in capture order.

Frame k goes to worker k mod N once that worker's previous frame (k-N) is answered, so each worker has
at most one frame in flight and each worker's detector sees every N-th frame (its tracking: see
:mod:`atlas_onboard.detector.workers`). A collector thread waits for the oldest frame in flight and hands
its result on before any later one: the autopilot gets the frames in the order they were taken, each as
soon as it and every earlier one are done. A worker that dies (killed, an exception) or does not answer
within ``timeout_s`` is restarted (counted ``worker_restarts``); its frame is lost (``frames_lost``) and
the frames after it go on. An answer that is not the one awaited (a frame already given up) is dropped
(``frames_late_dropped``): a late result never overtakes a newer one.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter, deque
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.core.shutter import BodyRate, BodyVelocity
from atlas_onboard.detector.workers import Job, Outcome, WorkerDiedError

_logger = logging.getLogger(__name__)

WORKER_TIMEOUT_S = 5.0  # a frame not answered in this long: the worker is taken as hung and restarted
POLL_S = 0.05  # how often the collector looks at whether the worker it waits for is still alive


class Worker(Protocol):
    """A detection worker (:class:`atlas_onboard.detector.workers.ProcessWorker`)."""

    name: str

    def send(self, msg: Job | int) -> None: ...

    def result(self, timeout_s: float) -> Outcome | None: ...

    def restart(self) -> None: ...

    def close(self) -> None: ...


class InOrder:
    """Frames in (:meth:`submit`, from the camera's thread), ``on_result(job, outcome)`` out in capture
    order (from the collector's thread); ``on_restart(index)`` when worker ``index`` was restarted."""

    def __init__(
        self,
        workers: Sequence[Worker],
        on_result: Callable[[Job, Outcome], None],
        on_restart: Callable[[int], None] = lambda index: None,
        timeout_s: float = WORKER_TIMEOUT_S,
    ) -> None:
        if not workers:
            raise ValueError("InOrder needs at least one worker")
        self.workers = list(workers)
        self.on_result = on_result
        self.on_restart = on_restart
        self.timeout_s = timeout_s
        self.counts: Counter[str] = Counter()
        self._seq = 0
        self._pending: deque[Job] = deque()
        self._cond = threading.Condition()
        self._closed = False
        self._changed: list[int] = []  # map changes so far: a restarted worker is told them again
        self._collector = threading.Thread(target=self._collect, name="detect-collector", daemon=True)
        self._collector.start()

    @property
    def next_index(self) -> int:
        """The worker the next frame goes to."""
        return self._seq % len(self.workers)

    def submit(
        self,
        gray: NDArray[np.uint8],
        capture_time_us: int,
        attitude: Rotation | None,
        stop: threading.Event,
        body_rate: BodyRate | None = None,
        body_velocity: BodyVelocity | None = None,
    ) -> bool:
        """Send the next frame (``attitude``: the camera's orientation at its capture, or None) to the next
        worker in turn, once that worker is free; False (nothing sent) if ``stop`` was set or the pipeline
        closed meanwhile."""
        if not self.wait_free(stop):
            return False
        with self._cond:
            job = Job(self._seq, gray, capture_time_us, attitude, body_rate, body_velocity)
            self._seq += 1
            index = job.seq % len(self.workers)
            # Sent under the lock: the collector does not restart this worker while its frame goes out
            # (the worker is idle, so it reads the frame at once).
            try:
                self.workers[index].send(job)
            except WorkerDiedError as exc:
                self._restart(index, f"pipe broken ({exc})")
                try:
                    self.workers[index].send(job)
                except WorkerDiedError:
                    self.counts["frames_lost"] += 1
                    return True
            self._pending.append(job)
            self._cond.notify_all()
        return True

    def wait_free(self, stop: threading.Event) -> bool:
        """Wait until the next worker in turn is free (a live camera then takes its newest frame, not one
        that waited for a worker); False if ``stop`` was set or the pipeline closed meanwhile."""
        with self._cond:
            while len(self._pending) >= len(self.workers) and not stop.is_set() and not self._closed:
                self._cond.wait(0.1)
            return not (stop.is_set() or self._closed)

    def map_pose_changed(self, marker_id: int) -> None:
        """Tell every worker's detector (and the workers restarted later)."""
        with self._cond:
            self._changed.append(marker_id)
            for worker in self.workers:
                try:
                    worker.send(marker_id)
                except WorkerDiedError:
                    pass  # restarted when its next frame is due, and told then

    def drain(self, stop: threading.Event) -> None:
        """Wait until every frame sent is answered (or given up), or ``stop`` is set."""
        with self._cond:
            while self._pending and not stop.is_set():
                self._cond.wait(0.1)

    def close(self) -> None:
        """Stop: frames in flight are not handed on; the workers end."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._collector.join(timeout=2.0)
        for worker in self.workers:
            worker.close()

    def _collect(self) -> None:
        while True:
            with self._cond:
                while not self._pending and not self._closed:
                    self._cond.wait(0.1)
                if self._closed:
                    return
                job = self._pending[0]
            outcome = self._await(job)
            if outcome is not None:
                try:
                    self.on_result(job, outcome)
                except Exception:  # the stream goes on; the node's loop logs what it refuses
                    _logger.exception("delivering frame %d", job.seq)
                    self.counts["delivery_errors"] += 1
            with self._cond:
                self._pending.popleft()
                self._cond.notify_all()

    def _await(self, job: Job) -> Outcome | None:
        """The answer to ``job`` (the oldest frame in flight), or None when its worker died or hung (it is
        restarted) or the pipeline closed."""
        index = job.seq % len(self.workers)
        worker = self.workers[index]
        waited = 0.0
        while not self._closed:
            try:
                out = worker.result(POLL_S)
            except WorkerDiedError as exc:
                with self._cond:
                    self._restart(index, f"ended ({exc})")
                    self.counts["frames_lost"] += 1
                return None
            if out is None:
                waited += POLL_S
                if waited < self.timeout_s:
                    continue
                with self._cond:
                    self._restart(index, f"no answer in {self.timeout_s:g} s")
                    self.counts["frames_lost"] += 1
                return None
            if out.seq != job.seq:  # the answer to a frame given up: never handed on after a newer one
                with self._cond:
                    self.counts["frames_late_dropped"] += 1
                continue
            return out
        return None

    def _restart(self, index: int, why: str) -> None:
        """Restart worker ``index`` (with the lock held) and tell it the map changes so far."""
        worker = self.workers[index]
        _logger.warning("detection worker %s %s: restarting it", worker.name, why)
        self.counts["worker_restarts"] += 1
        worker.restart()
        for marker_id in self._changed:
            try:
                worker.send(marker_id)
            except WorkerDiedError:
                break
        self.on_restart(index)
