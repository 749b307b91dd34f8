"""The corner refit's cheaper forms compute what the plain ones did (detector/refine.py): the lens model
evaluated in numpy against cv2.projectPoints, the half-level search over padded profiles of four sides
at once against each side alone, the batched line fits against one at a time."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.detector import edge_profile, edge_sampling, lens, refine

K = np.array([[457.0, 0.0, 319.5], [0.0, 459.0, 241.25], [0.0, 0.0, 1.0]])


def _cv2_distort(pts: np.ndarray, K: np.ndarray, dist: np.ndarray, fisheye: bool) -> np.ndarray:
    rays = np.column_stack([pts, np.ones(len(pts))]) @ np.linalg.inv(K).T
    project = cv2.fisheye.projectPoints if fisheye else cv2.projectPoints
    return project(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)[0].reshape(-1, 2)


coefficient = st.floats(-0.3, 0.3, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(
    size=st.sampled_from([4, 5, 8, 12, 14]),
    coeffs=st.lists(coefficient, min_size=14, max_size=14),
    zero=st.lists(st.booleans(), min_size=14, max_size=14),
    seed=st.integers(0, 2**31),
)
def test_standard_lens_model_equals_opencv_bit_for_bit(size: int, coeffs: list[float], zero: list[bool], seed: int):
    """Every coefficient count OpenCV takes, with any of them zero (the groups left out), the tilted sensor
    among them: the image pixels are exactly cv2.projectPoints'."""
    dist = np.where(zero, 0.0, coeffs)[:size] * np.array([1, 1, 0.01, 0.01] + [0.3] * 10)[:size]
    pts = np.random.default_rng(seed).uniform(-40, 680, (300, 2))
    assert np.array_equal(lens.distort(pts, K, dist, False), _cv2_distort(pts, K, dist, False))


@settings(max_examples=60, deadline=None)
@given(coeffs=st.lists(st.floats(-0.05, 0.05, allow_nan=False), min_size=4, max_size=4), seed=st.integers(0, 2**31))
def test_fisheye_lens_model_equals_opencv(coeffs: list[float], seed: int):
    """The fisheye model (an arctangent, whose last bit numpy and the C library may round apart)."""
    pts = np.random.default_rng(seed).uniform(-40, 680, (300, 2))
    dist = np.array(coeffs)
    assert np.abs(lens.distort(pts, K, dist, True) - _cv2_distort(pts, K, dist, True)).max() < 1e-9


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


@settings(max_examples=60, deadline=None)
@given(counts=st.lists(st.integers(6, 12), min_size=4, max_size=4), seed=st.integers(0, 2**31))
def test_batched_line_fits_equal_one_at_a_time(counts: list[int], seed: int):
    """Equal point counts go through one batched SVD, unequal ones one by one: the same means, singular
    values and directions as fitting each alone."""
    rng = np.random.default_rng(seed)
    for sizes in (counts, [counts[0]] * 4):
        edges = [rng.normal(0, 0.3, (n, 2)) + rng.uniform(-300, 300, 2) + np.linspace(0, 40, n)[:, None] for n in sizes]
        for e, (mean, sv, vt) in zip(edges, refine._principal_axes(edges), strict=True):
            alone_mean = e.mean(axis=0)
            _, alone_sv, alone_vt = np.linalg.svd(e - alone_mean)
            assert np.array_equal(mean, alone_mean)
            assert np.array_equal(sv, alone_sv) and np.array_equal(vt, alone_vt)
