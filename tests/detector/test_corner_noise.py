"""The corner noise of a frame's markers computed stacked (detector/corner_noise.py) against the per-side,
per-marker forms it replaces: the sides' statistics against refine's loop over the sides, the corner
covariances of many markers against each one's."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from atlas_onboard.detector import corner_noise, refine


def _sides(rng: np.random.Generator, m: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(m, 4, n, 2) edge points scattered about the sides of squares, and (m, 4, n, 5) levels."""
    corners = np.array([[0.0, 0.0], [60.0, 2.0], [58.0, 61.0], [-1.0, 59.0]]) + rng.normal(0, 3, (m, 4, 2))
    t = np.linspace(0.15, 0.85, n)
    a, b = corners, corners[:, [1, 2, 3, 0]]
    points = a[:, :, None] + t[None, None, :, None] * (b - a)[:, :, None] + rng.normal(0, 0.2, (m, 4, n, 2))
    levels = np.column_stack([rng.uniform(20, 60, m * 4 * n), rng.uniform(150, 230, m * 4 * n)])
    extra = rng.normal(0, 2, (m * 4 * n, 3)) * [0.1, 1, 1] + [2.0, 0, 0]
    return points, np.concatenate([levels, extra], axis=1).reshape(m, 4, n, 5)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), m=st.integers(1, 5), n=st.integers(12, 24))
def test_stacked_side_statistics_equal_each_sides_own(seed: int, m: int, n: int):
    points, levels = _sides(np.random.default_rng(seed), m, n)
    stacked = corner_noise.side_statistics(points, levels)
    keep = np.ones((4, n), bool)
    for k in range(m):
        each = refine._side_statistics_each(list(points[k]), levels[k], keep)
        for got, want in zip((x[k] for x in stacked), each, strict=True):
            want = np.asarray(want, float)
            # a line's direction may come out either way round (both the same line)
            if np.shape(want) == (4, 2) and not np.allclose(got, want, atol=1e-9):
                got = got * np.sign((got * want).sum(axis=1, keepdims=True))
            np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12 * max(np.abs(want).max(), 1.0))


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), m=st.integers(1, 5), shrink=st.booleans())
def test_corner_covariances_of_many_equal_each_ones(seed: int, m: int, shrink: bool):
    rng = np.random.default_rng(seed)
    points, _ = _sides(rng, m, 16)
    means = points.mean(axis=2)
    dirs = points[:, :, -1] - points[:, :, 0]
    dirs /= np.linalg.norm(dirs, axis=2, keepdims=True)
    corners = points[:, :, 0]
    var, npts, spread = rng.uniform(0.01, 0.1, m), np.full((m, 4), 16.0), rng.uniform(100, 900, (m, 4))
    shrinks, shift = rng.uniform(0, 0.3, (m, 4)), rng.uniform(0, 0.2, m)
    many = corner_noise.corner_covariances(means, dirs, corners, var, npts, spread, shrinks if shrink else None, shift)
    for k in range(m):
        lines = [(means[k, i], dirs[k, i]) for i in range(4)]
        one = refine._corner_covariance(
            lines, corners[k], var[k], npts[k], spread[k], shrinks[k] if shrink else None, shift[k]
        )
        np.testing.assert_allclose(many[k], one, rtol=0, atol=1e-12 * np.abs(one).max())
