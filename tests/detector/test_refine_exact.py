"""The corner refit's cheaper forms compute what the plain ones did (detector/refine.py): the lens model
evaluated in numpy against cv2.projectPoints, the batched line fits against one at a time."""

from __future__ import annotations

import cv2
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.detector import lens, refine

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
