"""Following tracked markers without the library (detector.follow, driven by Detector.find): against the
rendered truth and against the library's corners on real photographs; a wrong id, a wrong orientation,
a prediction beyond reach and a marker gone are never followed."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from atlas_onboard.detector import pipeline
from atlas_onboard.detector.backends import MarkerFinder
from atlas_onboard.detector.follow import MIN_CELL_PX, REACH_CELLS, follow, pattern
from atlas_onboard.detector.refine import refine_markers_undistorted
from atlas_onboard.detector.search import side
from tests.detector.test_finder import corner_errors_px, frame, tracker, truth_corners, view_at
from tests.detector.test_realdata import images

CELLS = 8  # tag36h11's detected square


def test_a_drifting_marker_is_followed_without_the_library_as_exactly_as_it_places_corners(monkeypatch):
    """A marker about 70 px wide drifting 20 px a frame, the tracker alone (no contrast candidates, no
    whole-image searches): in the frame after the hunt's, 20 px from where it was (no motion known yet,
    beyond the reach) the library finds it in its region; from then on (its motion predicted) the library
    is never called, the marker is followed every frame, and its corners are no farther from the truth
    than the library's own on the same frame (at decimate 1, its most exact), give or take a tenth of a
    pixel."""
    monkeypatch.setattr(pipeline, "CANDIDATE_AREA", 0.0)
    monkeypatch.setattr(pipeline, "SCAN_EVERY", 10**6)
    det = tracker()
    library = MarkerFinder({25: "tag36h11"}, decimate=1.0)
    calls = []
    find = det.finder.find
    det.finder.find = lambda gray, decimate=None: calls.append(gray.shape) or find(gray, decimate)  # type: ignore[method-assign]
    for k in range(10):
        views = [view_at(25, 220 + 20 * k, 240 - 6 * k, 1.05)]
        img = frame(views, seed=k)
        calls.clear()
        errs = corner_errors_px(det.find(img), views)
        assert set(errs) == {25}, f"frame {k}: lost"
        if k == 1:
            assert len(calls) == 1 and calls[0] != img.shape  # its region
        if k > 1:
            assert calls == [], f"frame {k}: the library was called"
            truth = truth_corners(views[0])
            lib_err = float(np.abs(library.find(img)[0].corners_px - truth).max())
            assert errs[25] <= lib_err + 0.1, (k, errs[25], lib_err)
    assert det.counters["followed"] == 8


def _marker_image():
    view = view_at(25, 320, 240, 1.0)
    return frame([view], seed=4), truth_corners(view)


def test_only_the_marker_with_the_pattern_in_its_orientation_is_followed():
    """Predicted exactly where marker 25 is: followed as 25; as 11 or 3 (another code) not; as 25 with its
    corners in another order (turned a quarter, a half; mirrored) not."""
    img, truth = _marker_image()
    got = follow(img, {25: ("tag36h11", truth + 0.8)})
    assert set(got) == {25} and np.abs(got[25].corners_px - truth).max() < 0.3
    assert follow(img, {11: ("tag36h11", truth), 3: ("tag36h11", truth)}) == {}
    for turned in (np.roll(truth, 1, axis=0), np.roll(truth, 2, axis=0), truth[::-1]):
        assert follow(img, {25: ("tag36h11", turned)}) == {}


@pytest.mark.parametrize("direction_deg", [0, 60, 135, 250])
def test_a_prediction_within_reach_is_placed_on_the_marker_and_one_beyond_it_is_left_to_the_library(direction_deg):
    """Predicted off by up to the reach (a few tenths of a cell, in any direction): followed, its corners
    within a third of a pixel of the truth. Off by two cells: not followed (no edge of its own within
    reach; the library searches its region)."""
    img, truth = _marker_image()
    cell = side(truth) / CELLS
    u = np.array([np.cos(np.radians(direction_deg)), np.sin(np.radians(direction_deg))])
    for shift_cells in (0.2, 0.45, 0.6 * REACH_CELLS):
        got = follow(img, {25: ("tag36h11", truth + shift_cells * cell * u)})
        assert set(got) == {25}, shift_cells
        assert np.abs(got[25].corners_px - truth).max() < 1 / 3
    assert follow(img, {25: ("tag36h11", truth + 2.0 * cell * u)}) == {}


def test_a_marker_gone_from_its_place_is_not_followed():
    """The floor alone where the marker was, or half of it: nothing followed, whatever the texture's edges;
    nor any other id than the marker's where it is."""
    view = view_at(25, 320, 240, 1.0)
    floor = frame([], seed=4)
    assert follow(floor, {25: ("tag36h11", truth_corners(view))}) == {}
    half = frame([view], seed=4)
    half[:240] = floor[:240]  # its upper half gone (covered by the floor)
    assert follow(half, {25: ("tag36h11", truth_corners(view))}) == {}
    # every id of the family predicted there at once (more than one batch): none is it
    everyone = {i: ("tag36h11", truth_corners(view)) for i in range(587) if i != 25}
    assert follow(frame([view], seed=4), everyone) == {}


