"""Blur pulls a small marker's edges inwards: once an edge's ramp spans more than about half
a cell, the one-cell white quiet zone never reaches its level between the black border and the darker
floor beyond it, so the half-level edges sit inside the true ones and the square looks too small (its
depth too large). The corners' covariance must cover that, measured against rendered truth."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.detector import edge_profile, pose, refine
from atlas_onboard.detector.backends import MarkerFinder
from atlas_onboard.detector.render import Camera, MarkerView, render

W, H = 640, 480
K = np.array([[460.0, 0.0, 319.5], [0.0, 460.0, 239.5], [0.0, 0.0, 1.0]])
CAM = Camera(W, H, K, np.zeros(5))
SIZE = 0.15


def size_errors(blur_px: tuple[float, float], distance_m: float, n: int) -> list[tuple[float, float]]:
    """For ``n`` renders of one marker: how far its four refitted edges sit outside the true ones on
    average (px; negative: inside) and that figure's standard deviation by the corners' covariance."""
    finder = MarkerFinder({7: "tag36h11"}, 1.0)
    rng = np.random.default_rng(5)
    out = []
    for k in range(n):
        rot = Rotation.from_euler("xyz", [180 + rng.uniform(-20, 20), rng.uniform(-20, 20), rng.uniform(0, 90)], True)
        xy = rng.uniform(-0.3, 0.3, 2) * distance_m
        T = RigidTransform.from_components([xy[0], xy[1], distance_m], rot)
        img = render(CAM, [MarkerView("tag36h11", 7, SIZE, T)], noise_sigma=3.0, blur_px=blur_px, seed=k,
                     background_style="concrete", background_seed=k % 5)  # fmt: skip
        found = finder.find(img, 1.0)
        assert len(found) == 1
        M = T.as_matrix()
        P = pose.object_corners(SIZE) @ M[:3, :3].T + M[:3, 3]
        truth = (P @ K.T)[:, :2] / P[:, 2:]
        ref = refine.refine_corners_undistorted(img, found[0].corners_px, K, np.zeros(5))
        assert ref is not None
        # The mean outward offset of the four edges is g . (corner errors), g built from the edges' normals.
        g = np.zeros(8)
        centre = truth.mean(axis=0)
        for i in range(4):
            a, b = truth[i], truth[(i + 1) % 4]
            normal = np.array([a[1] - b[1], b[0] - a[0]]) / np.linalg.norm(b - a)
            if normal @ (centre - a) > 0:
                normal = -normal
            for c in (i, (i + 1) % 4):
                g[2 * c : 2 * c + 2] += normal / 8.0
        d = (ref.corners - truth).ravel()
        out.append((float(g @ d), float(np.sqrt(g @ ref.covariance @ g))))
    return out


def test_a_blurred_small_markers_shrink_is_within_its_covariance():
    # A 15 cm tag at 2.6 m: 26 px across, cells of 3.3 px; a diagonal blur of 3.5 px spreads every edge
    # over about a cell.
    errs = size_errors((2.5, 2.5), 2.6, 8)
    z = np.array([e / s for e, s in errs])
    assert np.mean([e for e, _ in errs]) < -0.05  # the pull is there: the edges sit inside
    assert np.all(np.abs(z) <= 3.0), z
    assert np.mean(z**2) <= 3.0, z


def test_sharp_markers_get_no_shrink():
    """The same markers unblurred: their edges are unbiased and the term adds nothing."""
    # Four edges that read the same ink and paper and settle evenly at both ends, within their noise (a sharp,
    # evenly lit marker): dark, light, window half width, unevenness, and the standard errors of the three.
    levels = np.array(
        [
            [20.0, 220.0, 2.0, 0.3, 0.5, 0.5, 0.4],
            [20.5, 219.5, 2.0, -0.5, 0.5, 0.5, 0.4],
            [19.8, 220.0, 1.9, 0.0, 0.5, 0.5, 0.4],
            [20.2, 219.8, 2.0, 0.6, 0.5, 0.5, 0.4],
        ]
    )
    assert np.all(edge_profile.contamination_px(levels) == 0.0)
    errs = size_errors((0.0, 0.0), 2.6, 4)
    assert all(abs(e) <= 3 * s for e, s in errs)
