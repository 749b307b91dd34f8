"""A detector's tracks (detector.tracks): the prediction scaled to the time passed, the board a camera's
workers share them on (each slot written whole or not read), and two detectors dealt a camera's frames in
turn that predict from each other's newest frame as one detector does from its previous one."""

from __future__ import annotations

import mmap

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from atlas_onboard.detector import pipeline
from atlas_onboard.detector.tracks import NO_TRACKS, BoardSlot, TrackBoard, Tracks
from tests.detector.test_finder import frame, tracker, view_at

SQUARE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])
PERIOD_US = 33_333


def _moving(t_prev: int, t: int, velocity: np.ndarray, at: float = 100.0) -> Tracks:
    """Tracks of one marker moving at ``velocity`` px per period, seen at ``t_prev`` and ``t``."""
    c_prev = SQUARE + at + velocity * t_prev / PERIOD_US
    c = SQUARE + at + velocity * t / PERIOD_US
    return NO_TRACKS.then(t_prev, {7: c_prev}, {}, None).then(t, {7: c}, {}, None)


def test_constant_image_motion_is_predicted_over_any_time_passed():
    v = np.array([3.0, -2.0])
    tracks = _moving(0, PERIOD_US, v)
    for periods in (1, 2, 3):
        t = PERIOD_US * (1 + periods)
        got, turned = tracks.predicted(t, None, lambda c, R: c)
        np.testing.assert_allclose(got[7], SQUARE + 100.0 + v * (1 + periods), atol=1e-9)
        assert turned == {}
    # A stamp that does not increase (a replay started again): one period on, as without stamps.
    got, _ = tracks.predicted(0, None, lambda c, R: c)
    np.testing.assert_allclose(got[7], SQUARE + 100.0 + 2 * v, atol=1e-9)
    # Without stamps: one period on.
    unstamped = NO_TRACKS.then(None, {7: SQUARE}, {}, None).then(None, {7: SQUARE + v}, {}, None)
    got, _ = unstamped.predicted(None, None, None)
    np.testing.assert_array_equal(got[7], SQUARE + 2 * v)


def test_with_a_turn_the_drift_is_what_the_turn_left_over_scaled_to_the_time_passed():
    """The turn moves the corners by ``rotate``; the drift (the motion the turn did not explain) is added
    for each period passed."""
    shift = np.array([5.0, 0.0])

    def rotate(c, R):  # a turn that moves every point 5 px right
        return c + shift

    drift = np.array([0.0, 1.5])
    first = NO_TRACKS.then(0, {7: SQUARE}, {}, None)
    _, turned = first.predicted(PERIOD_US, Rotation.identity(), rotate)
    second = first.then(PERIOD_US, {7: SQUARE + shift + drift}, turned, None)
    np.testing.assert_allclose(second.drift[7], np.tile(drift, (4, 1)))
    assert second.interval_us == PERIOD_US
    got, turned = second.predicted(3 * PERIOD_US, Rotation.identity(), rotate)
    np.testing.assert_allclose(turned[7], SQUARE + 2 * shift + drift)
    np.testing.assert_allclose(got[7], SQUARE + 2 * shift + 3 * drift)


def test_the_turn_between_two_frames_is_from_their_orientations():
    a = Rotation.from_euler("xyz", [10, -5, 30], degrees=True)
    turn = Rotation.from_euler("z", 4, degrees=True)
    tracks = NO_TRACKS.then(0, {}, {}, a)
    got = tracks.turn_to(a * turn)
    assert got is not None and got.approx_equal(turn, atol=1e-12)
    assert tracks.turn_to(None) is None and NO_TRACKS.turn_to(a) is None


def _board(slots: int) -> TrackBoard:
    return TrackBoard(mmap.mmap(-1, TrackBoard.size(slots)), slots)


def test_the_board_gives_back_what_was_posted_and_nothing_before():
    board = _board(2)
    assert board.read(0) is None and board.read(1) is None
    att = Rotation.from_euler("xyz", [1, 2, 3])
    tracks = _moving(0, PERIOD_US, np.array([1.0, 2.0]))
    tracks = Tracks(tracks.capture_time_us, tracks.corners | {3: SQUARE * 2}, tracks.previous, {7: SQUARE / 3},
                    tracks.interval_us, att)  # fmt: skip
    BoardSlot(board, 1).post(tracks)
    got = board.read(1)
    assert got is not None and board.read(0) is None
    assert (got.capture_time_us, got.interval_us) == (PERIOD_US, PERIOD_US)
    assert set(got.corners) == {3, 7} and set(got.previous) == {7} and set(got.drift) == {7}
    for i in (3, 7):
        np.testing.assert_array_equal(got.corners[i], tracks.corners[i])
    np.testing.assert_array_equal(got.previous[7], tracks.previous[7])
    np.testing.assert_array_equal(got.drift[7], tracks.drift[7])
    assert got.attitude is not None and got.attitude.approx_equal(att, atol=1e-15)
    # A frame with no stamp is not shared; a later post replaces the slot whole.
    BoardSlot(board, 1).post(NO_TRACKS)
    assert board.read(1).capture_time_us == PERIOD_US
    BoardSlot(board, 1).post(NO_TRACKS.then(5 * PERIOD_US, {9: SQUARE}, {}, None))
    got = board.read(1)
    assert got.capture_time_us == 5 * PERIOD_US and set(got.corners) == {9} and got.attitude is None


def test_a_slot_being_written_or_not_yet_wholly_visible_is_not_read():
    board = _board(2)
    BoardSlot(board, 0).post(_moving(0, PERIOD_US, np.array([1.0, 0.0])))
    board._slots[0, 0] += 1.0  # its worker is between the two halves of a write
    assert board.read(0) is None
    board._slots[0, 0] += 1.0  # the version says written, but a corner's new value is not visible yet
    assert board.read(0) is not None
    board._slots[0, 12] += 0.5
    assert board.read(0) is None
    assert BoardSlot(board, 1).newer(NO_TRACKS, 10 * PERIOD_US) is None


