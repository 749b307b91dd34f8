"""Where a marker's edge lies on profiles sampled across it, against known answers: ramps of any width
and place, padded profiles against each alone, and how far levels short of the marker's ink and paper
may have pulled an edge."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.detector import edge_profile, edge_sampling


@settings(max_examples=100, deadline=None)
@given(
    halves=st.lists(st.sampled_from([1.0, 1.3, 2.45, 4.0, 6.0]), min_size=4, max_size=4),
    edges=st.lists(st.floats(-0.8, 0.8), min_size=4, max_size=4),
    seed=st.integers(0, 2**31),
)
def test_half_level_of_padded_sides_equals_each_side_alone(halves: list[float], edges: list[float], seed: int):
    """Four sides' profiles of different lengths, each padded with its last sample to the longest: every
    edge offset and ramp is what the side's own profiles alone give, NaNs where they are."""
    rng = np.random.default_rng(seed)
    rows = 12
    offsets = [np.arange(-h, h + 1e-9, edge_sampling.STEP_PX) for h in halves]
    profiles = []
    for i, (off, edge) in enumerate(zip(offsets, edges, strict=True)):
        blur = 0.3 if i == 0 else rng.uniform(0.2, 1.5)
        contrast = 150.0 if i == 0 else rng.choice([5.0, 60.0, 150.0])  # some below MIN_CONTRAST: no edge placed
        prof = 40 + contrast / (1 + np.exp(-(off[None, :] - edge) / blur)) + rng.normal(0, 3, (rows, len(off)))
        profiles.append(prof.astype(np.float32))
    width = max(len(o) for o in offsets)
    padded_prof = np.concatenate([np.pad(p, ((0, 0), (0, width - p.shape[1])), mode="edge") for p in profiles])
    padded_off = np.repeat([np.pad(o, (0, width - len(o)), mode="edge") for o in offsets], rows, axis=0)
    counts = np.repeat([len(o) for o in offsets], rows)
    cells = np.repeat(2.5 * np.array(halves), rows)  # a cell a little larger than the search, as refine's
    found, ramp, levels = edge_profile.place_edges(padded_prof, padded_off, counts, cells)
    for i, (prof, off) in enumerate(zip(profiles, offsets, strict=True)):
        alone = edge_profile.place_edges(
            prof, np.tile(off, (rows, 1)), np.full(rows, len(off)), np.full(rows, 2.5 * halves[i])
        )
        np.testing.assert_array_equal(found[i * rows : (i + 1) * rows], alone[0])
        np.testing.assert_array_equal(ramp[i * rows : (i + 1) * rows], alone[1])
        np.testing.assert_array_equal(levels[i * rows : (i + 1) * rows], alone[2])
    assert np.isfinite(found[:rows]).any()  # the first side's sharp strong edge was placed


def test_half_level_places_a_known_edge():
    """A clean step from 50 to 200 grey levels between the samples at 0.5 and 0.75: the profile, linear
    between its samples, has the area of a step midway between them."""
    off = np.arange(-3.0, 3.0 + 1e-9, 0.25)
    prof = np.where(off < 0.6, 50.0, 200.0).astype(np.float32)[None, :]
    found, ramp, levels = edge_profile.place_edges(prof, off[None, :], np.array([len(off)]), np.array([8.0]))
    assert abs(found[0] - (0.5 + 0.75) / 2) < 1e-9
    assert ramp[0] == 0.25  # the whole contrast within one step
    # dark, light, the window's half width, and no change over the last half pixel to either end (settled)
    assert levels[0].tolist() == [50.0, 200.0, edge_profile.AREA_HALF_WIDTH_PX, 0.0, 0.0]


