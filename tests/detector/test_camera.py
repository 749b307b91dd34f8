"""The camera worker: a source that dies, hangs up or ends and comes back, stopped while reading, real-time
and every-frame replays, and the turn since the previous frame handed to the detector."""

import math
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import CameraConfig, SensorConfig, parse_world
from atlas_onboard.core.shutter import BodyRate
from atlas_onboard.detector import camera as camera_module
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.camera import CameraWorker
from atlas_onboard.detector.pipeline import Detector
from atlas_onboard.detector.sources import Frame, Source, SourceError

pytestmark = pytest.mark.deadlines  # camera threads and their deadlines

# A camera looking forward and 30 degrees down, off the body's centre (its optical frame in the body FLU frame).
MOUNT = RigidTransform.from_components(
    [0.1, 0.02, -0.05],
    Rotation.from_euler("y", 30, degrees=True) * Rotation.from_matrix([[0, 0, 1], [-1, 0, 0], [0, -1, 0]]),
)

DATA = Path(__file__).resolve().parents[1] / "data"


def photo_detector() -> Detector:
    """A detector for the swatbotics photo IMG_1368 (tags 13 and 19 among ids 0-19 of 12.7 cm)."""
    world = parse_world(
        {
            "entities": {
                "world": {
                    "markers": [{"id": i, "size_m": 0.127, "pose": {"pos": [float(i), 0, 0]}} for i in range(20)]
                },
                "cam": {"sensors": [{"name": "c", "id": 1, "pose": {}}]},
            }
        }
    )
    K = np.array([[765.0, 0, 393.72], [0, 764.18, 304.66], [0, 0, 1]])
    cal = Calibration(816, 612, K, np.zeros(5))
    return Detector(world.sensors[1], world, cal, decimate=1.0, track=False, joint=False, max_ambiguity=1.0)


def test_camera_worker_survives_a_source_that_dies_and_comes_back(monkeypatch):
    """Open fails twice, then a source gives 3 frames and dies, then one gives 3 more: 6 frames reach
    the detector and the worker keeps running."""
    gray = cv2.imread(str(DATA / "swatbotics_mapping" / "IMG_1368.JPG"), cv2.IMREAD_GRAYSCALE)
    attempts = {"n": 0}
    released = threading.Event()  # ends the endless source with the test: its reader thread would outlive it

    class Flaky(Source):
        def __init__(self, dies):
            self.dies = dies

        def frames(self):
            for k in range(3):
                yield Frame(gray, k)
            if self.dies:
                raise SourceError("camera unplugged")
            while not released.is_set():
                time.sleep(0.05)
                yield from ()

    def fake_open(camera, fast=False, start_us=None):
        attempts["n"] += 1
        if attempts["n"] <= 2:
            raise SourceError("no such device")
        return Flaky(dies=attempts["n"] == 3)

    monkeypatch.setattr(camera_module, "open_source", fake_open)
    monkeypatch.setattr(camera_module, "BACKOFF_S", (0.01,))
    worker = CameraWorker("c", CameraConfig(source="/dev/video9"), photo_detector())
    got = []
    worker.start(got.append)
    deadline = time.time() + 20
    # A live source keeps only the newest frame: a frame the detector had no time for is dropped.
    while time.time() < deadline and worker.counts["frames"] + worker.counts["frames_dropped"] < 6:
        time.sleep(0.02)
    alive = worker._thread.is_alive()
    worker.stop()
    released.set()
    c = worker.counters()
    assert c["open_errors"] == 2 and c["source_failures"] == 1 and c["opened"] == 2
    assert c["frames"] + c.get("frames_dropped", 0) == 6 and alive
    # One delivery per image, holding all of its detections: the expected ids of IMG_1368.
    assert got and all(sorted(md.marker_id for md in image) == [13, 19] for image in got)


