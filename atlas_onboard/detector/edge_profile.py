"""Where a marker's edge lies on profiles sampled across it, and what its levels say of blur.

A profile runs from the marker's black border (inside) to its white quiet zone (outside). The edge is the
step whose area matches the profile's between its two levels (pixels integrate the image, so the area is
kept by them and by any symmetric blur); the levels tell how far blur or a neighbouring edge may have
pulled it (:func:`contamination_px`). Used by :mod:`atlas_onboard.detector.refine`.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

MIN_CONTRAST = 20.0  # grey levels between a profile's ends for an edge to be placed on it
AREA_HALF_WIDTH_PX = 2.0  # the area fit's window each side of the edge: at least this, or the ramp (px)
LEVEL_SE = 2.0  # a level's shortfall counts beyond this many of its standard errors


def contamination_px(edge_levels: NDArray[np.float64]) -> NDArray[np.float64]:
    """How far (px) each edge may sit off the true one because its levels were not the marker's ink and
    paper: ``edge_levels`` (4, 7), each edge's dark and light levels, its window's half width R, how
    unevenly its profile settles over the last half pixel to the window's two ends, and the standard
    errors of the two levels and of that.

    Where blur (or a quiet zone narrower than the blur) reaches the background beyond the white quiet zone
    or the data cells inside the black border, the level read there falls short of the paper (or rises
    above the ink) by some delta, and the area fit then moves the edge by up to R delta / contrast (the
    profile inside the window is pulled alike, which takes back part of it). The marker's paper and ink
    are its brightest light and darkest dark level over the four edges, so a sharp, evenly lit marker
    gets nothing. One cause for all four edges (the blur, the quiet zone's width): the quadrilateral
    too small, fully correlated (:func:`refine._corner_covariance`).
    """
    levels = np.nan_to_num(np.asarray(edge_levels, dtype=float))  # (..., 4, 7): several markers' at once
    dark, light, reach, uneven, dark_se, light_se, uneven_se = np.moveaxis(levels, -1, 0)
    i_ink, i_paper = np.argmin(dark, axis=-1)[..., None], np.argmax(light, axis=-1)[..., None]
    ink, ink_se = np.take_along_axis(dark, i_ink, -1), np.take_along_axis(dark_se, i_ink, -1)
    paper, paper_se = np.take_along_axis(light, i_paper, -1), np.take_along_axis(light_se, i_paper, -1)
    contrast = np.maximum(paper - ink, MIN_CONTRAST)
    # A shortfall within LEVEL_SE of its standard error (the levels' own noise) is no evidence of one.
    short = np.maximum(paper - light - LEVEL_SE * np.hypot(light_se, paper_se), 0.0)
    excess = np.maximum(dark - ink - LEVEL_SE * np.hypot(dark_se, ink_se), 0.0)
    # Levels read where the profile has not settled, unevenly at the two ends (a neighbour's edge within
    # reach: every edge alike when the cells are too small for the ramp, which comparing edges cannot show).
    unsettled = np.maximum(np.abs(uneven) - LEVEL_SE * uneven_se, 0.0)
    return reach * np.maximum(short + excess, unsettled) / contrast


def place_edges(
    prof: NDArray[np.float32], offsets: NDArray[np.float64], counts: NDArray[np.int64], cell_px: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Where each profile (rows: dark marker border inside, light quiet zone outside) has its edge, as an
    offset; NaN where it has too little contrast or no single crossing of its half level. Each profile's
    ramp width (px, NaN without contrast): how far blur spreads the edge. And each profile's levels (rows,
    5): dark, light, the half width of the window they were read at, and how much the profile still changes
    over the last half pixel to each end, dark and light (NaN where no edge was placed).

    ``offsets`` (rows, L): each row's samples' offsets, evenly spaced; ``counts`` (rows,): each row's
    samples, the rest of a shorter row being its last sample repeated (which adds no crossing and no
    slope); ``cell_px`` (rows,): the marker's cell across the edge.

    A first pass places the edge roughly where the profile crosses halfway between its ends. The edge is
    then the place of the step that has the profile's area between its levels, read at both ends of a
    window about that crossing: the ramp's width or AREA_HALF_WIDTH_PX each way, at most half a cell (the
    black border and the white quiet zone are a cell wide, so the levels are read as far as can be from
    the data cells inside and the background outside). Pixels integrate the image over their area, and
    the area under a step seen through them and through any symmetric blur is the step's: the crossing
    of linearly interpolated pixels is not (it misses a sharp edge by up to a tenth of a pixel, by where
    the edge falls between pixel centres, alike all along an edge that lies along a pixel axis).
    """
    rows = np.arange(len(prof))
    lo = (prof[:, 0] + prof[:, 1]) / 2  # each end the mean of its two samples (float32, as np.mean)
    hi = (prof[rows, counts - 2] + prof[rows, counts - 1]) / 2
    # The ramp's width (px): the contrast over the steepest slope; about a pixel for a sharp edge, more with blur.
    step = offsets[:, 1] - offsets[:, 0]
    slope = (prof[:, 1:] - prof[:, :-1]).max(axis=1) / step
    contrast = hi - lo >= MIN_CONTRAST
    ramp = np.where((slope > 0) & contrast, (hi - lo) / np.maximum(slope, 1e-9), np.nan)
    found = rising_crossing(prof, offsets, (lo + hi) / 2.0, contrast)
    # Second pass: the edge as the step whose area matches the profile's between its levels, over a window
    # about the first crossing (at most half a cell each way, in the black border and the white quiet zone).
    ok = np.isfinite(found)
    reach = np.minimum(0.5 * cell_px, np.maximum(AREA_HALF_WIDTH_PX, np.nan_to_num(ramp)))
    index = (np.where(ok, found, 0.0)[:, None] + reach[:, None] * np.array([-1.0, 1.0]) - offsets[:, :1]) / step[
        :, None
    ]
    index = np.clip(index, 0.0, (counts - 1)[:, None].astype(float))
    # The profile is linear between its samples: its integral from sample 0 to any fractional index.
    cumulative = np.zeros(prof.shape)
    np.cumsum((prof[:, 1:] + prof[:, :-1]) / 2.0, axis=1, out=cumulative[:, 1:])
    j = np.minimum(index.astype(int), (counts - 2)[:, None])  # (rows, 2): the sample before each window end
    frac = index - j
    p0, p1 = prof[rows[:, None], j], prof[rows[:, None], j + 1]
    ends = p0 + frac * (p1 - p0)  # the profile at the window's ends: dark, light
    integral = cumulative[rows[:, None], j] + frac * (p0 + ends) / 2.0  # in samples
    dark, light = ends[:, 0], ends[:, 1]
    # How much the profile still changes over the last half pixel to each end: 0 on the plateaus of ink and
    # paper, not where the window is too narrow for the ramp or a neighbour's edge reaches into it.
    inner = np.clip(index + np.array([0.5, -0.5]) / step[:, None], 0.0, (counts - 1)[:, None].astype(float))
    k = np.minimum(inner.astype(int), (counts - 2)[:, None])
    q0, q1 = prof[rows[:, None], k], prof[rows[:, None], k + 1]
    unsettled = ends - (q0 + (inner - k) * (q1 - q0))  # (rows, 2), signed
    usable = ok & (light - dark >= MIN_CONTRAST)
    width = (index[:, 1] - index[:, 0]) * step
    area = ((integral[:, 1] - integral[:, 0]) * step - dark * width) / np.where(usable, light - dark, 1.0)
    edge = offsets[:, 0] + index[:, 1] * step - area
    levels = np.where(usable[:, None], np.column_stack([dark, light, reach, unsettled]), np.nan)
    return np.where(usable, edge, np.nan), ramp, levels


def rising_crossing(
    prof: NDArray[np.float32],
    offsets: NDArray[np.float64],
    level: NDArray[np.float64],
    usable: NDArray[np.bool_],
) -> NDArray[np.float64]:
    """Each profile's offset where it rises through ``level`` (linear between samples); NaN where it is
    not ``usable`` or does not rise through it exactly once."""
    above = prof > level[:, None]
    cross = ~above[:, :-1] & above[:, 1:]
    single = np.flatnonzero(usable & (np.count_nonzero(cross, axis=1) == 1))
    j = np.argmax(cross[single], axis=1)
    a, b = prof[single, j], prof[single, j + 1]  # a <= level < b
    off, off_next = offsets[single, j], offsets[single, j + 1]
    found = np.full(len(prof), np.nan)
    found[single] = off + (level[single] - a) / (b - a) * (off_next - off)
    return found
