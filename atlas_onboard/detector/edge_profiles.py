"""The image along the corner refit's sample rows (:mod:`atlas_onboard.detector.edge_sampling`), for all
markers of a frame in one pass: every sample point through the lens at once, one crop of the image around
the points it reads, one bilinear remap."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from atlas_onboard.detector.edge_sampling import STEP_PX, Sampling
from atlas_onboard.detector.lens import distort_columns


@dataclass(frozen=True)
class Profiles:
    """The image sampled along every row of a frame's :class:`Sampling`: ``values`` (R, width) float32, and
    each sampled marker's undistorted pixels per image pixel about it, ``scales`` (M,) (the lens residual is
    in image pixels)."""

    values: NDArray[np.float32]
    scales: NDArray[np.float64]


def image_points(
    plan: Sampling, rows: slice, K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Where the sample points of ``plan``'s ``rows`` (each row's base plus its offsets along the normal)
    fall in the image, x and y (rows, width)."""
    offsets, normals, bases = plan.offsets[rows], plan.normals[rows], plan.bases[rows]
    u = offsets * normals[:, 0, None]
    u += bases[:, 0, None]
    v = offsets * normals[:, 1, None]
    v += bases[:, 1, None]
    x, y = distort_columns(u.ravel(), v.ravel(), K, dist, fisheye)
    return x.reshape(u.shape), y.reshape(v.shape)


def profiles(
    gray: NDArray[np.uint8], plan: Sampling, K: NDArray[np.float64], dist: NDArray[np.float64], fisheye: bool
) -> Profiles:
    """The image (bilinear, the border replicated) at every sample point of ``plan``, and each marker's scale.

    Marker by marker: its points through the lens, the crop of the image they read (:func:`crop`), sampled
    there. Each step is elementwise or a marker's own, so the values are those of the whole frame's points
    at once; arrays of one marker's points stay in the core's cache (the whole frame's, some 45,000 points
    with ten markers, are each fresh memory pages, which cost as much as the arithmetic)."""
    values = np.empty(plan.offsets.shape, np.float32)
    scales = np.empty(len(plan.markers))
    for k, (a, n) in enumerate(zip(plan.starts, plan.samples, strict=True)):
        rows = slice(a, a + 4 * n)
        x, y = image_points(plan, rows, K, dist, fisheye)
        img, (cx, cy) = crop(gray, x, y)
        mx, my = (x - cx).astype(np.float32), (y - cy).astype(np.float32)
        values[rows] = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        dx, dy = mx[:, 1] - mx[:, 0], my[:, 1] - my[:, 0]
        scales[k] = float(np.mean(STEP_PX / np.maximum(np.sqrt(dx * dx + dy * dy), 1e-9)))  # np.linalg.norm's
    return Profiles(values, scales)


def crop(
    gray: NDArray[np.uint8], x: NDArray[np.float64], y: NDArray[np.float64]
) -> tuple[NDArray[np.float32], tuple[float, float]]:
    """The part of ``gray`` that bilinear sampling at the points ``x``, ``y`` reads, as float32, and its
    top-left corner (x, y): sampling it at the points less the corner gives what sampling the whole image
    gives (a sample beyond the crop's edge is beyond the image's there, where both replicate the border)."""
    h, w = gray.shape[:2]
    # In python floats: a NaN bound counts as 0, an infinite one is clipped to the image.
    lo = [float(x.min()), float(y.min())]
    hi = [float(x.max()), float(y.max())]
    lo, hi = ([0.0 if math.isnan(v) else min(max(v, -8.0), 8.0 + max(w, h)) for v in b] for b in (lo, hi))
    x0, y0 = min(max(math.floor(lo[0]) - 2, 0), w - 1), min(max(math.floor(lo[1]) - 2, 0), h - 1)
    x1, y1 = min(max(math.ceil(hi[0]) + 3, x0 + 1), w), min(max(math.ceil(hi[1]) + 3, y0 + 1), h)
    return gray[y0:y1, x0:x1].astype(np.float32), (float(x0), float(y0))
