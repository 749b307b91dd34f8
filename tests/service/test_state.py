"""What the node keeps across restarts (service/state.py) and the atomic write under it (fsio.py)."""

import os
import stat

import pytest

from atlas_onboard.fsio import write_atomic
from atlas_onboard.service.state import ResetCounterStore


def test_each_start_signals_a_reset_to_the_autopilot(tmp_path):
    first = ResetCounterStore(tmp_path / "state", "drone").initial(wall_ns=7_000_000_000)
    second = ResetCounterStore(tmp_path / "state", "drone").initial(wall_ns=7_000_000_000)
    assert first == 7 and second == 8  # the clock's seconds the first time, one past the saved value after
    store = ResetCounterStore(tmp_path / "state", "drone")
    store.save(255)
    assert ResetCounterStore(tmp_path / "state", "drone").initial(0) == 0  # wraps like the uint8 field


def test_an_unreadable_state_file_falls_back_to_the_clock(tmp_path):
    (tmp_path / "reset-counter-drone.json").write_text("{not json", encoding="utf-8")
    assert ResetCounterStore(tmp_path, "drone").initial(wall_ns=300 * 1_000_000_000) == 300 % 256


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path, monkeypatch):
    path = tmp_path / "f.json"
    write_atomic(path, "old")
    assert stat.S_IMODE(path.stat().st_mode) == 0o644

    def fail(*_a):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", fail)
    with pytest.raises(OSError):
        write_atomic(path, b"new", mode=0o600)
    assert path.read_text() == "old" and [p.name for p in tmp_path.iterdir()] == ["f.json"]
