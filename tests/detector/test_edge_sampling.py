"""Where a frame's marker edges are sampled, against squares whose answers are known by hand: points
along each side, outward normals, the search across each edge (a tenth of the marker's depth, 1 to 6 px,
padded with its outermost offset) and its cell (an eighth of the depth)."""

from __future__ import annotations

import numpy as np
import pytest

from atlas_onboard.detector.edge_sampling import STEP_PX, sample_places, sampling


def square(x0: float, y0: float, side: float) -> np.ndarray:
    """Corners in the detector's order (clockwise in the image, y down)."""
    return np.array([[x0, y0], [x0 + side, y0], [x0 + side, y0 + side], [x0, y0 + side]])


def test_two_squares_and_one_too_small_are_laid_out_row_by_row():
    s = sampling([square(100, 100, 80), square(300, 50, 5), square(400, 300, 20)])
    assert s is not None
    assert s.markers == [0, 2]  # the 5 px square has no side long enough to fit
    # 70 % of the shortest side, one sample a pixel, within [12, 24]: 56 -> 24, 14 -> 14.
    assert s.samples == [24, 14] and s.starts == [0, 96]
    assert len(s.bases) == 96 + 56
    # The big square's first side runs from (100, 100) to (180, 100): its points from 15 % to 85 % of it,
    # its outward normal up (y down in the image).
    np.testing.assert_allclose(
        s.bases[:24], np.column_stack([100 + 80 * np.linspace(0.15, 0.85, 24), np.full(24, 100)])
    )
    np.testing.assert_allclose(s.normals[:24], np.tile([0.0, -1.0], (24, 1)), atol=1e-15)
    np.testing.assert_allclose(s.normals[24:48], np.tile([1.0, 0.0], (24, 1)), atol=1e-15)  # right side
    # The search: a tenth of the depth, 8 px -> 6 px at most, in quarter pixels; the small square's 2 px,
    # padded with its outermost offset to the big one's width.
    assert s.offsets.shape == (152, 49)
    np.testing.assert_allclose(s.offsets[0], np.arange(-6.0, 6.0 + 1e-9, STEP_PX), atol=1e-12)
    assert s.counts[0] == 49 and s.counts[96] == 17
    np.testing.assert_allclose(s.offsets[96, :17], np.arange(-2.0, 2.0 + 1e-9, STEP_PX), atol=1e-12)
    assert np.all(s.offsets[96, 17:] == s.offsets[96, 16])
    np.testing.assert_allclose(s.cells, np.r_[np.full(96, 10.0), np.full(56, 2.5)])


def test_normals_point_out_whatever_the_corners_order():
    ccw = square(0, 0, 40)[::-1]
    s = sampling([ccw])
    assert s is not None
    centre = ccw.mean(axis=0)
    # Each row's normal points away from the centre: base + normal is farther from it than the base.
    out = np.linalg.norm(s.bases + s.normals - centre, axis=1) > np.linalg.norm(s.bases - centre, axis=1)
    assert out.all()


@pytest.mark.parametrize("corners", [[], [square(0, 0, 7.9)]])
def test_nothing_to_sample_is_none(corners):
    assert sampling(corners) is None


def test_sample_places_are_from_15_to_85_percent_and_read_only():
    ts = sample_places(12)
    np.testing.assert_allclose(ts, np.linspace(0.15, 0.85, 12))
    with pytest.raises(ValueError):
        ts[0] = 0.0