def test_a_worker_takes_the_newest_tracks_of_the_others_between_its_own_and_its_frame():
    board = _board(3)
    me, a, b = (BoardSlot(board, k) for k in range(3))
    own = NO_TRACKS.then(2 * PERIOD_US, {1: SQUARE}, {}, None)
    me.post(NO_TRACKS.then(9 * PERIOD_US, {1: SQUARE}, {}, None))  # its own slot is never taken
    a.post(NO_TRACKS.then(3 * PERIOD_US, {1: SQUARE}, {}, None))
    b.post(NO_TRACKS.then(4 * PERIOD_US, {1: SQUARE}, {}, None))
    assert me.newer(own, 5 * PERIOD_US).capture_time_us == 4 * PERIOD_US
    assert me.newer(own, 4 * PERIOD_US).capture_time_us == 3 * PERIOD_US  # not one of the frame itself
    assert me.newer(own, 3 * PERIOD_US) is None
    assert me.newer(NO_TRACKS.then(4 * PERIOD_US, {}, {}, None), 6 * PERIOD_US) is None  # none newer than its own


def _accelerating(k: int) -> float:
    """The marker's centre column in frame k: 10 px a frame, 1.5 px a frame more each frame."""
    return 200.0 + 10.0 * k + 1.5 * k * k


@pytest.mark.parametrize("shared", [True, False])
def test_two_detectors_dealt_frames_in_turn_follow_as_one_does_when_they_share_tracks(monkeypatch, shared):
    """An accelerating marker (about 70 px, 10 px a frame, 1.5 px a frame more each frame), the tracker
    alone (no contrast candidates, no whole-image searches). One detector on every frame predicts one
    period on and follows it from the third frame (the hunt, then the library's region). Two detectors
    given alternate frames: sharing a board, each predicts from the other's newest frame, one period back,
    and follows as often; each on its own predicts two periods on, where the acceleration puts the marker
    beyond the follow's reach."""
    monkeypatch.setattr(pipeline, "CANDIDATE_AREA", 0.0)
    monkeypatch.setattr(pipeline, "SCAN_EVERY", 10**6)
    frames = [frame([view_at(25, _accelerating(k), 240.0, 1.05)], seed=k) for k in range(10)]
    one = tracker()
    pair = [tracker(), tracker()]
    if shared:
        board = _board(2)
        for i, det in enumerate(pair):
            det.shared = BoardSlot(board, i)
    for k, img in enumerate(frames):
        assert [d.marker_id for d in one.find(img, None, k * PERIOD_US)] == [25]
        assert [d.marker_id for d in pair[k % 2].find(img, None, k * PERIOD_US)] == [25]
    followed = sum(d.counters["followed"] for d in pair)
    assert one.counters["followed"] == len(frames) - 2
    if shared:
        assert followed == one.counters["followed"]
        assert sum(d.counters["tracks_shared"] for d in pair) == len(frames) - 1
    else:
        assert followed < one.counters["followed"] - 3


def test_a_frame_skipped_by_a_busy_detector_is_crossed_not_taken_for_one_period(monkeypatch):
    """A marker drifting 20 px a frame, every third frame skipped (a detector slower than its camera):
    predicted over the time that passed, it is followed in every frame after the first two."""
    monkeypatch.setattr(pipeline, "CANDIDATE_AREA", 0.0)
    monkeypatch.setattr(pipeline, "SCAN_EVERY", 10**6)
    det = tracker()
    seen = [k for k in range(14) if k % 3 != 2]
    for k in seen:
        img = frame([view_at(25, 180.0 + 20.0 * k, 240.0 - 4.0 * k, 1.05)], seed=k)
        assert [d.marker_id for d in det.find(img, None, k * PERIOD_US)] == [25]
    assert det.counters["followed"] == len(seen) - 2


def test_two_detectors_sharing_tracks_turn_them_by_the_attitudes_of_the_frames_between(monkeypatch):
    """A camera turning fast, its turn reversing (the marker lost from its last image motion alone,
    tests/detector/test_finder.py), its frames dealt to two detectors in turn with the camera's
    orientation at each capture: each predicts from the other's newest frame turned by the orientations
    of the two frames, and the marker is found every frame, where the frame's turn puts it."""
    from atlas_onboard.detector.render import MarkerView, render
    from tests.detector.test_finder import CAM_WIDE, SIZE, distorted_corners, turning, wide_tracker

    monkeypatch.setattr(pipeline, "CANDIDATE_AREA", 0.0)
    monkeypatch.setattr(pipeline, "SCAN_EVERY", 10**6)
    poses = turning(14)
    board = _board(2)
    pair = [wide_tracker(), wide_tracker()]
    for i, det in enumerate(pair):
        det.shared = BoardSlot(board, i)
    misses = []
    for k, (R, T) in enumerate(poses):
        img = render(
            CAM_WIDE, [MarkerView("tag36h11", 25, SIZE, T)], seed=k, noise_sigma=2.0, background_style="concrete"
        )
        found = {d.marker_id: d for d in pair[k % 2].find(img, None, k * PERIOD_US, R)}
        if 25 not in found:
            misses.append(k)
        else:
            assert np.abs(found[25].corners_px - distorted_corners(T)).max() < 1.0
    assert set(misses) <= {0, 1}, misses  # the hunt (no candidates here) has found it by frame 1
    assert sum(d.counters["tracks_shared"] for d in pair) == len(poses) - 1
