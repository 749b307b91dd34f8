"""The detector's search for markers in a frame: the regions where the previous frame's markers are predicted
to be, the cells of strong black-white contrast, the tiles of a full-resolution grid (a collaborator of
:class:`atlas_onboard.detector.pipeline.Detector`, whose :meth:`find` drives them)."""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.detector import pose
from atlas_onboard.detector.backends import Detection, MarkerFinder
from atlas_onboard.detector.calibration import Calibration
from atlas_onboard.detector.families import family
from atlas_onboard.detector.follow import follow

SMALL_SIDE_PX = 40.0  # markers smaller than this are re-searched at full resolution
TRACKED_SIDE_PX = 30.0  # a tracked marker's region is decimated while the marker stays this wide in it (the hunt's)
ROI_MARGIN = 0.4  # a region is the marker's predicted box grown by this fraction of its size on each side
MAX_REGION_DECIMATE = 3.0  # the hunt's decimation and the largest of a tracked marker's region
TILES = (3, 3)  # the grid of full-resolution tiles searched one a frame (columns, rows)
CELL_PX = 8  # contrast is measured in cells of this many pixels
MIN_RATIO = 0.6  # a candidate cell's contrast is at least this share of its brightest pixel (ink on paper)
TILE_OVERLAP_PX = 1.5 * SMALL_SIDE_PX  # adjacent tiles share this much: a small marker and its quiet zone
BORDER_MARGIN_PX = 6.0  # corners closer than this to an image or region border: the edge fit's reach, and 3 px
MIN_CONTRAST = 20  # grey levels: a cell with less is not a marker's black and white (edge_profile.MIN_CONTRAST)
PRINT_EDGE_PX = 2.0  # a print's edge in the image: blur and the corners' own error
QUIET_FRAMES = 4  # a candidate region in which nothing was found is not searched again for this many frames
FOREIGN_FRAMES = 15  # a tag that is not ours is not searched again for this many frames (then checked again)


@dataclass(frozen=True)
class ForeignTag:
    """Where a tag that is not configured was decoded (its corners (4, 2), predicted to the current
    frame) and the frame from which its place is searched again."""

    corners_px: NDArray[np.float64]
    until: int


