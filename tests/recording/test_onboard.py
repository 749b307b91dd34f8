"""``run --record`` and replaying a recording, in process: the recording camera source (real time and
every frame, at the recorded stamps), a disk that fills during the flight, the cap over earlier
recordings, and the settings' errors."""

from __future__ import annotations

import errno
import logging
import time
from pathlib import Path

import numpy as np
import pytest

from atlas_onboard.cli import main
from atlas_onboard.config import CameraConfig, ConfigError, RecordConfig, load_node
from atlas_onboard.detector import sources
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.camera import CameraWorker
from atlas_onboard.recording import format as rec
from atlas_onboard.recording import onboard
from tests.e2e.helpers import wait_for, write_world
from tests.recording.test_format import gated_writer

pytestmark = pytest.mark.deadlines  # the recorder's thread and its deadlines

K = np.array([[100.0, 0.0, 15.5], [0.0, 100.0, 11.5], [0.0, 0.0, 1.0]])
CAL = Calibration(32, 24, K, np.zeros(5))
# Irregular stamps, as a camera delivers them (us): about 40 Hz with jitter and a gap.
STAMPS_US = [1_000_000 + s for s in (0, 24_000, 51_000, 75_000, 100_000, 190_000, 214_000, 240_000, 266_000)]


def _recording(path: Path, stamps_us: list[int]) -> Path:
    w = rec.RecordingWriter(path, CAL)
    for k, t in enumerate(stamps_us):
        w.write(np.full((24, 32), k * 20, np.uint8), t)
    w.close()
    return path


class _SlowDetector:
    def __init__(self, delay_s: float) -> None:
        self.delay_s = delay_s
        self.counters: dict[str, int] = {}
        self.seen: list[tuple[int, int]] = []  # (stamp us, grey level = 20 * recorded frame number)

    def detect(self, gray, capture_time_us, R_prev_now=None, body_rate=None, body_velocity=None):
        self.seen.append((capture_time_us, int(gray[0, 0])))
        time.sleep(self.delay_s)
        return []


def _replay(path: Path, replay: str, delay_s: float) -> tuple[CameraWorker, _SlowDetector]:
    det = _SlowDetector(delay_s)
    worker = CameraWorker("c", CameraConfig(source=str(path), replay=replay), det)  # type: ignore[arg-type]
    worker.start(lambda found: None)
    worker._thread.join(timeout=30)  # type: ignore[union-attr]
    assert worker._thread is not None and not worker._thread.is_alive()
    return worker, det


@pytest.mark.parametrize("replay", ["every_frame", "realtime"])
def test_a_recording_replays_at_its_recorded_stamps_shifted_to_now(tmp_path: Path, replay: str) -> None:
    path = _recording(tmp_path / "r", STAMPS_US)
    assert sources.default_replay(str(path)) == "realtime"  # a recorded camera stream
    start_us = time.time_ns() // 1000
    # every_frame with a fast detector sees every frame; realtime with one 3x slower than the camera drops.
    worker, det = _replay(path, replay, 0.001 if replay == "every_frame" else 0.075)
    c = worker.counters()
    frame_numbers = [level // 20 for _, level in det.seen]
    shift_us = det.seen[0][0] - STAMPS_US[frame_numbers[0]]
    assert det.seen[0][0] >= start_us
    # Each frame stamped by its own recorded stamp, all shifted by one offset.
    assert [t - shift_us for t, _ in det.seen] == [STAMPS_US[k] for k in frame_numbers]
    assert frame_numbers == sorted(frame_numbers)
    if replay == "every_frame":
        assert frame_numbers == list(range(len(STAMPS_US)))
    else:
        assert c["frames"] < len(STAMPS_US)
        assert c["frames"] + c.get("frames_dropped", 0) + c.get("frames_skipped", 0) == len(STAMPS_US)


def test_an_empty_or_broken_recording_is_a_source_error(tmp_path: Path) -> None:
    empty = _recording(tmp_path / "e", [])
    with pytest.raises(sources.SourceError, match="without frames"):
        sources.open_source(CameraConfig(source=str(empty)))
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / rec.META).write_text("{not json")
    with pytest.raises(sources.SourceError, match="not valid JSON"):
        sources.open_source(CameraConfig(source=str(tmp_path / "b")))


