"""Detection in worker processes: real processes (a stand-in detector with random delays, killed or
raising), and the camera worker with the node's detector on the demo's frames, 1 core and 2."""

import os
import random
import signal
import threading
import time
import zlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from atlas_onboard.config import load_node
from atlas_onboard.detector.camera import CameraWorker
from atlas_onboard.detector.inorder import InOrder
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.sources import open_source
from atlas_onboard.detector.workers import ProcessWorker
from atlas_onboard.service.run import build_cameras

pytestmark = pytest.mark.realtime  # worker processes and their deadlines

IMAGE = np.zeros((8, 8), np.uint8)


class _Stand:
    """A detector that takes a random time (seeded by the stamp), counts its frames and says the last stamp
    it saw; it raises (ending its process) at ``crash_at`` and works a long time on ``slow_at``."""

    def __init__(self, crash_at: int = -1, slow_at: int = -1) -> None:
        self.counters: Counter[str] = Counter()
        self.crash_at = crash_at
        self.slow_at = slow_at

    def detect(self, gray, capture_time_us, R_prev_now=None, body_rate=None, body_velocity=None, attitude=None):
        if capture_time_us == self.crash_at:
            raise RuntimeError("a bug")
        slow = capture_time_us == self.slow_at
        time.sleep(3.0 if slow else random.Random(capture_time_us).uniform(0.0, 0.03))
        self.counters["frames"] += 1
        self.counters["last_stamp"] = capture_time_us
        self.counters["image_crc"] = zlib.crc32(np.ascontiguousarray(gray).tobytes())
        self.counters["image_rows"], self.counters["image_cols"] = gray.shape
        return []

    def take_status(self):
        return []

    def map_pose_changed(self, marker_id):
        pass


@dataclass(frozen=True)
class _StandSpec:
    crash_at: int = -1
    slow_at: int = -1

    def build(self):
        return _Stand(self.crash_at, self.slow_at)


def _stream(workers, stamps, kill_at=None, idle=False):
    """Stream ``stamps``; before ``kill_at`` is sent, its worker is killed: while it still works on its
    previous frame, or (``idle``) once every frame sent is answered and the process is gone."""
    got: list[int] = []
    pipe = InOrder(workers, lambda job, out: got.append((job.capture_time_us, out.counters["last_stamp"])))
    stop = threading.Event()
    try:
        for t in stamps:
            if t == kill_at:
                if idle:
                    pipe.drain(stop)
                worker = workers[pipe.next_index]
                os.kill(worker.process.pid, signal.SIGKILL)
                if idle:
                    worker.process.join()
            assert pipe.submit(IMAGE, t, None, stop)
        pipe.drain(stop)
    finally:
        pipe.close()
    return pipe, got


def test_processes_hand_results_on_in_capture_order():
    workers = [ProcessWorker(_StandSpec(), f"w{i}") for i in range(3)]
    stamps = list(range(1000, 1045))
    pipe, got = _stream(workers, stamps)
    assert got == [(t, t) for t in stamps]  # every frame, in order, each its own worker's answer
    assert pipe.counts["worker_restarts"] == 0
    assert all(not w.process.is_alive() for w in workers)  # closed


def test_a_worker_killed_mid_frame_is_restarted_its_frame_counted_lost_and_the_stream_goes_on():
    # Frame 2009 (this worker's, 2 workers) takes 3 s: the kill before 2011 finds it in flight.
    workers = [ProcessWorker(_StandSpec(slow_at=2009), f"w{i}") for i in range(2)]
    stamps = list(range(2000, 2030))
    pipe, got = _stream(workers, stamps, kill_at=2011)
    assert pipe.counts["worker_restarts"] == 1 and pipe.counts["frames_lost"] == 1
    assert got == [(t, t) for t in stamps if t != 2009]  # the rest, in order, 2011 from the new process


def test_a_worker_killed_idle_is_restarted_when_its_frame_goes_out_and_nothing_is_lost():
    workers = [ProcessWorker(_StandSpec(), f"w{i}") for i in range(2)]
    stamps = list(range(2000, 2030))
    pipe, got = _stream(workers, stamps, kill_at=2011, idle=True)
    assert pipe.counts["worker_restarts"] == 1 and pipe.counts["frames_lost"] == 0
    assert got == [(t, t) for t in stamps]


def test_every_image_reaches_its_worker_as_it_was_sent_whatever_its_size():
    # Through the buffer the node and a worker share: frames of growing and shrinking sizes (the buffer
    # grows), one a strided view, each the frame of that worker the one before could not overwrite.
    rng = np.random.default_rng(5)
    images = [rng.integers(0, 256, shape, dtype=np.uint8) for shape in [(8, 8), (480, 640), (16, 24), (720, 1280)] * 2]
    images.append(images[1][::2, 1::3])
    sent = {4000 + k: img for k, img in enumerate(images)}
    got: list[tuple[int, int, tuple[int, int]]] = []
    workers = [ProcessWorker(_StandSpec(), f"w{i}") for i in range(2)]

    def on_result(job, out):
        got.append(
            (job.capture_time_us, out.counters["image_crc"], (out.counters["image_rows"], out.counters["image_cols"]))
        )

    pipe = InOrder(workers, on_result)
    stop = threading.Event()
    try:
        for t, img in sent.items():
            assert pipe.submit(img, t, None, stop)
        pipe.drain(stop)
    finally:
        pipe.close()
    assert got == [(t, zlib.crc32(np.ascontiguousarray(img).tobytes()), img.shape) for t, img in sent.items()]