class RegionSearch:
    """The region searches of :class:`~atlas_onboard.detector.pipeline.Detector`: it owns the regions to
    search in the next frame and the next tile of the grid, and searches with the detector's finder
    (counting into the detector's counters)."""

    def __init__(self, calibration: Calibration, finder: MarkerFinder, counters: Counter[str], tile: int) -> None:
        self.calibration = calibration
        self.finder = finder
        self.counters = counters
        self.predicted: dict[int, NDArray[np.float64]] = {}  # the tracked markers' corners predicted in the next frame
        self._tile = tile  # the next tile of the grid (in a phase of its own for each sensor)
        self.foreign: list[ForeignTag] = []  # tags not ours found lately: their places are not candidates
        self._foreign_now: list[NDArray[np.float64]] = []  # corners of those decoded in this frame
        self._quiet_until = np.zeros((0, 0), np.int64)  # per cell: the frame until which it is not a candidate
        self._quiet_level = np.zeros((0, 0), np.uint8)  # per cell: its contrast when last searched in vain

    def scan(self, gray: NDArray[np.uint8], decimate: float) -> list[Detection]:
        """The whole image searched at ``decimate``: our markers (the tags not ours noted)."""
        ours = self.finder.find(gray, decimate)
        self.saw_foreign(self.finder.foreign)
        return ours

    def saw_foreign(self, found: list[Detection], offset: tuple[int, int] = (0, 0)) -> None:
        """Note the tags not ours of a search (``found``: corners in a region whose top-left is ``offset``)."""
        self._foreign_now += [d.corners_px + np.array(offset, dtype=float) for d in found]

    def foreign_boxes(self, frame: int, R_prev_now: Rotation | None) -> list[NDArray[np.float64]]:
        """The boxes (x0, y0, x1, y1) about the tags not ours whose contrast is not searched in ``frame``
        (:func:`contrast_regions`' ``explained``): each moved by the camera's turn ``R_prev_now`` (if
        given) and grown as a tracked marker's region is; those due a check again are forgotten (their
        place is a candidate again)."""
        kept = [t for t in self.foreign if t.until > frame]
        if kept and R_prev_now is not None:
            turned = self.rotated(np.array([t.corners_px for t in kept]), R_prev_now)
            kept = [ForeignTag(c, t.until) for c, t in zip(turned, kept, strict=True)]
        self.foreign = kept
        return list(grown_boxes(np.array([t.corners_px for t in kept]))) if kept else []

    def explained(self, frame: int, R_prev_now: Rotation | None, found: list[Detection]) -> list[NDArray[np.float64]]:
        """The boxes (x0, y0, x1, y1) of contrast explained already in ``frame``: the tags not ours searched
        lately (:meth:`foreign_boxes`) and the prints of the markers ``found`` (:func:`printed_boxes`)."""
        return self.foreign_boxes(frame, R_prev_now) + printed_boxes(found)

    def remember_foreign(self, frame: int) -> None:
        """Remember the tags not ours decoded in ``frame`` until ``FOREIGN_FRAMES`` later (each replaces
        what was remembered where it is)."""
        for c in self._foreign_now:
            lo, hi = c.min(axis=0), c.max(axis=0)
            self.foreign = [t for t in self.foreign if not np.all((t.corners_px.mean(axis=0) >= lo)
                                                                  & (t.corners_px.mean(axis=0) <= hi))]  # fmt: skip
            self.foreign.append(ForeignTag(c, frame + FOREIGN_FRAMES))
        self._foreign_now = []

    def rotated(self, corners_px: NDArray[np.float64], R_prev_now: Rotation) -> NDArray[np.float64]:
        """Where corners (..., N, 2) of the previous image are seen now after the camera turned by
        ``R_prev_now`` (far points: a turn moves them alike whatever their depth), every set of N at once;
        a set turned out of view (a corner behind the camera) stays where it was: nothing to predict from."""
        cal = self.calibration
        flat = corners_px.reshape(-1, 2)
        ideal = pose.undistort(flat, cal.K, cal.dist, cal.fisheye)
        rays_prev = np.column_stack([ideal, np.ones(len(ideal))]) @ np.linalg.inv(cal.K).T
        rays_now = R_prev_now.inv().apply(rays_prev)
        behind = np.any((rays_now[:, 2] <= 1e-3).reshape(corners_px.shape[:-1]), axis=-1)
        pts = rays_now.reshape(-1, 1, 3)
        zero = np.zeros(3)
        if cal.fisheye:
            out, _ = cv2.fisheye.projectPoints(pts, zero, zero, cal.K, cal.dist)
        else:
            out, _ = cv2.projectPoints(pts, zero, zero, cal.K, cal.dist)
        out = out.reshape(corners_px.shape)
        out[behind] = corners_px[behind]
        return out

    def track(self, gray: NDArray[np.uint8], found: dict[int, Detection]) -> None:
        """The tracked markers: each followed from its predicted corners (:func:`follow.follow`), and
        the library's search of the regions (:func:`box`) of those not followed."""
        wanted = self.finder.wanted
        followed = follow(gray, {i: (wanted[i], c) for i, c in self.predicted.items() if i in wanted}, self.calibration)
        found.update(followed)
        self.counters["followed"] += len(followed)
        rest = [box(c) for i, c in self.predicted.items() if i not in followed]
        self.find_in(gray, rest, found)

    def candidates(
        self, gray: NDArray[np.uint8], frame: int, R_prev_now: Rotation | None, found: dict[int, Detection], area: float
    ) -> None:
        """The regions of strong contrast in ``frame`` outside the markers ``found`` and the contrast
        explained already (:meth:`explained`), at most ``area`` pixels (:func:`contrast_regions`), each
        searched for new markers. Texture searched in vain is not searched again for ``QUIET_FRAMES``
        unless its contrast rose (a marker came in)."""
        h, w = gray.shape[:2]
        cells = (-(-h // CELL_PX), -(-w // CELL_PX))
        if self._quiet_until.shape != cells:
            self._quiet_until = np.zeros(cells, np.int64)
            self._quiet_level = np.zeros(cells, np.uint8)
        contrast, top = cell_contrast(gray)
        quiet = (self._quiet_until > frame) & (contrast <= self._quiet_level.astype(np.int16) + MIN_CONTRAST)
        taken = [np.concatenate([d.corners_px.min(axis=0), d.corners_px.max(axis=0)]) for d in found.values()]
        explained = self.explained(frame, R_prev_now, list(found.values()))
        for region in contrast_regions(contrast, top, taken, area, quiet, explained):
            before = len(found)
            self.find_in(gray, [region], found, only_new=True)
            self.counters["candidate_regions"] += 1
            if len(found) == before:
                x0, y0, x1, y1 = (max(int(v), 0) // CELL_PX for v in region[:4])
                self._quiet_until[y0 : y1 + 1, x0 : x1 + 1] = frame + QUIET_FRAMES
                self._quiet_level[y0 : y1 + 1, x0 : x1 + 1] = contrast[y0 : y1 + 1, x0 : x1 + 1]

    def next_tile(self, w: int, h: int) -> NDArray[np.float64]:
        """The next tile of the grid, grown so that every small marker (the decimated search finds
        the others) lies wholly inside one tile."""
        cols, rows = TILES
        k = self._tile % (cols * rows)
        self._tile += 1
        tx, ty = k % cols, k // cols
        m = TILE_OVERLAP_PX / 2
        return np.array(
            [tx * w // cols - m, ty * h // rows - m, (tx + 1) * w // cols + m, (ty + 1) * h // rows + m], float
        )

    def checked(
        self, found: list[Detection], shape: tuple[int, ...], region: tuple[int, int, int, int]
    ) -> list[Detection]:
        """``found`` in a ``region`` (x0, y0, x1, y1) of the image without the detections whose corners
        touch a border of the region inside the image: the marker may be cut there (counted; it is found
        again when the whole image is searched)."""
        h, w = shape[:2]
        x0, y0, x1, y1 = region
        m = BORDER_MARGIN_PX
        out = []
        for d in found:
            lo, hi = d.corners_px.min(axis=0), d.corners_px.max(axis=0)
            if (
                (x0 > 0 and lo[0] < x0 + m)
                or (y0 > 0 and lo[1] < y0 + m)
                or (x1 < w and hi[0] > x1 - 1 - m)
                or (y1 < h and hi[1] > y1 - 1 - m)
            ):
                self.counters["dropped_region_border"] += 1
                continue
            out.append(d)
        return out

    def find_in(
        self,
        gray: NDArray[np.uint8],
        boxes: list[NDArray[np.float64]],
        found: dict[int, Detection],
        only_new: bool = False,
    ) -> None:
        """Search each region (boxes (x0, y0, x1, y1[, decimate]), merged where they overlap)."""
        h, w = gray.shape[:2]
        for x0, y0, x1, y1, decimate in _merge(boxes, w, h):
            shifted = []
            ours = self.finder.find(np.ascontiguousarray(gray[y0:y1, x0:x1]), decimate)
            self.saw_foreign(self.finder.foreign, (x0, y0))
            for d in ours:
                if only_new and d.marker_id in found:
                    continue
                c = d.corners_px + np.array([x0, y0], dtype=float)
                shifted.append(Detection(d.marker_id, d.family, c, d.decision_margin))
            for d in self.checked(shifted, gray.shape, (x0, y0, x1, y1)):
                found[d.marker_id] = d
                self.counters["roi_finds"] += 1


def at_border(c: NDArray[np.float64], w: int, h: int) -> bool:
    """Whether any corner (c: (4, 2) pixels) lies within ``BORDER_MARGIN_PX`` of the image's border or outside."""
    lo, hi = c.min(axis=0), c.max(axis=0)
    m = BORDER_MARGIN_PX
    return bool(lo[0] < m or lo[1] < m or hi[0] > w - 1 - m or hi[1] > h - 1 - m)


def side(c: NDArray[np.float64]) -> float:
    return float(np.mean(np.linalg.norm(c - np.roll(c, 1, axis=0), axis=1)))


def box(c: NDArray[np.float64]) -> NDArray[np.float64]:
    """The region (x0, y0, x1, y1, decimate) to search for a marker with corners ``c`` in the next
    frame: its box grown by ``ROI_MARGIN``, decimated while the marker stays ``TRACKED_SIDE_PX`` wide
    (at most ``MAX_REGION_DECIMATE``, at which the hunt finds it). The library fits the quad's edges
    at full resolution whatever the decimation, and the corner refit places them again on the image."""
    decimate = float(min(max(math.floor(side(c) / TRACKED_SIDE_PX), 1), MAX_REGION_DECIMATE))
    return np.concatenate([grown_boxes(c[None])[0], [decimate]])


def grown_boxes(corners: NDArray[np.float64]) -> NDArray[np.float64]:
    """The boxes (M, 4: x0, y0, x1, y1) of :func:`box` (without its decimation) of markers with corners
    ``corners`` (M, 4, 2)."""
    lo, hi = corners.min(axis=1), corners.max(axis=1)
    grow = (hi - lo) * ROI_MARGIN + 8
    return np.concatenate([lo - grow, hi + grow], axis=1)


def printed_boxes(found: list[Detection]) -> list[NDArray[np.float64]]:
    """The box (x0, y0, x1, y1) of each found marker's whole print: its detected square grown by the
    pattern outside it and the white quiet zone (``Family.printed_cells``), at the scale of its longest
    side in the image, and ``PRINT_EDGE_PX``. The black-white edge of the print's border (ink, then
    paper on whatever it lies on) is strong contrast that no other marker can own."""
    if not found:
        return []
    c = np.array([d.corners_px for d in found])
    fams = [family(d.family) for d in found]
    outside = np.array([f.printed_cells - f.cells for f in fams], float)
    cells = np.array([2 * f.cells for f in fams], float)
    longest = np.linalg.norm(c - np.roll(c, 1, axis=1), axis=2).max(axis=1)
    grow = (longest * outside / cells + PRINT_EDGE_PX)[:, None]
    return list(np.concatenate([c.min(axis=1) - grow, c.max(axis=1) + grow], axis=1))


def cell_contrast(gray: NDArray[np.uint8]) -> tuple[NDArray[np.uint8], NDArray[np.uint8]]:
    """Each ``CELL_PX`` cell's contrast (brightest minus darkest pixel) and brightest pixel, after a 2x2
    average (so that one noisy pixel does not count); each of shape (ceil(h / CELL_PX), ceil(w / CELL_PX))."""
    h, w = gray.shape[:2]
    cell = CELL_PX // 2
    small = cv2.resize(gray, (-(-w // 2), -(-h // 2)), interpolation=cv2.INTER_AREA)
    kernel = np.ones((cell, cell), np.uint8)
    top = cv2.dilate(small, kernel, anchor=(0, 0))[::cell, ::cell]
    bottom = cv2.erode(small, kernel, anchor=(0, 0))[::cell, ::cell]
    return cv2.subtract(top, bottom), top


def contrast_regions(
    contrast: NDArray[np.uint8],
    top: NDArray[np.uint8],
    taken: list[NDArray[np.float64]],
    budget_px: float,
    quiet: NDArray[np.bool_] | None = None,
    explained: list[NDArray[np.float64]] | None = None,
) -> list[NDArray[np.float64]]:
    """Regions (x0, y0, x1, y1, decimate) of the strongest black-white contrast outside the boxes
    ``taken`` (x0, y0, x1, y1: the markers found already) and the ``quiet`` cells, the strongest first,
    at most ``budget_px`` pixels (divided by the decimation squared) in all; a region whose contrast
    lies wholly within the boxes ``explained`` (x0, y0, x1, y1: tags not ours found there lately, the
    prints of the markers found) is left out.

    ``contrast`` and ``top``: :func:`cell_contrast`. Black ink reflects a tenth or less of what white
    paper does, whatever the light: a printed marker's outline crosses cells whose darkest pixel is at
    most ``1 - MIN_RATIO`` of their brightest; such cells (with at least ``MIN_CONTRAST``), with their
    neighbours, are joined into regions, strongest contrast first.
    """
    contrast = np.where(contrast >= MIN_RATIO * np.maximum(top, 1), contrast, 0).astype(np.uint8)
    for x0, y0, x1, y1, *_ in taken:  # markers found: their cells are not candidates
        x0, y0 = max(int(x0), 0) // CELL_PX, max(int(y0), 0) // CELL_PX
        contrast[y0 : -(-int(y1) // CELL_PX), x0 : -(-int(x1) // CELL_PX)] = 0
    if quiet is not None:  # searched lately and found to be texture
        contrast[quiet] = 0
    strong = contrast >= MIN_CONTRAST
    foreign = np.zeros(contrast.shape, bool)  # the cells of the boxes ``explained``
    for x0, y0, x1, y1 in explained or ():
        x0, y0 = max(int(x0), 0) // CELL_PX, max(int(y0), 0) // CELL_PX
        foreign[y0 : -(-int(y1) // CELL_PX), x0 : -(-int(x1) // CELL_PX)] = True
    mask = cv2.dilate(strong.astype(np.uint8), np.ones((3, 3), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    peaks = []
    for i in range(1, n):
        x, y, bw, bh = stats[i, :4]
        inside = labels[y : y + bh, x : x + bw] == i
        if explained and foreign[y : y + bh, x : x + bw][inside & strong[y : y + bh, x : x + bw]].all():
            continue  # tags not ours, whatever their contrast: a marker of ours beside them has cells of its own
        peaks.append((-int(contrast[y : y + bh, x : x + bw][inside].max()), i))
    out = []
    m = BORDER_MARGIN_PX
    for _, i in sorted(peaks):
        x, y, bw, bh = (int(v) * CELL_PX for v in stats[i, :4])
        # A wide region holds large markers (or clutter): searched decimated, as a tracked one would be.
        side = min(bw, bh) - 2 * CELL_PX  # the largest marker it can hold
        decimate = float(min(max(side // SMALL_SIDE_PX, 1), MAX_REGION_DECIMATE))
        cost = (bw + 2 * m) * (bh + 2 * m) / decimate**2
        if cost > budget_px:
            continue
        budget_px -= cost
        out.append(np.array([x - m, y - m, x + bw + m, y + bh + m, decimate]))
    return out


def _area(r: list[float]) -> float:
    return (r[2] - r[0]) * (r[3] - r[1])


def _merge(boxes: list[NDArray[np.float64]], w: int, h: int) -> list[tuple[int, int, int, int, float]]:
    """Clip boxes (x0, y0, x1, y1[, decimate]; 1 if not given) to the image and merge overlapping ones
    (so no marker is cut in two), a merged region at the smallest of its decimations."""
    rects = [
        [max(int(b[0]), 0), max(int(b[1]), 0), min(int(b[2]) + 1, w), min(int(b[3]) + 1, h), b[4] if len(b) > 4 else 1]
        for b in boxes
    ]
    rects = [r for r in rects if r[2] - r[0] >= 16 and r[3] - r[1] >= 16]
    merged: list[list[float]] = []
    for r in sorted(rects):
        for m in merged:
            union = (max(m[2], r[2]) - min(m[0], r[0])) * (max(m[3], r[3]) - min(m[1], r[1]))
            # Overlapping boxes are searched as one where that is cheaper than searching both (each
            # holds its own marker whole).
            if r[0] <= m[2] and r[2] >= m[0] and r[1] <= m[3] and r[3] >= m[1] and union <= _area(r) + _area(m):
                m[:] = [min(m[0], r[0]), min(m[1], r[1]), max(m[2], r[2]), max(m[3], r[3]), min(m[4], r[4])]
                break
        else:
            merged.append(r)
    return [(int(a), int(b), int(c), int(d), float(e)) for a, b, c, d, e in merged]