def test_a_disk_that_fills_during_the_flight_stops_the_recording_with_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    w = rec.RecordingWriter(tmp_path / "r", CAL)
    bg = rec.BackgroundRecorder(w, queue_size=64)
    frame = np.zeros((24, 32), np.uint8)
    assert bg.offer(frame, 0)
    assert wait_for(lambda: w.frames_written == 1)
    real = Path.write_bytes

    def full(self: Path, data: bytes) -> int:
        if self.parent.name == "frames":
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, data)

    monkeypatch.setattr(Path, "write_bytes", full)
    with caplog.at_level(logging.ERROR):
        for k in range(1, 10):
            bg.offer(frame, k)
            time.sleep(0.01)
        with pytest.raises(rec.RecordingError, match="disk full after 1 frames"):
            bg.close()
    assert [r.getMessage() for r in caplog.records if r.levelno >= logging.ERROR] == [
        f"{tmp_path / 'r'}: disk full after 1 frames (recording stopped)"
    ]
    c = bg.counters()
    assert c["record_failed"] == 1 and c["record_written"] == 1
    assert c["record_dropped_error"] + c["record_dropped_queue_full"] == 8  # the frames after the failing one
    assert len(list(rec.read_frames(tmp_path / "r"))) == 1  # what was written is a readable recording


def test_the_cap_counts_earlier_recordings(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    _recording(tmp_path / "all" / "earlier", STAMPS_US)
    used = onboard.bytes_under(tmp_path / "all")
    assert used > 0
    left, _ = onboard.budget_bytes(RecordConfig(tmp_path / "all", max_mb=used / 1e6 + 0.5))
    assert left == 500_000
    # Full already: nothing is recorded, said in one line.
    with caplog.at_level(logging.ERROR):
        got = onboard.start([_Recordable()], None, "d", RecordConfig(tmp_path / "all", max_mb=used / 2e6))  # type: ignore[arg-type]
    assert got == [] and len(caplog.records) == 1 and "no room left" in caplog.records[0].getMessage()


class _Recordable:
    name = "cam"
    recorder = None


def _doc(record: object) -> dict:
    return {
        "entities": {"world": {"markers": [{"id": 1, "size_m": 0.1, "pose": {}}]}, "d": {}},
        "nodes": {"d": {"system_id": 1, "record": record}},
    }


def test_record_settings_and_their_errors(tmp_path: Path) -> None:
    _, config = load_node(write_world(tmp_path, _doc({"dir": "flights", "max_mb": 500})), "d")
    assert config.record == RecordConfig(tmp_path / "flights", 500.0, "png")  # relative to the world file
    for bad, field in (({"dir": "x", "max_mb": 0}, "max_mb"), ({"dir": "x", "image_format": "bmp"}, "image_format"),
                       ({"max_mb": 5}, "dir"), ({"dir": "x", "size": 1}, "size")):  # fmt: skip
        with pytest.raises(ConfigError, match=f"nodes.d.record.{field}"):
            load_node(write_world(tmp_path, _doc(bad)), "d")


def test_run_record_options_are_checked_before_anything_starts(tmp_path: Path, capsys) -> None:
    doc = _doc({"dir": "x"})
    del doc["nodes"]["d"]["record"]
    path = write_world(tmp_path, doc)
    assert main(["run", "--config", str(path), "--record", str(tmp_path), "--record-max-mb", "-3"]) == 2
    assert main(["run", "--config", str(path), "--record-max-mb", "30"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--record-max-mb: expected a positive size" in err[0] and "give --record DIR" in err[1]


def test_a_hung_disk_does_not_hang_the_node_s_shutdown(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    w, gate = gated_writer(tmp_path / "r", CAL, 10.0)
    bg = rec.BackgroundRecorder(w, queue_size=2)
    for k in range(4):
        bg.offer(np.zeros((24, 32), np.uint8), k)
    with caplog.at_level(logging.ERROR):
        onboard.finish(bg, "cam")  # returns although the writer is stuck
    assert any("did not finish" in r.getMessage() for r in caplog.records)
    gate.set()