def test_real_photographs_markers_are_followed_and_refitted_where_the_librarys_corners_are_refitted():
    """The swatbotics photographs (real prints, light, blur and lens): of the markers the library finds at
    decimate 1 with cells of at least ``MIN_CELL_PX``, each predicted a third of a cell away, nine in ten or
    more are followed; from each followed marker's corners the corner refit (the detector's next step)
    lands where it lands from the library's: a fiftieth of a pixel apart in the median, and no marker more
    than half a pixel (the refit's own dependence on where it starts, on small markers in JPEG photos; a
    marker followed onto something else would be pixels off)."""
    library = MarkerFinder({i: "tag36h11" for i in range(587)}, decimate=1.0)
    rng = np.random.default_rng(1)
    tried = followed = 0
    apart: list[float] = []
    for kind in ("mapping_feb_2014", "clipboard"):
        for path, _expected in images(kind):
            gray = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            for d in library.find(gray):
                cell = side(d.corners_px) / CELLS
                if cell < MIN_CELL_PX:
                    continue
                tried += 1
                u = rng.normal(size=2)
                got = follow(gray, {d.marker_id: ("tag36h11", d.corners_px + cell / 3 * u / np.linalg.norm(u))})
                if d.marker_id not in got:
                    continue
                followed += 1
                K = np.array([[300.0, 0, (gray.shape[1] - 1) / 2], [0, 300.0, (gray.shape[0] - 1) / 2], [0, 0, 1]])
                a, b = refine_markers_undistorted(gray, [d.corners_px, got[d.marker_id].corners_px], K, np.zeros(5))
                assert (a is None) == (b is None), (path.name, d.marker_id)
                if a is not None and b is not None:
                    apart.append(float(np.abs(a.corners - b.corners).max()))
                    assert apart[-1] < 0.5, (path.name, d.marker_id)
    assert tried >= 100
    assert followed >= 0.9 * tried
    assert np.median(apart) < 0.02


def _paint_cell(img: np.ndarray, corners: np.ndarray, col: int, row: int, value: int) -> np.ndarray:
    """``img`` with the middle of cell (col, row) of the marker whose detected square has ``corners`` painted."""
    square = np.array([[0, 0], [CELLS, 0], [CELLS, CELLS], [0, CELLS]], np.float32)
    H = cv2.getPerspectiveTransform(square, corners.astype(np.float32))
    patch = np.array([[col + 0.2, row + 0.2], [col + 0.8, row + 0.2], [col + 0.8, row + 0.8], [col + 0.2, row + 0.8]])
    poly = cv2.perspectiveTransform(patch[None], H)[0]
    out = img.copy()
    cv2.fillConvexPoly(out, np.round(poly).astype(np.int32), value)
    return out


def test_data_cells_misread_are_accepted_as_the_librarys_decoding_corrects_them_border_cells_never():
    """tag36h11: up to the library's two corrected bits of data cells read wrong (say, dirt on the print),
    the marker is followed; three, or one cell of its black border, not."""
    img, truth = _marker_image()
    white = pattern("tag36h11", 25).white.reshape(CELLS, CELLS)
    data = [(c, r) for r in range(1, CELLS - 1) for c in range(1, CELLS - 1)]
    for n_wrong, ok in ((1, True), (2, True), (3, False)):
        dirty = img
        for c, r in data[:n_wrong]:
            dirty = _paint_cell(dirty, truth, c, r, 0 if white[r, c] else 255)
        assert (25 in follow(dirty, {25: ("tag36h11", truth)})) is ok, n_wrong
    assert follow(_paint_cell(img, truth, 3, 0, 255), {25: ("tag36h11", truth)}) == {}


def test_under_a_wide_lens_the_sides_are_fitted_where_they_are_straight():
    """A 15 cm marker 0.9 m away by the left edge of a wide-angle image (k1 = -0.3), where the lens bends
    its sides by pixels: given the calibration, the follow fits the sides in undistorted pixels and samples
    them where the lens puts them; its corners lie within a third of a pixel of the truth, closer than
    straight lines fitted in the image put them."""
    from scipy.spatial.transform import RigidTransform, Rotation

    from atlas_onboard.detector.calibration import Calibration
    from atlas_onboard.detector.render import MarkerView, render
    from tests.detector.test_finder import CAM_WIDE, DIST, K_WIDE, SIZE, H, W, distorted_corners

    T = RigidTransform.from_components([-0.5, 0.05, 0.9], Rotation.from_euler("xy", [180, -25], degrees=True))
    img = render(CAM_WIDE, [MarkerView("tag36h11", 25, SIZE, T)], seed=3, noise_sigma=2.0, blur_px=(0.8, 0.3),
                 supersample=3, background_style="concrete", background_seed=1)  # fmt: skip
    truth = distorted_corners(T)
    assert truth[:, 0].min() < 60  # near the image's left edge
    cal = Calibration(W, H, K_WIDE, DIST)
    bent = follow(img, {25: ("tag36h11", truth + 1.0)}, cal)
    straight = follow(img, {25: ("tag36h11", truth + 1.0)})
    err = np.abs(bent[25].corners_px - truth).max()
    assert err < 1 / 3
    assert 25 not in straight or err < np.abs(straight[25].corners_px - truth).max()