class _MjpegServer:
    """An HTTP camera (multipart MJPEG, as IP cameras and mjpg-streamer serve it) on 127.0.0.1 that
    sends ``per_connection[i]`` frames on its i-th connection, then hangs up: a camera that dies."""

    def __init__(self, jpeg: bytes, per_connection: list[int]) -> None:
        import http.server
        import threading

        server_self = self
        self.connections = 0

        class Handler(http.server.BaseHTTPRequestHandler):
            def log_message(self, *args):
                pass

            def do_GET(self):
                i = server_self.connections
                server_self.connections += 1
                n = per_connection[min(i, len(per_connection) - 1)]
                self.send_response(200)
                self.send_header("Content-Type", "multipart/x-mixed-replace; boundary=frame")
                self.end_headers()
                try:
                    for _ in range(n):
                        self.wfile.write(b"--frame\r\nContent-Type: image/jpeg\r\n")
                        self.wfile.write(f"Content-Length: {len(jpeg)}\r\n\r\n".encode() + jpeg + b"\r\n")
                        self.wfile.flush()
                        time.sleep(0.05)
                except OSError:
                    pass

        self.httpd = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}/stream.mjpg"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def test_an_http_camera_that_hangs_up_is_reopened_and_delivers_again(monkeypatch):
    """A real stream through OpenCV's FFmpeg backend: 4 frames, the camera hangs up, the worker reopens
    it (with backoff) and gets 4 more; the detections are the photo's tags, and the worker lives on."""
    gray = cv2.imread(str(DATA / "swatbotics_mapping" / "IMG_1368.JPG"), cv2.IMREAD_GRAYSCALE)
    ok, jpeg = cv2.imencode(".jpg", gray, [cv2.IMWRITE_JPEG_QUALITY, 95])
    assert ok
    server = _MjpegServer(jpeg.tobytes(), [4, 4, 0])
    monkeypatch.setattr(camera_module, "BACKOFF_S", (0.05,))
    worker = CameraWorker("c", CameraConfig(source=server.url), photo_detector())
    got = []
    try:
        worker.start(got.append)
        deadline = time.time() + 30
        while time.time() < deadline and worker.counts["frames"] + worker.counts["frames_dropped"] < 8:
            time.sleep(0.02)
        alive = worker._thread.is_alive()
    finally:
        worker.stop()
        server.close()
    c = worker.counters()
    assert alive and c["opened"] >= 2 and c["source_failures"] >= 1, c
    assert c["frames"] + c.get("frames_dropped", 0) == 8, c
    assert got and all(sorted(md.marker_id for md in image) == [13, 19] for image in got)
    assert all(len({md.capture_time_us for md in image}) == 1 for image in got)


@pytest.mark.parametrize("stopped", [True, False])
def test_a_file_source_says_end_only_when_it_ran_out(monkeypatch, caplog, stopped):
    """A worker stopped while reading a folder or video logs "stopped", not "end of" the source."""
    gray = np.zeros((48, 64), np.uint8)

    class Folder(Source):
        live = False

        def frames(self):
            for k in range(1000 if stopped else 3):
                time.sleep(0.01)
                yield Frame(gray, k)

    monkeypatch.setattr(camera_module, "open_source", lambda cam, fast=False, start_us=None: Folder())
    worker = CameraWorker("c", CameraConfig(source="/data/frames"), photo_detector())
    with caplog.at_level("INFO", logger="atlas_onboard.detector.camera"):
        worker.start(lambda image: None)
        if stopped:
            time.sleep(0.1)
            worker.stop()
        worker._thread.join(5)
    said = [r.getMessage() for r in caplog.records]
    assert ("camera c: stopped" in said) == stopped
    assert ("camera c: end of /data/frames" in said) == (not stopped)


class _SlowDetector:
    """Stands in for a detector that needs ``delay_s`` per frame; records the stamps it saw."""

    def __init__(self, delay_s: float) -> None:
        self.delay_s = delay_s
        self.counters: dict[str, int] = {}
        self.stamps: list[int] = []
        self.turns: list[Rotation | None] = []
        self.rates: list[BodyRate | None] = []
        self.sensor = SensorConfig("c", 1, "drone", MOUNT)

    def detect(self, gray, capture_time_us, R_prev_now=None, body_rate=None, body_velocity=None):
        self.stamps.append(capture_time_us)
        self.turns.append(R_prev_now)
        self.rates.append(body_rate)
        time.sleep(self.delay_s)
        return []


