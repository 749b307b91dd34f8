"""The corners' covariance that four fitted edge lines imply (refine._corner_covariance) against Monte
Carlo of the same fits: correlated corners (adjacent ones share a line), oblique crossings."""

import numpy as np

from atlas_onboard.detector import refine


def fit_corners(edges):
    """Lines through each edge's points (mean, direction by SVD) and their crossings, as refine does."""
    lines = []
    for e in edges:
        mean = e.mean(axis=0)
        _, _, vt = np.linalg.svd(e - mean)
        lines.append((mean, vt[0]))
    out = np.empty((4, 2))
    for i in range(4):
        (p1, d1), (p2, d2) = lines[(i - 1) % 4], lines[i]
        s, _ = np.linalg.solve(np.array([d1, -d2]).T, p2 - p1)
        out[i] = p1 + s * d1
    return lines, out


def test_corner_covariance_matches_monte_carlo_of_the_line_fits():
    corners = np.array([[100.0, 100.0], [160.0, 96.0], [150.0, 140.0], [104.0, 150.0]])  # a skewed quad
    ts = np.linspace(0.15, 0.85, 12)
    sigma = 0.1
    rng = np.random.default_rng(3)
    normals = []
    for i in range(4):
        d = corners[(i + 1) % 4] - corners[i]
        normals.append(np.array([-d[1], d[0]]) / np.linalg.norm(d))
    samples = []
    for _ in range(4000):
        edges = []
        for i in range(4):
            a, b = corners[i], corners[(i + 1) % 4]
            pts = a + ts[:, None] * (b - a)
            edges.append(pts + rng.normal(0.0, sigma, (len(ts), 1)) * normals[i])
        samples.append(fit_corners(edges)[1].ravel() - corners.ravel())
    sampled = np.cov(np.array(samples).T)
    clean = [corners[i] + ts[:, None] * (corners[(i + 1) % 4] - corners[i]) for i in range(4)]
    lines, _ = fit_corners(clean)
    spread = np.array([float(((e - m) @ d) @ ((e - m) @ d)) for e, (m, d) in zip(clean, lines, strict=True)])
    # The noise of the fits alone: no blur pull, no lens residual.
    model = refine._corner_covariance(lines, corners, sigma**2, np.full(4, float(len(ts))), spread, None, 0.0)
    np.testing.assert_allclose(np.diag(model), np.diag(sampled), rtol=0.1)
    corr = lambda C: C / np.sqrt(np.outer(np.diag(C), np.diag(C)))  # noqa: E731
    np.testing.assert_allclose(corr(model), corr(sampled), atol=0.05)
    assert np.abs(corr(model) - np.eye(8)).max() > 0.3  # the corners are correlated, as the fits say
