"""Frames over several detection workers: handed on in capture order whatever each worker's delay; a
worker that dies or hangs is restarted and counted, and the frames after it go on."""

import queue
import random
import threading

import numpy as np
import pytest

from atlas_onboard.detector.inorder import InOrder
from atlas_onboard.detector.workers import Outcome, WorkerDiedError

pytestmark = pytest.mark.deadlines  # worker threads and their deadlines

IMAGE = np.zeros((4, 4), np.uint8)


class FakeWorker:
    """A worker in a thread: answers each frame after a random delay with its stamp. ``die_at`` /
    ``hang_at``: stamps at which it dies (its pipe breaks) or never answers; ``stale_at``: stamps whose
    answer comes with an earlier frame's number (a result of a frame given up) before the right one."""

    def __init__(self, name, seed, die_at=(), hang_at=(), stale_at=()):
        self.name = name
        self.rng = random.Random(seed)
        self.die_at, self.hang_at, self.stale_at = set(die_at), set(hang_at), set(stale_at)
        self.answers: queue.Queue = queue.Queue()
        self.dead = False
        self.restarts = 0
        self.changes: list[int] = []

    def send(self, msg):
        if self.dead:
            raise WorkerDiedError("dead")
        if isinstance(msg, int):
            self.changes.append(msg)
            return
        if msg.capture_time_us in self.hang_at:
            return
        answers = self.answers

        def answer():
            if msg.capture_time_us in self.die_at:
                self.dead = True
                answers.put(None)
                return
            if msg.capture_time_us in self.stale_at:
                answers.put(Outcome(msg.seq - 1, ["stale"], {}, []))
            answers.put(Outcome(msg.seq, [msg.capture_time_us], {"frames": 1}, []))

        threading.Timer(self.rng.uniform(0.0, 0.02), answer).start()

    def result(self, timeout_s):
        try:
            out = self.answers.get(timeout=timeout_s)
        except queue.Empty:
            return None
        if out is None:
            raise WorkerDiedError("exit code -9")
        return out

    def restart(self):
        self.restarts += 1
        self.dead = False
        self.answers = queue.Queue()

    def close(self):
        pass


def _run(workers, stamps, timeout_s=2.0):
    delivered: list[tuple[int, list]] = []
    restarted: list[int] = []
    pipe = InOrder(workers, lambda job, out: delivered.append((job.capture_time_us, out.found)), restarted.append,
                   timeout_s=timeout_s)  # fmt: skip
    stop = threading.Event()
    for t in stamps:
        assert pipe.submit(IMAGE, t, None, stop)
    pipe.drain(stop)
    pipe.close()
    return pipe, delivered, restarted


def test_results_come_in_capture_order_whatever_the_workers_delays():
    workers = [FakeWorker(f"w{i}", seed=i) for i in range(3)]
    stamps = [1_000_000 + 33_333 * k for k in range(90)]
    pipe, delivered, restarted = _run(workers, stamps)
    assert [t for t, _ in delivered] == stamps  # every frame, in order
    assert all(found == [t] for t, found in delivered)  # each with its own result
    assert not restarted and pipe.counts["worker_restarts"] == 0


def test_each_worker_gets_every_nth_frame():
    seen: dict[int, list[int]] = {}
    stop = threading.Event()
    workers = [FakeWorker(f"w{i}", seed=i) for i in range(2)]
    pipe = InOrder(workers, lambda job, out: seen.setdefault(job.seq % 2, []).append(job.seq))
    for k in range(10):
        assert pipe.next_index == k % 2
        pipe.submit(IMAGE, k, None, stop)
    pipe.drain(stop)
    pipe.close()
    assert seen == {0: [0, 2, 4, 6, 8], 1: [1, 3, 5, 7, 9]}


def test_a_worker_that_dies_is_restarted_counted_and_the_stream_goes_on():
    stamps = list(range(100, 160))
    workers = [FakeWorker("w0", 0), FakeWorker("w1", 1, die_at={111, 131})]
    pipe, delivered, restarted = _run(workers, stamps)
    assert [t for t, _ in delivered] == [t for t in stamps if t not in (111, 131)]
    assert pipe.counts["worker_restarts"] == 2 and pipe.counts["frames_lost"] == 2
    assert workers[1].restarts == 2 and restarted == [1, 1]


def test_a_hung_worker_is_restarted_after_the_timeout():
    stamps = list(range(20))
    workers = [FakeWorker("w0", 0, hang_at={6}), FakeWorker("w1", 1)]
    pipe, delivered, _ = _run(workers, stamps, timeout_s=0.3)
    assert [t for t, _ in delivered] == [t for t in stamps if t != 6]
    assert pipe.counts["worker_restarts"] == 1 and pipe.counts["frames_lost"] == 1


def test_an_answer_to_another_frame_is_dropped_never_handed_on():
    stamps = list(range(30))
    workers = [FakeWorker("w0", 0), FakeWorker("w1", 1, stale_at={9, 15})]
    pipe, delivered, _ = _run(workers, stamps)
    assert [t for t, _ in delivered] == stamps and all(found == [t] for t, found in delivered)
    assert pipe.counts["frames_late_dropped"] == 2


def test_map_changes_reach_every_worker_and_a_restarted_one_again():
    workers = [FakeWorker("w0", 0), FakeWorker("w1", 1, die_at={3})]
    stop = threading.Event()
    pipe = InOrder(workers, lambda job, out: None)
    pipe.map_pose_changed(7)
    for k in range(8):
        pipe.submit(IMAGE, k, None, stop)
    pipe.drain(stop)
    pipe.close()
    assert workers[0].changes == [7] and workers[1].changes == [7, 7]  # told again after its restart
