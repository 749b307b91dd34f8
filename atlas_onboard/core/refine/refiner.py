"""The evidence of every world marker, its estimate, and when the map moves (see :mod:`atlas_onboard.core.refine`).

Conventions as in :mod:`atlas_onboard.core.covariance`: a pose's error is ``[dp, dtheta]``, ``dp`` in the
parent frame (m) and ``dtheta`` about the child's own axes (rad). Pure: the time is each
image's capture stamp (microseconds), passed in.
"""

from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Callable, Hashable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.special import chdtri  # chi-square's inverse survival function (scipy.stats costs 0.6 s to import)

from atlas_onboard.core import covariance
from atlas_onboard.core.refine.mean import residuals, robust_mean, view_labels, view_scatter
from atlas_onboard.core.refine.placement import leave_one_out_many
from atlas_onboard.core.refine.records import Estimate, Evidence, Image, RefineOptions, Sighting, Update


@dataclass
class _MapPose:
    p: NDArray[np.float64]
    R: NDArray[np.float64]
    cov: NDArray[np.float64] = field(default_factory=lambda: np.zeros((6, 6)))


@dataclass(frozen=True)
class _Placed:
    """Where the others of b images place n markers of each (:meth:`MapRefiner._place`): arrays of b n
    rows, image by image, or of one image's n (:meth:`image`)."""

    n: int
    p: NDArray[np.float64]
    R: NDArray[np.float64]
    cov: NDArray[np.float64]
    direction: NDArray[np.float64]
    chi2: NDArray[np.float64]

    def image(self, j: int) -> _Placed:
        rows = slice(j * self.n, (j + 1) * self.n)
        return _Placed(self.n, self.p[rows], self.R[rows], self.cov[rows], self.direction[rows], self.chi2[rows])