def test_a_worker_that_raises_is_restarted_counted_and_the_stream_goes_on():
    workers = [ProcessWorker(_StandSpec(crash_at=3007), f"w{i}") for i in range(2)]
    stamps = list(range(3000, 3020))
    pipe, got = _stream(workers, stamps)
    assert pipe.counts["worker_restarts"] == 1 and pipe.counts["frames_lost"] == 1
    assert got == [(t, t) for t in stamps if t != 3007]


# --- the camera worker with the node's detector, on the demo's frames ---------------------------------


@pytest.fixture(scope="module")
def demo(tmp_path_factory) -> Path:
    from atlas_onboard.sim.demo import write_demo

    d = tmp_path_factory.mktemp("demo")
    path = write_demo(d / "demo", seconds=1.5, n_tags=10)
    doc = yaml.safe_load(path.read_text())
    doc["entities"]["drone"]["sensors"][0]["camera"]["replay"] = "every_frame"
    path.write_text(yaml.safe_dump(doc))
    return path


def _with_cores(path: Path, cores: int) -> Path:
    doc = yaml.safe_load(path.read_text())
    doc["nodes"]["drone"]["cores"] = cores
    out = path.with_name(f"world-{cores}.yaml")
    out.write_text(yaml.safe_dump(doc))
    return out


def _camera_run(path: Path) -> tuple[CameraWorker, list]:
    world, config = load_node(path, "drone")
    [camera] = build_cameras(world, config)
    got: list = []
    camera.start(got.append)
    camera._thread.join(timeout=120)
    assert not camera._thread.is_alive()
    camera.stop()
    return camera, got


def test_one_core_is_the_serial_path_with_the_same_output(demo):
    camera, got = _camera_run(_with_cores(demo, 1))
    assert camera.detector is not None and camera.processes == 0  # detects in its own thread
    world, _ = load_node(demo, "drone")
    sensor = world.entity("drone").sensors[0]
    detector = Detector(sensor, world, camera.calibration, decimate=2.0)
    expected = []
    for frame in open_source(sensor.camera, fast=True).frames():
        found = detector.detect(frame.gray, frame.capture_time_us)
        if found:
            expected.append(found)
    stamps = lambda runs: [[md.capture_time_us for md in run] for run in runs]  # noqa: E731
    # The same detections; the stamps differ by when each replay started (the folder is played in real time).
    assert len(got) == len(expected) > 20
    offsets = {g[0].capture_time_us - e[0].capture_time_us for g, e in zip(got, expected, strict=True)}
    assert len(offsets) == 1
    for g, e in zip(got, expected, strict=True):
        assert [(md.marker_id, md.p_sensor_marker_m, md.q_sensor_marker_wxyz, md.sigma_m) for md in g] == [
            (md.marker_id, md.p_sensor_marker_m, md.q_sensor_marker_wxyz, md.sigma_m) for md in e
        ]
    assert stamps(got) == sorted(stamps(got))


def test_two_worker_processes_deliver_every_frame_in_order_with_the_same_recall(demo):
    serial, got1 = _camera_run(_with_cores(demo, 1))
    camera, got2 = _camera_run(_with_cores(demo, 2))
    assert camera.detector is None and camera.processes == 2
    stamps = [run[0].capture_time_us for run in got2]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)  # capture order, each once
    c1, c2 = serial.counters(), camera.counters()
    assert c2["frames"] == c1["frames"] and c2.get("worker_restarts", 0) == 0
    # Tracking from the newest frame either worker has searched (shared on the camera's board), or from
    # the worker's own previous one (two frames back), finds what the serial path finds.
    assert c2["detector_tracks_shared"] > 0 and "detector_tracks_shared" not in c1
    assert len(got2) == len(got1)
    assert c2["detector_detections"] == c1["detector_detections"]
    tracked1 = c1["detector_roi_finds"] + c1.get("detector_followed", 0)
    assert c2["detector_roi_finds"] + c2.get("detector_followed", 0) >= tracked1 - 2
    # The same poses within a small part of their sigmas (each frame's markers found by either search).
    for a, b in zip(got1, got2, strict=True):
        for m1, m2 in zip(a, b, strict=True):
            assert m1.marker_id == m2.marker_id
            assert np.linalg.norm(np.subtract(m1.p_sensor_marker_m, m2.p_sensor_marker_m)) < 0.5 * m1.sigma_m


def test_one_core_a_detector_that_raises_is_counted_and_the_camera_goes_on(tmp_path):
    import cv2

    from atlas_onboard.config import CameraConfig

    for k in range(6):
        cv2.imwrite(str(tmp_path / f"img{k:03d}.png"), np.full((8, 8), k, np.uint8))

    class Flaky(_Stand):
        def detect(self, gray, capture_time_us, R_prev_now=None, body_rate=None, body_velocity=None, attitude=None):
            if int(gray[0, 0]) == 2:
                raise RuntimeError("a bug")
            self.counters["frames"] += 1
            return [int(gray[0, 0])]

    camera = CameraWorker("c", CameraConfig(source=str(tmp_path), fps=200.0, replay="every_frame"), Flaky())
    got: list = []
    camera.start(got.append)
    camera._thread.join(timeout=30)
    assert not camera._thread.is_alive()
    assert got == [[0], [1], [3], [4], [5]]
    assert camera.counters()["worker_restarts"] == 1
