"""The tracked regions' search (detector.search, driven by Detector.find), against rendered ground truth."""

from __future__ import annotations

import itertools

import numpy as np

from atlas_onboard.detector import pipeline, search
from atlas_onboard.detector.render import render
from atlas_onboard.detector.search import MAX_REGION_DECIMATE, side
from tests.detector.test_finder import CAM, corner_errors_px, frame, tracker, truth_corners, view_at


def test_a_tracked_marker_is_searched_decimated_and_kept_to_its_corners(monkeypatch):
    """A marker about 70 px wide drifting across the image, the tracker alone (no contrast candidates,
    no whole-image searches while tracking) and never followed without the library (as a marker that
    :func:`follow.follow` leaves to it): every frame's region about it is searched at the largest
    decimation that keeps the marker ``TRACKED_SIDE_PX`` wide, and it is found in it every frame with
    its corners within a pixel of the truth. The hunt's whole-image search at ``MAX_REGION_DECIMATE`` finds
    it (about 23 px wide there), so its region is searched decimated too (never at full resolution), the
    marker at least as wide in it as in the hunt."""
    monkeypatch.setattr(pipeline, "CANDIDATE_AREA", 0.0)
    monkeypatch.setattr(pipeline, "SCAN_EVERY", 10**6)
    monkeypatch.setattr(search, "follow", lambda gray, predicted, calibration=None: {})
    det = tracker()
    searched: list[tuple[tuple[int, ...], float, list[int]]] = []
    find = det.finder.find

    def spy(gray, decimate=None):  # type: ignore[no-untyped-def]
        out = find(gray, decimate)
        searched.append((gray.shape, float(decimate or det.finder.backends[0].decimate), [d.marker_id for d in out]))
        return out

    det.finder.find = spy  # type: ignore[method-assign]
    decimations, widths = [], []
    for k in range(10):
        views = [view_at(25, 220 + 20 * k, 240 - 6 * k, 1.05)]
        searched.clear()
        found = det.find(frame(views, seed=k))
        errs = corner_errors_px(found, views)
        assert set(errs) == {25}, f"frame {k}: lost"
        assert errs[25] < 1.0
        if k == 0:  # the hunt: the whole image at MAX_REGION_DECIMATE finds it
            assert searched[0] == ((480, 640), MAX_REGION_DECIMATE, [25])
        else:  # then only the tracked region is searched
            assert len(searched) == 1 and searched[0][0] != (480, 640)
            decimations.append(searched[0][1])
            widths.append(side(found[0].corners_px))
    assert min(decimations) >= 2.0
    hunt_width = side(truth_corners(view_at(25, 220, 240, 1.05))) / MAX_REGION_DECIMATE
    assert min(w / d for w, d in zip(widths, decimations, strict=True)) >= hunt_width


def _yawing(k: int, views: list) -> tuple[list, object]:
    """The views seen after the camera yawed ``k`` half degrees (markers fixed in the world), and that turn."""
    from scipy.spatial.transform import RigidTransform, Rotation

    from atlas_onboard.detector.render import MarkerView

    R = Rotation.from_euler("y", 0.5 * k, degrees=True)
    turn = RigidTransform.from_rotation(R.inv())
    return [MarkerView(v.family, v.marker_id, v.size_m, turn * v.T_camera_marker) for v in views], R


def _candidate_searches(det, monkeypatch):  # type: ignore[no-untyped-def]
    """A list that each frame's contrast-candidate searches (boxes x0, y0, x1, y1) are appended to (not
    the tiles of the grid, searched in turn whatever they hold)."""
    boxes: list[tuple[float, ...]] = []
    tiles: list[tuple[float, ...]] = []
    find_in, next_tile = det.search.find_in, det.search.next_tile

    def tile(w, h):  # type: ignore[no-untyped-def]
        t = next_tile(w, h)
        tiles.append(tuple(float(v) for v in t[:4]))
        return t

    def spy(gray, regions, found, only_new=False):  # type: ignore[no-untyped-def]
        if only_new:
            boxes.extend(b for b in (tuple(float(v) for v in r[:4]) for r in regions) if b not in tiles)
        return find_in(gray, regions, found, only_new)

    monkeypatch.setattr(det.search, "find_in", spy)
    monkeypatch.setattr(det.search, "next_tile", tile)
    return boxes


def test_a_tag_not_ours_is_searched_once_a_check_period_while_ours_are_found_every_frame(monkeypatch):
    """Two of our markers and one tag of the same family that is not in the world file, the camera
    yawing half a degree a frame (the turn given): the foreign tag's place is searched as a contrast
    candidate (a region holding its centre) at most once every ``FOREIGN_FRAMES`` frames, while both our markers
    are found within a pixel of the truth in every frame."""
    from atlas_onboard.detector.search import FOREIGN_FRAMES

    det = tracker()
    boxes = _candidate_searches(det, monkeypatch)
    world_views = [view_at(11, 260, 200, 3.0), view_at(25, 330, 330, 3.0), view_at(7, 420, 150, 3.5)]
    n = 2 * FOREIGN_FRAMES + 2
    searched = []
    previous = None
    for k in range(n):
        views, R = _yawing(k, world_views)
        boxes.clear()
        found = det.find(frame(views, seed=k), None if previous is None else previous.inv() * R)
        previous = R
        errs = corner_errors_px(found, views[:2])
        assert set(errs) == {11, 25}, f"frame {k}: {sorted(errs)}"
        assert max(errs.values()) < 1.0
        u, v = truth_corners(views[2]).mean(axis=0)
        assert 40 < u < 600, "the foreign tag stays in view"
        if any(x0 <= u <= x1 and y0 <= v <= y1 for x0, y0, x1, y1 in boxes):
            searched.append(k)
    assert searched, "the foreign tag is a candidate at all"
    gaps = [b - a for a, b in itertools.pairwise(searched)]
    assert min(gaps, default=FOREIGN_FRAMES) >= FOREIGN_FRAMES, searched
    assert len(searched) <= 1 + (n - 1) // FOREIGN_FRAMES


