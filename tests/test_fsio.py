"""Atomic writes: the new content whole with the asked mode, no temporary file left behind, and on a
failure the old file untouched."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from atlas_onboard.fsio import write_atomic


def _mode(path: Path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


def test_text_and_bytes_replace_the_file_whole_with_the_asked_mode(tmp_path):
    target = tmp_path / "state.json"
    target.write_text("old")
    write_atomic(target, "néw\n")
    assert target.read_bytes() == "néw\n".encode()
    assert _mode(target) == 0o644
    write_atomic(target, b"\x00\x01secret", mode=0o600)
    assert target.read_bytes() == b"\x00\x01secret" and _mode(target) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["state.json"]  # no temporary left


def test_missing_directories_are_made_only_when_asked(tmp_path):
    target = tmp_path / "a" / "b" / "f.txt"
    with pytest.raises(FileNotFoundError):
        write_atomic(target, "x")
    assert not (tmp_path / "a").exists()
    write_atomic(target, "x", make_dirs=True)
    assert target.read_text() == "x"


def test_a_failed_replace_leaves_the_old_content_and_no_temporary(tmp_path):
    target = tmp_path / "dir"
    target.mkdir()
    (target / "inside").write_text("kept")
    with pytest.raises(OSError):
        write_atomic(target, "cannot replace a directory with a file")
    assert (target / "inside").read_text() == "kept"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["dir"]
