"""The sensor worker's thread: started with a deliver callback, stopped by its event and joined; a
worker without a detector has no counters and no status lines."""

from __future__ import annotations

import threading

from atlas_onboard.worker import Deliver, SensorWorker


class Ticker(SensorWorker):
    name = "ticker"

    def __init__(self) -> None:
        super().__init__()
        self.delivered = threading.Event()
        self.thread_name = ""
        self.stopped_cleanly = False

    def _run(self, deliver: Deliver) -> None:
        self.thread_name = threading.current_thread().name
        deliver([])
        self.delivered.set()
        self._stop.wait(10.0)
        self.stopped_cleanly = self._stop.is_set()


def test_the_worker_runs_in_its_own_named_thread_and_stop_ends_it():
    w = Ticker()
    got: list[int] = []
    w.start(lambda items: got.append(len(items)))
    assert w.delivered.wait(10.0)
    assert got == [0] and w.thread_name == "sensor-ticker"
    w.stop()
    assert w._thread is not None and not w._thread.is_alive()
    assert w.stopped_cleanly


def test_stop_before_start_does_nothing_and_the_defaults_are_empty():
    w = Ticker()
    w.stop()
    assert w.counters() == {} and w.take_status() == []
    w.map_pose_changed(3)  # no detector: nothing to forget
    assert w.attitude_at is None and w.rate_at is None
