"""Where a frame's markers will be in a later frame of the same camera (a detector's tracking state), and
the board on which a camera's detection workers share it.

Each marker found is predicted from its corners, the image motion it made over the interval before and
the camera's turn since (from the autopilot's attitude): constant velocity in the image, the turn taken
out, scaled to the time that has passed (a frame skipped by a busy detector is crossed, not mistaken for
one period).

With N worker processes a worker sees every N-th frame of its camera. Each posts its frame's tracks on
the camera's board as soon as its search is done, before the rest of its work; a worker starting a frame
predicts from the newest tracks any worker of the camera has posted before that frame (once the pipeline
is full, the frame one period back) instead of its own frame N periods back: a prediction over one period
stays within the follow's reach far more often than one over N periods.
"""

from __future__ import annotations

import math
import mmap
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

Corners = dict[int, NDArray[np.float64]]


@dataclass(frozen=True)
class Tracks:
    """The markers found in a frame: their ``corners`` (4, 2) each, those of the same markers in the frame
    before (``previous``, ``interval_us`` earlier; 0: none) and the part of their motion since then that
    the camera's turn did not explain (``drift``: the drone's travel), and the camera's orientation at
    the capture when the autopilot's attitude was there (``attitude``: R_level_camera)."""

    capture_time_us: int | None
    corners: Corners
    previous: Corners
    drift: Corners
    interval_us: int = 0
    attitude: Rotation | None = None

    def ratio(self, capture_time_us: int | None) -> float:
        """The time from this frame to one captured at ``capture_time_us`` over the interval its motion
        was measured over (1 where either is unknown, or where the stamps do not increase: a replay
        started again, a clock stepped back)."""
        if capture_time_us is None or self.capture_time_us is None or self.interval_us <= 0:
            return 1.0
        if capture_time_us <= self.capture_time_us:
            return 1.0
        return (capture_time_us - self.capture_time_us) / self.interval_us

    def turn_to(self, attitude: Rotation | None) -> Rotation | None:
        """The camera's turn from this frame to one whose orientation is ``attitude`` (maps directions in
        the camera frame then into the camera frame of this one); None unless both are known."""
        if attitude is None or self.attitude is None:
            return None
        return self.attitude.inv() * attitude

    def predicted(
        self,
        capture_time_us: int | None,
        R_prev_now: Rotation | None,
        rotate: Callable[[NDArray[np.float64], Rotation], NDArray[np.float64]],
    ) -> tuple[Corners, Corners]:
        """Each marker's corners predicted in a frame captured at ``capture_time_us``, and (given the
        camera's turn ``R_prev_now`` since this frame) where the turn alone moves them (``rotate``: every
        marker's corners (M, 4, 2) at once, :meth:`atlas_onboard.detector.search.RegionSearch.rotated`),
        empty without it."""
        r = self.ratio(capture_time_us)
        if R_prev_now is not None:
            ids = list(self.corners)
            turned = (
                dict(zip(ids, rotate(np.array([self.corners[i] for i in ids]), R_prev_now), strict=True)) if ids else {}
            )
            return {i: c + self.drift.get(i, 0.0) * r for i, c in turned.items()}, turned
        if r == 1.0:  # one period on, as most frames are: 2c - c_prev, exactly as it always was
            return {i: 2 * c - self.previous[i] if i in self.previous else c for i, c in self.corners.items()}, {}
        return {i: c + (c - self.previous[i]) * r if i in self.previous else c for i, c in self.corners.items()}, {}

    def then(self, capture_time_us: int | None, corners: Corners, turned: Corners, attitude: Rotation | None) -> Tracks:
        """The tracks of the next frame searched: its ``corners``, moved on from these (``turned``: where
        the camera's turn alone moved them, from :meth:`predicted`)."""
        interval = 0
        if capture_time_us is not None and self.capture_time_us is not None:
            interval = capture_time_us - self.capture_time_us
        drift = {i: c - turned[i] for i, c in corners.items() if i in turned}
        return Tracks(capture_time_us, corners, self.corners, drift, interval, attitude)


NO_TRACKS = Tracks(None, {}, {}, {})


class SharedTracks(Protocol):
    """A worker's place on its camera's board (:class:`BoardSlot`)."""

    def post(self, tracks: Tracks) -> None: ...

    def newer(self, own: Tracks, capture_time_us: int) -> Tracks | None: ...


MAX_TRACKS = 1024  # markers a slot holds (the most of a frame's markers shared; more are tracked by the worker)
_HEADER = 9  # float64 words: version, capture time, interval, count, attitude quaternion (x, y, z, w), checksum
_RECORD = 25  # float64 words a marker: id, corners, previous corners, drift (NaN where none)
_SLOT_WORDS = _HEADER + MAX_TRACKS * _RECORD