class MapRefiner:
    """The evidence of every world marker and the map it refines (see the module).

    ``T_world_marker``: the world file's marker poses, id -> (p (3,), R (3, 3)), ENU world frame;
    ``anchors``: ids never moved (surveyed markers). ``counters``: ``images`` (images with evidence),
    ``evidence``, ``rejected_few_markers`` (images with too few world markers), ``rejected_inconsistent``
    (others that disagree), ``rejected_singular`` (a covariance that cannot be inverted),
    ``rejected_anchor`` (evidence of an anchor, not kept), ``updates`` (bounded steps applied)."""

    def __init__(
        self,
        T_world_marker: Mapping[int, tuple[NDArray[np.float64], NDArray[np.float64]]],
        anchors: Iterable[int] = (),
        options: RefineOptions | None = None,
    ) -> None:
        self.options = options or RefineOptions()
        self._map = {int(k): _MapPose(np.array(p, float), np.array(R, float)) for k, (p, R) in T_world_marker.items()}
        self._file = {k: (v.p.copy(), v.R.copy()) for k, v in self._map.items()}
        self.anchors = frozenset(int(a) for a in anchors)
        self._evidence: dict[int, deque[Evidence]] = {}
        self._active: set[int] = set()  # markers moved at least once: they continue to their estimate
        self.counters: Counter[str] = Counter()

    # --- the map --------------------------------------------------------------------------------------

    def pose(self, marker_id: int) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """The current map pose of a marker: p (3,), R (3, 3) and its 6x6 covariance (zero: as in the file)."""
        m = self._map[marker_id]
        return m.p.copy(), m.R.copy(), m.cov.copy()

    @property
    def moved(self) -> frozenset[int]:
        """The markers whose map pose differs from the world file's."""
        return frozenset(self._active)

    def file_offset_m(self, marker_id: int) -> NDArray[np.float64]:
        """(3,) current map position minus the world file's, world axes, m."""
        return self._map[marker_id].p - self._file[marker_id][0]

    # --- evidence -------------------------------------------------------------------------------------

    def add_image(self, camera: Hashable, capture_time_us: int, sightings: Sequence[Sighting]) -> int:
        """One image's world markers (unknown ids ignored); returns how many evidence items it gave."""
        return self.add_images([Image(camera, capture_time_us, tuple(sightings))])

    def add_images(self, images: Sequence[Image], marker_id: int | None = None) -> int:
        """Several images' world markers, oldest first: the evidence :meth:`add_image` of each in turn gives,
        the arithmetic of the images with as many markers done at once; returns the evidence items added.
        With ``marker_id``: that marker's evidence alone (the others' is not computed; the counters of
        whole images, ``images`` and the image rejections, are left to the call without it)."""
        whole = marker_id is None
        seen = [self._screen(image.sightings, count=whole) for image in images]
        rows: list[list[int]] = [[] for _ in images]
        for k, found in enumerate(seen):
            if found:
                rows[k] = (
                    list(range(len(found))) if whole else [i for i, s in enumerate(found) if s.marker_id == marker_id]
                )
        placed: list[_Placed | None] = [None] * len(images)
        for n in sorted({len(s) for k, s in enumerate(seen) if s and rows[k]}):
            group = [k for k, s in enumerate(seen) if s and rows[k] and len(s) == n]
            row = None if whole else np.array([rows[k][0] for k in group])
            got = self._place([seen[k] for k in group], row)
            if got is None:  # some image is singular: each on its own, to tell which
                for j, k in enumerate(group):
                    placed[k] = self._place([seen[k]], None if row is None else row[j : j + 1])
                    self.counters["rejected_singular"] += whole and placed[k] is None
                continue
            for j, k in enumerate(group):
                placed[k] = got.image(j)
        added = 0
        for image, found, got, kept in zip(images, seen, placed, rows, strict=True):
            if found and got is not None:
                added += self._keep(image, found, kept, got, count=whole)
        return added

    def _screen(self, sightings: Sequence[Sighting], count: bool = True) -> list[Sighting] | None:
        """An image's known markers, or None (counted with ``count``) when they cannot give evidence."""
        seen = [s for s in sightings if s.marker_id in self._map]
        ids = [s.marker_id for s in seen]
        if len(set(ids)) != len(ids):  # an id twice in one image: which one is it?
            self.counters["rejected_duplicate"] += count
            return None
        if len(seen) < self.options.min_others + 1:
            self.counters["rejected_few_markers"] += count
            return None
        return seen

    def _place(self, images: Sequence[Sequence[Sighting]], row: NDArray[np.int_] | None = None) -> _Placed | None:
        """Where the others of each image (all of n markers) place each marker (or the one of ``row``, see
        :func:`leave_one_out_many`), with the covariance and the others' chi-square, image by image; None if
        any image's covariances are singular."""
        b, n = len(images), len(images[0])
        flat = [s for seen in images for s in seen]
        p_sm = np.array([s.p_sensor_marker_m for s in flat])
        R_sm = np.array([s.R_sensor_marker for s in flat])
        C_sm = np.array([s.cov for s in flat])
        cams = self._camera_candidates(flat, p_sm, R_sm, C_sm)
        if cams is None:
            return None
        fused = leave_one_out_many(*(a.reshape(b, n, *a.shape[1:]) for a in cams), row)
        if fused is None:
            return None
        m = n if row is None else 1
        p_ws, R_ws, C_ws, chi2_values = (a.reshape(b * m, *a.shape[2:]) for a in fused)
        if row is not None:  # the placed marker's own square in each image
            mine = np.arange(b) * n + row
            p_sm, R_sm, C_sm = p_sm[mine], R_sm[mine], C_sm[mine]
        # T_world_marker = T_world_sensor T_sensor_marker, the camera's and the square's errors together.
        Jp, Je = covariance.compose_jacobians(R_ws, p_sm, R_sm)
        cov = covariance.transform(Jp, C_ws) + covariance.transform(Je, C_sm)
        cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
        p_wm = p_ws + (R_ws @ p_sm[..., None])[..., 0]
        R_wm = R_ws @ R_sm
        to_camera = -(np.swapaxes(R_sm, -1, -2) @ p_sm[..., None])[..., 0]
        directions = to_camera / np.maximum(np.linalg.norm(to_camera, axis=1, keepdims=True), 1e-9)
        return _Placed(m, p_wm, R_wm, cov, directions, chi2_values)

    def _keep(self, image: Image, seen: Sequence[Sighting], rows: Sequence[int], placed: _Placed, count: bool) -> int:
        """An image's evidence items of the markers at ``rows`` of ``seen`` (``placed`` in that order) kept,
        those whose others agree; returns how many (``count``: the image counted when it gave any)."""
        n = len(seen)
        # With one other there is nothing to check it against: min_others 1 leaves trust to the caller.
        limit = chdtri(6 * (n - 2), self.options.consistency_p) if n > 2 else math.inf
        added = 0
        ids_seen = frozenset(s.marker_id for s in seen)
        for j, i in enumerate(rows):
            s = seen[i]
            if s.marker_id in self.anchors:
                self.counters["rejected_anchor"] += 1
                continue
            if placed.chi2[j] > limit:
                self.counters["rejected_inconsistent"] += 1
                continue
            items = self._evidence.setdefault(s.marker_id, deque(maxlen=self.options.max_evidence))
            others = ids_seen - {s.marker_id}
            items.append(
                Evidence(placed.p[j], placed.R[j], placed.cov[j], placed.direction[j], image.camera,
                         int(image.capture_time_us), others)
            )  # fmt: skip
            added += 1
        if added:
            self.counters["images"] += count
            self.counters["evidence"] += added
        return added

    def _camera_candidates(
        self, seen: Sequence[Sighting], p_sm: NDArray, R_sm: NDArray, C_sm: NDArray
    ) -> tuple[NDArray, NDArray, NDArray] | None:
        """T_world_sensor from each sighting and its marker's map pose (with its covariance):
        p (n, 3), R (n, 3, 3), C (n, 6, 6); None if a covariance is not finite."""
        maps = [self._map[s.marker_id] for s in seen]
        p_wm = np.array([m.p for m in maps])
        R_wm = np.array([m.R for m in maps])
        C_wm = np.array([m.cov for m in maps])
        R_ms = np.swapaxes(R_sm, -1, -2)
        p_ms = -(R_ms @ p_sm[..., None])[..., 0]
        C_ms = covariance.transform(covariance.inverse_jacobian(p_sm, R_sm), C_sm)
        Jp, Je = covariance.compose_jacobians(R_wm, p_ms, R_ms)
        C = covariance.transform(Jp, C_wm) + covariance.transform(Je, C_ms)
        if not np.all(np.isfinite(C)):
            return None
        return p_wm + (R_wm @ p_ms[..., None])[..., 0], R_wm @ R_ms, C

    # --- the estimate ---------------------------------------------------------------------------------

    def evidence(self, marker_id: int) -> list[Evidence]:
        return list(self._evidence.get(marker_id, ()))

    def latest(self, marker_id: int) -> Evidence | None:
        """The marker's newest evidence item (None without any)."""
        items = self._evidence.get(marker_id)
        return items[-1] if items else None

    def estimate(self, marker_id: int, accept: Callable[[Evidence], bool] | None = None) -> Estimate | None:
        """The marker's refined pose from its evidence (None without two items or if singular);
        ``accept``: only the items it accepts count (e.g. those whose ``others`` are trusted now).

        The robust mean of the evidence (:func:`~atlas_onboard.core.refine.mean.robust_mean`); its
        covariance is the inliers' information inverted, scaled by the evidence's scatter and by frames
        per independent view; the views' scatter about each other comes with it
        (:func:`~atlas_onboard.core.refine.mean.view_scatter`)."""
        items = self._evidence.get(marker_id)
        if items is not None and accept is not None:
            items = [e for e in items if accept(e)]
        if not items or len(items) < 2:
            return None
        o = self.options
        P = np.array([e.p_world_marker_m for e in items])
        Rs = np.array([e.R_world_marker for e in items])
        C = np.array([e.cov for e in items])
        try:
            W = np.linalg.inv(C)
        except np.linalg.LinAlgError:
            return None
        mean = robust_mean(P, Rs, W, o.outlier_p)
        if mean is None:
            return None
        p_ref, R_ref, inlier, scale = mean
        labels = view_labels(items, inlier, o.view_gap_s)
        views = int(labels.max()) + 1
        by_view = view_scatter(residuals(P, Rs, p_ref, R_ref), W, labels)
        if by_view is None:
            return None
        info = W[inlier].sum(axis=0)
        cov = np.linalg.inv(info) * scale * max(1.0, inlier.sum() / max(views, 1))
        cov = 0.5 * (cov + cov.T)
        dirs = np.array([e.direction for e, ok in zip(items, inlier, strict=True) if ok])
        mean_dir = dirs.mean(axis=0)
        mean_dir /= max(float(np.linalg.norm(mean_dir)), 1e-9)
        spread = float(np.degrees(np.arccos(np.clip(dirs @ mean_dir, -1.0, 1.0)).max()))
        m = self._map[marker_id]
        delta = residuals(m.p[None], m.R[None], p_ref, R_ref)[0]  # current map pose about the estimate
        try:
            d2_map = float(delta @ np.linalg.solve(cov, delta))
        except np.linalg.LinAlgError:
            return None
        return Estimate(
            marker_id, p_ref, R_ref, cov, len(items), int((~inlier).sum()), views, spread,
            p_ref - m.p, float(np.degrees(np.linalg.norm(delta[3:]))), d2_map, scale, *by_view,
        )  # fmt: skip

    def forget(self, marker_id: int, before_us: int) -> None:
        """Drop a marker's evidence captured before ``before_us`` (it has moved since)."""
        items = self._evidence.get(marker_id)
        if items:
            self._evidence[marker_id] = deque((e for e in items if e.capture_time_us >= before_us), items.maxlen)

    def verdict(self, est: Estimate) -> str | None:
        """Why ``est`` may not replace the map pose (None: it may)."""
        o = self.options
        if est.marker_id in self.anchors:
            return "an anchor (surveyed)"
        if est.views < o.min_views:
            return f"{est.views} independent views (needs {o.min_views})"
        if est.spread_deg < o.min_spread_deg:
            return f"seen from one direction only ({est.spread_deg:.1f} deg, needs {o.min_spread_deg:g})"
        if est.max_sigma_m > o.max_sigma_m or est.max_sigma_deg > o.max_sigma_deg:
            return f"not converged (sigma {est.max_sigma_m * 1000:.1f} mm, {est.max_sigma_deg:.2f} deg)"
        if est.distance2 <= chdtri(6, o.significance_p):
            return "within the noise of the current pose"
        offset = float(np.linalg.norm(est.offset_m))
        if est.marker_id not in self._active and offset < o.min_offset_m and est.offset_deg < o.min_offset_deg:
            return f"offset {offset * 1000:.1f} mm, {est.offset_deg:.2f} deg: too small to act on"
        return None

    def step(self) -> list[Update]:
        """Move the marker whose estimate passes :meth:`verdict` and is farthest from its map pose (in
        its own sigmas) towards it, by a bounded step; its map covariance becomes its estimate's.

        One marker a step, the most significant first: a misplaced marker biases the evidence of every
        marker it helped place the camera for (a little, within the consistency gate, but the same in
        every image), so that evidence is dropped when it moves and gathered again against its new
        pose. Returns the update made (none or one)."""
        o = self.options
        best: Estimate | None = None
        for mid in sorted(self._evidence):
            est = self.estimate(mid)
            if est is not None and self.verdict(est) is None and (best is None or est.distance2 > best.distance2):
                best = est
        if best is None:
            return []
        mid, est = best.marker_id, best
        m = self._map[mid]
        dp = est.p_world_marker_m - m.p
        dr = Rotation.from_matrix(m.R.T @ est.R_world_marker).as_rotvec()
        dist, ang = float(np.linalg.norm(dp)), float(np.degrees(np.linalg.norm(dr)))
        f = min(1.0, o.max_step_m / dist if dist > 0 else 1.0, o.max_step_deg / ang if ang > 0 else 1.0)
        m.p = m.p + f * dp
        m.R = m.R @ Rotation.from_rotvec(f * dr).as_matrix()
        # Short of the estimate, the pose is off by what is left of the step as well as by the noise.
        left = (1.0 - f) * np.concatenate([dp, dr])
        m.cov = est.cov + np.outer(left, left)
        self._active.add(mid)
        self.counters["updates"] += 1
        for other, items in self._evidence.items():  # placed with its old pose: gathered again
            if other != mid:
                kept = [e for e in items if mid not in e.others]
                self.counters["evidence_dropped"] += len(items) - len(kept)
                self._evidence[other] = deque(kept, maxlen=o.max_evidence)
        return [Update(mid, m.p.copy(), m.R.copy(), m.cov.copy(), f * dist, f * ang, f == 1.0, est)]