@settings(max_examples=100, deadline=None)
@given(
    steps=st.integers(2, 8),
    edge=st.floats(-1.0, 1.0),
    dark=st.floats(0.0, 100.0),
    contrast=st.floats(30.0, 150.0),
)
def test_a_linear_ramp_is_placed_at_its_middle_with_its_width(steps: int, edge: float, dark: float, contrast: float):
    """A ramp from ``dark`` to ``dark + contrast`` over a whole number of sample steps, centred anywhere
    between samples: the profile, linear between its samples, loses as much area at the ramp's foot as it
    gains at its top, so the area's step is the ramp's middle; the steepest slope gives its width."""
    off = np.arange(-6.0, 6.0 + 1e-9, edge_sampling.STEP_PX)
    width = steps * edge_sampling.STEP_PX
    prof = (dark + contrast * np.clip((off - edge) / width + 0.5, 0.0, 1.0)).astype(np.float64)[None, :]
    found, ramp, levels = edge_profile.place_edges(prof, off[None, :], np.array([len(off)]), np.array([8.0]))
    assert abs(found[0] - edge) < 1e-9
    assert abs(ramp[0] - width) < 1e-9
    dark_level, light_level, reach, unsettled_dark, unsettled_light = levels[0]
    assert abs(dark_level - dark) < 1e-9 and abs(light_level - (dark + contrast)) < 1e-9
    # the window's half width, or the ramp's where wider (a ramp of 2 px found to rounding: 2 + 4e-16)
    assert abs(reach - max(edge_profile.AREA_HALF_WIDTH_PX, width)) < 1e-9
    assert unsettled_dark == 0.0 and unsettled_light == 0.0


def test_too_little_contrast_or_two_crossings_place_no_edge():
    off = np.arange(-3.0, 3.0 + 1e-9, 0.25)
    faint = np.where(off < 0.1, 100.0, 100.0 + edge_profile.MIN_CONTRAST - 1.0)
    twice = np.where((off < -1.0) | ((off > 0.0) & (off < 1.0)), 50.0, 200.0)  # rises through its half level twice
    prof = np.array([faint, twice])
    found, ramp, levels = edge_profile.place_edges(
        prof, np.tile(off, (2, 1)), np.array([len(off)] * 2), np.full(2, 8.0)
    )
    assert np.isnan(found).all() and np.isnan(levels).all()
    assert np.isnan(ramp[0]) and np.isfinite(ramp[1])  # the second has contrast, but no single crossing


def test_rising_crossing_interpolates_between_the_samples_around_the_level():
    off = np.array([[0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 3.0], [0.0, 1.0, 2.0, 3.0]])
    prof = np.array([[0.0, 10.0, 30.0, 40.0], [40.0, 30.0, 10.0, 0.0], [0.0, 30.0, 0.0, 30.0]])
    found = edge_profile.rising_crossing(prof, off, np.array([25.0, 25.0, 15.0]), np.array([True, True, True]))
    assert found[0] == 1.75  # 25 is three quarters of the way from 10 to 30
    assert np.isnan(found[1]) and np.isnan(found[2])  # falling; rising twice
    unusable = edge_profile.rising_crossing(prof[:1], off[:1], np.array([25.0]), np.array([False]))
    assert np.isnan(unusable[0])


def _levels(dark=40.0, light=200.0, reach=2.0, uneven=0.0, se=0.0):
    """(4, 7) levels of four alike edges: dark, light, reach, unevenness and their standard errors."""
    return np.tile([dark, light, reach, uneven, se, se, se], (4, 1)).astype(float)


def test_a_light_level_short_of_the_paper_pulls_its_edge_by_reach_times_shortfall_over_contrast():
    levels = _levels()
    levels[2, 1] = 180.0  # edge 2's quiet zone reads 20 below the paper (the brightest light level)
    expected = np.array([0.0, 0.0, 2.0 * 20.0 / 160.0, 0.0])
    np.testing.assert_allclose(edge_profile.contamination_px(levels), expected, atol=1e-12)
    levels[2, 5] = 5.0  # its standard error: a shortfall of 20 is 20 - 2 x hypot(5, 0) beyond the noise
    np.testing.assert_allclose(edge_profile.contamination_px(levels)[2], 2.0 * 10.0 / 160.0, atol=1e-12)


def test_a_dark_level_above_the_ink_or_an_unsettled_profile_pulls_by_the_larger():
    levels = _levels()
    levels[0, 0] = 56.0  # edge 0's border reads 16 above the ink
    levels[0, 3] = 8.0  # and its profile still changes by 8 near an end: the larger of the two counts
    levels[1, 3] = -24.0  # edge 1 only unsettled, either sign
    out = edge_profile.contamination_px(levels)
    np.testing.assert_allclose(out, [2.0 * 16.0 / 160.0, 2.0 * 24.0 / 160.0, 0.0, 0.0], atol=1e-12)
    # Several markers at once give each marker's own answer.
    both = edge_profile.contamination_px(np.stack([levels, _levels()]))
    np.testing.assert_allclose(both, [out, np.zeros(4)], atol=1e-12)