class TrackBoard:
    """Memory shared by a camera's workers (an anonymous file, Linux's ``memfd``), one slot per worker:
    each writes only its own, the others read it. A slot's version is odd while its worker writes it (a
    sequence lock: a reader that saw it change gives up and predicts from its own). A checksum over the
    slot's words guards against a reader on a processor that makes the writes visible out of order."""

    def __init__(self, memory: mmap.mmap, slots: int) -> None:
        self.memory = memory
        self.slots = slots
        words = np.frombuffer(memory, np.float64, count=slots * _SLOT_WORDS)
        self._slots = words.reshape(slots, _SLOT_WORDS)

    @staticmethod
    def size(slots: int) -> int:
        """Bytes of a board of ``slots`` slots."""
        return slots * _SLOT_WORDS * 8

    @classmethod
    def create(cls, slots: int, name: str) -> int | None:
        """The file descriptor of a new, empty board of ``slots`` (to pass to the workers, who map it);
        None where there is no ``memfd``."""
        try:
            fd = os.memfd_create(f"atlas-onboard-tracks-{name}", os.MFD_CLOEXEC)
        except (AttributeError, OSError):
            return None
        os.ftruncate(fd, cls.size(slots))
        return fd

    @classmethod
    def attach(cls, fd: int, slots: int) -> TrackBoard:
        """The board of ``slots`` whose descriptor is ``fd`` (the descriptor may be closed after)."""
        return cls(mmap.mmap(fd, cls.size(slots)), slots)

    def write(self, slot: int, tracks: Tracks) -> None:
        s = self._slots[slot]
        ids = sorted(tracks.corners)[:MAX_TRACKS]
        s[0] += 1.0  # odd: being written
        s[1] = np.nan if tracks.capture_time_us is None else tracks.capture_time_us
        s[2] = tracks.interval_us
        s[3] = len(ids)
        s[4:8] = np.nan if tracks.attitude is None else tracks.attitude.as_quat()
        rec = s[_HEADER : _HEADER + len(ids) * _RECORD].reshape(len(ids), _RECORD)
        nan = np.full((4, 2), np.nan)
        for row, i in zip(rec, ids, strict=True):
            row[0] = i
            row[1:9] = tracks.corners[i].ravel()
            row[9:17] = tracks.previous.get(i, nan).ravel()
            row[17:25] = tracks.drift.get(i, nan).ravel()
        s[8] = _checksum(s[1:8], rec)
        s[0] += 1.0  # even: complete

    def stamp(self, slot: int) -> float:
        """The capture stamp of the slot's tracks as last written (NaN if none; read whole with :meth:`read`)."""
        s = self._slots[slot]
        return math.nan if s[0] == 0.0 else float(s[1])

    def read(self, slot: int) -> Tracks | None:
        """The slot's tracks, None if empty or being written (read twice over and changed between)."""
        s = self._slots[slot]
        version = float(s[0])
        if version == 0.0 or version % 2 == 1.0:
            return None
        header = s[:_HEADER].copy()
        if not 0 <= header[3] <= MAX_TRACKS:  # (NaN too)
            return None
        rec = s[_HEADER : _HEADER + int(header[3]) * _RECORD].copy().reshape(-1, _RECORD)
        if float(s[0]) != version or np.isnan(header[1]) or _checksum(header[1:8], rec) != header[8]:
            return None
        corners, previous, drift = {}, {}, {}
        for row in rec:
            i = int(row[0])
            corners[i] = row[1:9].reshape(4, 2)
            if not np.isnan(row[9]):
                previous[i] = row[9:17].reshape(4, 2)
            if not np.isnan(row[17]):
                drift[i] = row[17:25].reshape(4, 2)
        attitude = None if np.isnan(header[4]) else Rotation.from_quat(header[4:8])
        return Tracks(int(header[1]), corners, previous, drift, int(header[2]), attitude)


def _checksum(header: NDArray[np.float64], records: NDArray[np.float64]) -> float:
    return float(np.nansum(header) + np.nansum(records))


@dataclass
class BoardSlot:
    """A worker's slot on its camera's board: it posts there, and reads the others'."""

    board: TrackBoard
    slot: int

    def post(self, tracks: Tracks) -> None:
        """Share this worker's newest tracks (those of a frame not stamped are not shared)."""
        if tracks.capture_time_us is not None:
            self.board.write(self.slot, tracks)

    def newer(self, own: Tracks, capture_time_us: int) -> Tracks | None:
        """The newest tracks another worker posted of a frame captured after ``own``'s and before
        ``capture_time_us``; None if there are none (or the newest cannot be read whole). Only that
        slot is read whole: the others' stamps are enough to pass them over."""
        after = -math.inf if own.capture_time_us is None else own.capture_time_us
        stamps = [(self.board.stamp(k), k) for k in range(self.board.slots) if k != self.slot]
        fit = [(t, k) for t, k in stamps if after < t < capture_time_us]  # (NaN: never written)
        if not fit:
            return None
        got = self.board.read(max(fit)[1])
        if got is None or got.capture_time_us is None or not after < got.capture_time_us < capture_time_us:
            return None
        return got
