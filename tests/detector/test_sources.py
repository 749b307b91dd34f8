"""Camera sources against known answers: stamps from file names and order, and from when the first frame is
read, however slow the listing or the video's opening."""

import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from atlas_onboard.config import CameraConfig
from atlas_onboard.detector import sources
from atlas_onboard.detector.sources import ImageFolder

pytestmark = pytest.mark.deadlines  # replay at the camera's rate


def test_image_folder_stamps_from_names_and_order(tmp_path):
    """A name's stamp is the image's file time (relative to the first named image), mapped onto the
    replay's start like every file time; unnamed images count by position."""
    for name in ("b_1700000000123.png", "a_1700000000100.png", "c_noise.png"):
        cv2.imwrite(str(tmp_path / name), np.zeros((8, 8), np.uint8))
    frames = list(
        sources.open_source(CameraConfig(source=str(tmp_path), fps=10), fast=True, start_us=5_000_000).frames()
    )
    assert [f.capture_time_us for f in frames] == [5_000_000, 5_000_000 + 23_000, 5_000_000 + 200_000]
    assert ImageFolder.stamp_from_name("x_1700000000.jpg") == 1_700_000_000_000_000
    assert ImageFolder.stamp_from_name("1700000000123456.png") == 1_700_000_000_123_456


def _slow_listing(monkeypatch, delay_s: float) -> None:
    """Listing a folder takes ``delay_s`` (a large folder on an SD card)."""
    listing = Path.iterdir

    def slow(self):
        time.sleep(delay_s)
        return listing(self)

    monkeypatch.setattr(Path, "iterdir", slow)


@pytest.mark.parametrize("replay", ["every_frame", "realtime"])
def test_file_source_stamps_from_when_the_first_frame_is_read(tmp_path, monkeypatch, replay):
    """A slow listing (or a slow video open) must not age the stamps: the first frame is stamped no
    earlier than the moment the source was ready, and later ones follow the file's time from it."""
    for k in range(3):
        cv2.imwrite(str(tmp_path / f"f{k}.png"), np.zeros((8, 8), np.uint8))
    _slow_listing(monkeypatch, 0.3)
    source = sources.open_source(CameraConfig(source=str(tmp_path), fps=20, replay=replay))
    ready_us = time.time_ns() // 1000
    frames = list(source.frames())
    done_us = time.time_ns() // 1000
    assert len(frames) + source.skipped == 3
    assert ready_us <= frames[0].capture_time_us <= done_us
    assert all(f.capture_time_us - frames[0].capture_time_us in (50_000, 100_000) for f in frames[1:])


def test_video_file_stamps_from_when_the_first_frame_is_read(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (32, 24))
    for k in range(4):
        writer.write(np.full((24, 32, 3), 40 * k, np.uint8))
    writer.release()
    source = sources.open_source(CameraConfig(source=str(path), replay="every_frame"))
    ready_us = time.time_ns() // 1000
    frames = list(source.frames())
    assert len(frames) == 4 and ready_us <= frames[0].capture_time_us
    assert [f.capture_time_us - frames[0].capture_time_us for f in frames] == [0, 40_000, 80_000, 120_000]