def test_a_tag_not_ours_replaced_by_one_of_ours_is_found_within_a_check_period():
    """A foreign tag in view for a few frames, then one of ours (same size, same place): ours is found
    no later than ``FOREIGN_FRAMES`` frames after it appears, its corners within a pixel."""
    from atlas_onboard.detector.search import FOREIGN_FRAMES

    det = tracker()
    ours = view_at(11, 260, 200, 3.0)
    for k in range(4):
        assert [d.marker_id for d in det.find(frame([ours, view_at(7, 420, 150, 3.5)], seed=k))] == [11]
    first = None
    for k in range(4, 4 + FOREIGN_FRAMES + 1):
        views = [ours, view_at(40, 420, 150, 3.5)]
        found = det.find(frame(views, seed=k))
        errs = corner_errors_px(found, views)
        if 40 in errs:
            assert errs[40] < 1.0
            first = k if first is None else first
    assert first is not None and first - 4 <= FOREIGN_FRAMES


def test_a_marker_of_ours_that_comes_in_beside_a_tag_not_ours_is_found_at_once():
    """A foreign tag in view for a few frames (remembered), then one of ours comes in right beside it:
    ours is found in the frame it appears, its corners within a pixel."""
    det = tracker()
    foreign = view_at(7, 420, 150, 3.5)
    for k in range(4):
        assert det.find(frame([foreign], seed=k)) == []
    assert det.search.foreign, "the foreign tag is remembered"
    views = [foreign, view_at(40, 462, 160, 3.5)]
    errs = corner_errors_px(det.find(frame(views, seed=4)), views)
    assert set(errs) == {40}
    assert errs[40] < 1.0


def _print_box(view) -> tuple[float, float, float, float]:  # type: ignore[no-untyped-def]
    """The box of a marker's whole print in the image: its true corners' box grown by the white quiet
    zone (a cell of the 8 across tag36h11's detected square) at its longest side."""
    c = truth_corners(view)
    q = max(side_px for side_px in np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)) / 8
    (x0, y0), (x1, y1) = c.min(axis=0) - q, c.max(axis=0) + q
    return x0, y0, x1, y1


def test_a_found_markers_own_print_is_explained_and_not_a_candidate():
    """A marker close up on a floor darker than its paper, found: the edge of its print (the white quiet
    zone on the floor) is strong contrast outside its corners, a candidate region unless the print explains it; with the
    print's box among the explained ones, no candidate is left about it."""
    from atlas_onboard.detector.search import cell_contrast, contrast_regions, printed_boxes

    det = tracker()
    view = view_at(11, 300, 240, 0.8)
    gray = render(CAM, [view], seed=1, noise_sigma=3.0, supersample=3, background_style="smooth", background_seed=2)
    found = det.find(gray)
    assert [d.marker_id for d in found] == [11]
    contrast, top = cell_contrast(gray)
    taken = [np.concatenate([d.corners_px.min(axis=0), d.corners_px.max(axis=0)]) for d in found]
    x0, y0, x1, y1 = _print_box(view)

    def about_the_print(regions):  # type: ignore[no-untyped-def]
        return [r for r in regions if r[0] < x1 and r[2] > x0 and r[1] < y1 and r[3] > y0]

    assert about_the_print(contrast_regions(contrast, top, taken, 1e9)), "the print's edge is strong contrast"
    explained = printed_boxes(found)
    np.testing.assert_allclose(explained[0], [x0, y0, x1, y1], atol=3.0)  # the true print's box, within 3 px
    assert about_the_print(contrast_regions(contrast, top, taken, 1e9, explained=explained)) == []


def test_a_marker_of_ours_that_comes_in_print_to_print_beside_a_found_one_is_found_at_once():
    """One of ours tracked, then another comes in with its print touching the first's: the new one's
    contrast is its own, not explained by the first's print, and it is found in the frame it appears."""
    det = tracker()
    first = view_at(11, 260, 200, 3.0)
    for k in range(4):
        assert [d.marker_id for d in det.find(frame([first], seed=k))] == [11]
    x0, _, x1, _ = _print_box(first)
    beside = view_at(40, 260 + (x1 - x0) * 1.02, 200, 3.0)  # print to print, a 2 % gap
    assert _print_box(beside)[0] - x1 < 0.05 * (x1 - x0)
    views = [first, beside]
    errs = corner_errors_px(det.find(frame(views, seed=4)), views)
    assert set(errs) == {11, 40}
    assert max(errs.values()) < 1.0


def test_the_search_explains_the_prints_of_the_markers_found_besides_the_tags_not_ours():
    """What ``Detector.find`` hands the contrast search as explained: each found marker's print box."""
    from atlas_onboard.detector.search import printed_boxes

    det = tracker()
    views = [view_at(11, 260, 200, 1.2), view_at(25, 420, 320, 1.2)]
    found = det.find(frame(views, seed=0))
    assert sorted(d.marker_id for d in found) == [11, 25]
    explained = det.search.explained(1, None, found)
    assert len(explained) == 2
    for d, box_ in zip(found, explained, strict=True):
        np.testing.assert_array_equal(box_, printed_boxes([d])[0])
        np.testing.assert_allclose(box_, _print_box(next(v for v in views if v.marker_id == d.marker_id)), atol=3.0)
