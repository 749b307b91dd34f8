"""The tracked regions' search (detector.search, driven by Detector.find), against rendered ground truth."""

from __future__ import annotations

from atlas_onboard.detector import pipeline
from atlas_onboard.detector.search import MAX_REGION_DECIMATE, side
from tests.detector.test_finder import corner_errors_px, frame, tracker, truth_corners, view_at


def test_a_tracked_marker_is_searched_decimated_and_kept_to_its_corners(monkeypatch):
    """A marker about 70 px wide drifting across the image, the tracker alone (no contrast candidates,
    no whole-image searches while tracking): every frame's region about it is searched at the largest
    decimation that keeps the marker ``TRACKED_SIDE_PX`` wide, and it is found in it every frame with
    its corners within a pixel of the truth. The hunt's whole-image search at ``MAX_REGION_DECIMATE`` finds
    it (about 23 px wide there), so its region is searched decimated too (never at full resolution), the
    marker at least as wide in it as in the hunt."""
    monkeypatch.setattr(pipeline, "CANDIDATE_AREA", 0.0)
    monkeypatch.setattr(pipeline, "SCAN_EVERY", 10**6)
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
