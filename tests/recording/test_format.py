"""The recording format: round trip, bounded disk use, a full disk, a slow disk, a cut-short index."""

from __future__ import annotations

import errno
import threading
from pathlib import Path

import numpy as np
import pytest

from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.recording import format as rec

K = np.array([[400.0, 0.0, 79.5], [0.0, 400.0, 59.5], [0.0, 0.0, 1.0]])
CAL = Calibration(160, 120, K, np.array([-0.1, 0.01, 0.0, 0.0, 0.0]))


def _frame(k: int) -> np.ndarray:
    return np.random.default_rng(k).integers(0, 255, (120, 160), dtype=np.uint8)


def test_round_trip(tmp_path: Path) -> None:
    md = MarkerData(sensor_id=3, marker_id=7, sigma_m=0.01, p_sensor_marker_m=(0.1, 0.2, 1.5),
                    q_sensor_marker_wxyz=(1.0, 0.0, 0.0, 0.0), capture_time_us=1000)  # fmt: skip
    w = rec.RecordingWriter(tmp_path / "r", CAL, sensor_name="down", sensor_id=3, entity="d1",
                            p_body_camera_m=(0.1, 0.0, 0.0), q_body_camera_wxyz=(0.5, -0.5, 0.5, -0.5))  # fmt: skip
    for k in range(3):
        assert w.write(_frame(k), 1000 + k, [md] if k == 1 else [], (1.0, 0.0, 0.0, 0.0) if k else None)
    w.close()
    info = rec.read_info(tmp_path / "r")
    assert (info.sensor_name, info.sensor_id, info.entity) == ("down", 3, "d1")
    assert np.allclose(info.calibration.K, K) and np.allclose(info.calibration.dist, CAL.dist)
    frames = list(rec.read_frames(tmp_path / "r"))
    assert [f.capture_time_us for f in frames] == [1000, 1001, 1002]
    assert all(np.array_equal(f.gray, _frame(k)) for k, f in enumerate(frames))  # lossless
    assert frames[0].q_level_body_wxyz is None and frames[1].q_level_body_wxyz == (1.0, 0.0, 0.0, 0.0)
    got = frames[1].markers[0]
    assert got.marker_id == 7 and got.p_sensor_marker_m == (0.1, 0.2, 1.5) and np.isnan(got.reprojection_error_px)


def test_disk_use_is_bounded(tmp_path: Path) -> None:
    w = rec.RecordingWriter(tmp_path / "r", CAL, max_bytes=150_000)
    kept = [w.write(_frame(k), k) for k in range(20)]
    w.close()
    used = sum(p.stat().st_size for p in (tmp_path / "r").rglob("*") if p.is_file())
    assert used <= 150_000 + 4096  # the index's last line may round up to a block
    assert 0 < sum(kept) < 20 and w.frames_dropped == 20 - sum(kept)
    assert len(list(rec.read_frames(tmp_path / "r"))) == sum(kept)


def test_a_full_disk_is_one_clear_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    w = rec.RecordingWriter(tmp_path / "r", CAL)
    assert w.write(_frame(0), 0)

    def full(self: Path, data: bytes) -> int:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", full)
    with pytest.raises(rec.RecordingError, match="disk full after 1 frames"):
        w.write(_frame(1), 1)


def gated_writer(path: Path, cal: Calibration, wait_s: float) -> tuple[rec.RecordingWriter, threading.Event]:
    """A recording writer on a slow or hung disk: each write waits for the event (at most ``wait_s``)."""
    w = rec.RecordingWriter(path, cal)
    gate = threading.Event()
    real = w.write

    def slow(*args: object) -> bool:
        gate.wait(wait_s)
        return real(*args)  # type: ignore[arg-type]

    w.write = slow  # type: ignore[method-assign]
    return w, gate


def test_a_slow_disk_drops_frames_and_never_blocks(tmp_path: Path) -> None:
    w, gate = gated_writer(tmp_path / "r", CAL, 5.0)
    bg = rec.BackgroundRecorder(w, queue_size=4)
    offered = [bg.offer(_frame(k), k) for k in range(12)]  # returns at once even though writing waits
    assert not all(offered) and bg.dropped_queue_full == offered.count(False)
    gate.set()
    bg.close()
    assert w.frames_written == offered.count(True)


def test_an_index_cut_short_reads_up_to_its_last_whole_line(tmp_path: Path) -> None:
    w = rec.RecordingWriter(tmp_path / "r", CAL)
    for k in range(3):
        w.write(_frame(k), k)
    w.close()
    index = tmp_path / "r" / rec.INDEX
    index.write_text(index.read_text()[:-20])
    assert len(list(rec.read_frames(tmp_path / "r"))) == 2


def test_a_recording_is_never_overwritten(tmp_path: Path) -> None:
    rec.RecordingWriter(tmp_path / "r", CAL).close()
    with pytest.raises(rec.RecordingError, match="not empty"):
        rec.RecordingWriter(tmp_path / "r", CAL)