def _replay(
    tmp_path, replay: str, n: int, fps: float, delay_s: float, attitude_at=None, rate_at=None
) -> tuple[CameraWorker, _SlowDetector, int]:
    for k in range(n):
        cv2.imwrite(str(tmp_path / f"img{k:03d}.png"), np.zeros((8, 8), np.uint8))
    det = _SlowDetector(delay_s)
    worker = CameraWorker("c", CameraConfig(source=str(tmp_path), fps=fps, replay=replay), det)  # type: ignore[arg-type]
    worker.attitude_at = attitude_at
    worker.rate_at = rate_at
    start_us = time.time_ns() // 1000
    worker.start(lambda found: None)
    worker._thread.join(timeout=30)
    assert not worker._thread.is_alive()
    return worker, det, start_us


def test_realtime_replay_drops_what_it_cannot_keep_up_with(tmp_path):
    """A detector 4x slower than the file's 40 Hz: a real-time replay keeps to the file's time (every
    frame accounted for as detected, dropped or skipped; each stamp the file time of its frame), and
    fewer frames reach the detector than the file holds."""
    n, fps = 24, 40.0
    worker, det, start_us = _replay(tmp_path, "realtime", n, fps, 0.1)
    c = worker.counters()
    assert c["frames"] == len(det.stamps) < n
    assert c["frames"] + c.get("frames_dropped", 0) + c.get("frames_skipped", 0) == n
    assert c.get("frames_dropped", 0) + c.get("frames_skipped", 0) > 0
    grid_us = 1e6 / fps
    offsets = [(s - det.stamps[0]) / grid_us for s in det.stamps]
    assert all(abs(o - round(o)) < 1e-6 for o in offsets) and det.stamps[0] >= start_us
    assert np.all(np.diff(offsets) >= 1)


def test_every_frame_replay_detects_every_frame_in_order(tmp_path):
    n, fps = 8, 40.0
    worker, det, _ = _replay(tmp_path, "every_frame", n, fps, 0.05)
    c = worker.counters()
    assert c["frames"] == n and not c.get("frames_dropped") and not c.get("frames_skipped")
    assert [s - det.stamps[0] for s in det.stamps] == [round(k * 1e6 / fps) for k in range(n)]


def test_the_camera_hands_the_detector_its_turn_since_the_previous_frame_from_the_autopilot(tmp_path):
    """With the autopilot's attitude (yawing 90 deg/s, rolling, except around the fourth frame), each frame
    is detected with the camera's turn since the previous one: a world-fixed direction seen now maps to
    where it was seen then; without an attitude near either capture, no turn."""
    n, fps = 8, 40.0
    stamps: list[int] = []

    def attitude_at(t_us: int) -> Rotation | None:
        stamps.append(t_us)
        k = len(stamps) - 1
        s = (t_us - stamps[0]) / 1e6
        return None if k == 3 else Rotation.from_euler("ZYX", [90.0 * s, 3.0 * s, 20.0 * s], degrees=True)

    gyro = BodyRate(np.radians([20.0, 3.0, 90.0]), 1e-6 * np.eye(3))  # its body rates, streamed too
    _, det, _ = _replay(tmp_path, "every_frame", n, fps, 0.0, attitude_at, lambda _t_us: gyro)
    assert det.stamps == stamps and len(det.turns) == n
    assert all(r is gyro for r in det.rates)  # each frame's body rate, for a rolling shutter
    R_body_cam = MOUNT.rotation
    world_dir = np.array([0.3, -0.5, 0.8])
    for k, R in enumerate(det.turns):
        if k in (0, 3, 4):  # no previous frame, or no attitude at this or the previous frame
            assert R is None
            continue
        assert R is not None
        R_then, R_now = (attitude_at_rotation(stamps, j) * R_body_cam for j in (k - 1, k))
        seen_now, seen_then = R_now.inv().apply(world_dir), R_then.inv().apply(world_dir)
        assert np.allclose(R.apply(seen_now), seen_then, atol=1e-9)
        assert R.magnitude() > math.radians(2.0)  # the test is not vacuous: the camera really turned


def attitude_at_rotation(stamps: list[int], k: int) -> Rotation:
    s = (stamps[k] - stamps[0]) / 1e6
    return Rotation.from_euler("ZYX", [90.0 * s, 3.0 * s, 20.0 * s], degrees=True)
