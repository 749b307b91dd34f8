"""Sub-pixel corner refinement by edge fitting (for OpenCV's ArUco corners, which sit inside the true
ones by a few tenths of a pixel).

Each side of the quadrilateral is sampled at points away from the corners; at each point the image is
sampled along the side's normal, the edge is placed at the sub-pixel maximum of the intensity gradient
(a parabola through the peak and its neighbours), a line is fitted through these edge points by least
squares, and the refined corners are the intersections of adjacent lines. The AprilTag library refines
its corners the same way.
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray

SAMPLES_PER_SIDE = 12
HALF_WIDTH_PX = 3.0  # search this far on each side of the current edge
STEP_PX = 0.25


def refine_corners(gray: NDArray[np.uint8], corners: NDArray[np.float64]) -> NDArray[np.float64]:
    """Corners (4, 2), pixel-centre convention, refined on ``gray``; unchanged where a fit fails."""
    img = gray.astype(np.float32)
    lines = []
    center = corners.mean(axis=0)
    offsets = np.arange(-HALF_WIDTH_PX, HALF_WIDTH_PX + 1e-9, STEP_PX)
    for i in range(4):
        a, b = corners[i], corners[(i + 1) % 4]
        d = b - a
        length = float(np.linalg.norm(d))
        if length < 8:
            return corners
        u = d / length
        n = np.array([-u[1], u[0]])
        if n @ (center - a) > 0:  # normal pointing out of the marker
            n = -n
        ts = np.linspace(0.15, 0.85, SAMPLES_PER_SIDE)
        base = a[None, :] + ts[:, None] * d[None, :]
        pts = base[:, None, :] + offsets[None, :, None] * n[None, None, :]
        xs = pts[..., 0].astype(np.float32)
        ys = pts[..., 1].astype(np.float32)
        prof = cv2.remap(img, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        # Dark (the black border) to bright (the quiet zone) outwards: the signed gradient, so that the
        # edge of a white data cell inside the border (the other polarity) is never taken for it.
        grad = np.maximum(np.diff(prof, axis=1), 0.0)  # between consecutive samples along the normal
        k = np.argmax(grad, axis=1)
        ok = (k > 0) & (k < grad.shape[1] - 1)
        edge = []
        for row in np.flatnonzero(ok):
            g0, g1, g2 = grad[row, k[row] - 1], grad[row, k[row]], grad[row, k[row] + 1]
            denom = g0 - 2 * g1 + g2
            frac = 0.5 * (g0 - g2) / denom if denom < 0 else 0.0
            off = offsets[0] + (k[row] + 0.5 + frac) * STEP_PX
            edge.append(base[row] + off * n)
        if len(edge) < 4:
            return corners
        e = np.array(edge)
        mean = e.mean(axis=0)
        _, _, vt = np.linalg.svd(e - mean)
        lines.append((mean, vt[0]))
    out = np.empty_like(corners)
    for i in range(4):
        (p1, d1), (p2, d2) = lines[(i - 1) % 4], lines[i]
        A = np.array([d1, -d2]).T
        if abs(np.linalg.det(A)) < 1e-9:
            return corners
        s, _ = np.linalg.solve(A, p2 - p1)
        out[i] = p1 + s * d1
    if np.abs(out - corners).max() > 2.0:  # a fit that moves a corner this far is wrong: keep OpenCV's
        return corners
    return out
