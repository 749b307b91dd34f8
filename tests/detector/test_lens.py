"""The lens model on coordinate arrays (lens.distort_uv, and lens.distort_columns, which the corner refit of a
frame's markers uses), against the homogeneous form it replaces there."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.detector import lens

K = np.array([[457.0, 0.0, 319.5], [0.0, 459.0, 241.25], [0.0, 0.0, 1.0]])
coefficient = st.floats(-0.3, 0.3, allow_nan=False)


@settings(max_examples=150, deadline=None)
@given(
    size=st.sampled_from([4, 5, 8, 12, 14]),
    coeffs=st.lists(coefficient, min_size=14, max_size=14),
    zero=st.lists(st.booleans(), min_size=14, max_size=14),
    fisheye=st.booleans(),
    seed=st.integers(0, 2**31),
)
def test_distort_uv_gives_distort_homogeneous_value(
    size: int, coeffs: list[float], zero: list[bool], fisheye: bool, seed: int
):
    """Any coefficient count (the ones it does not evaluate itself go through the homogeneous form), the
    fisheye model too: the same image pixels, bit for bit."""
    size = 4 if fisheye else size
    dist = np.where(zero, 0.0, coeffs)[:size] * np.array([1, 1, 0.01, 0.01] + [0.3] * 10)[:size]
    pts = np.random.default_rng(seed).uniform(-40, 680, (300, 2))
    want = lens.distort_homogeneous(np.column_stack([pts, np.ones(len(pts))]), K, dist, fisheye)
    got = lens.distort_uv(pts[:, 0].copy(), pts[:, 1].copy(), K, dist, fisheye)
    np.testing.assert_array_equal(got, want)
    x, y = lens.distort_columns(pts[:, 0].copy(), pts[:, 1].copy(), K, dist, fisheye)
    assert x.flags.c_contiguous and y.flags.c_contiguous
    np.testing.assert_array_equal(x, want[:, 0])
    np.testing.assert_array_equal(y, want[:, 1])
