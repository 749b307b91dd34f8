"""Live refinement of the world map from the swarm's observations (issue 21): evidence per marker,
its robust mean and covariance, and when a marker's refined pose may replace the world file's.

Evidence comes one image at a time: the world markers one camera saw in one image, each with its own
pose in the camera (the square's own solve, ``T_sensor_marker``) and that pose's 6x6 covariance. For
each marker seen with at least ``min_others`` other world markers, the others place the camera
(``T_world_sensor = T_world_other T_sensor_other^-1``, fused by information), and the camera places the
marker (``T_world_marker = T_world_sensor T_sensor_marker``): leave-one-out, a marker never confirms
itself. An image whose others do not agree with each other (a moved marker among them, a flipped
square) gives no evidence (counted). The evidence of a marker is accumulated over many images, and
its robust mean (outliers gated by Mahalanobis distance against the evidence's own scatter) is the
refined pose, with a covariance that counts views, not frames (successive frames from one place share
their errors).

A refined pose replaces the map's (:meth:`MapRefiner.step`) only when it is converged and
significant: enough independent views (images at least ``view_gap_s`` apart per camera), seen over a
spread of directions, a small sigma, and an offset from the current pose beyond its noise and beyond
``min_offset_m`` / ``min_offset_deg``. Each update moves one marker, the most significant, at most
``max_step_m`` and ``max_step_deg``, and drops the evidence it gave the others (gathered again against
its new pose). Anchors (surveyed markers) are never moved.

Conventions as in :mod:`atlas_onboard.core.covariance`: a pose's error is ``[dp, dtheta]``, ``dp`` in the
parent frame (m) and ``dtheta`` about the child's own axes (rad). Pure: the time is each image's
capture stamp (microseconds), passed in.
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


@dataclass(frozen=True)
class RefineOptions:
    """When evidence counts and when a refined pose is used (lengths m, angles deg, times s)."""

    min_others: int = 2  # other world markers in the image; two can be checked against each other
    consistency_p: float = 1e-4  # the others' camera poses disagree when their chi2 has this tail probability
    outlier_p: float = 1e-4  # an evidence item is an outlier when its distance has this tail probability
    min_views: int = 12  # independent views (images at least view_gap_s apart per camera)
    view_gap_s: float = 0.5
    min_spread_deg: float = 5.0  # the viewing directions' widest angle from their mean direction
    max_sigma_m: float = 0.005  # the refined position's largest 1-sigma
    max_sigma_deg: float = 1.0  # the refined rotation's largest 1-sigma
    significance_p: float = 1e-6  # the offset from the current pose, against the refined covariance
    min_offset_m: float = 0.01  # smaller offsets are left alone (well within what the poses' noise hides)
    min_offset_deg: float = 1.0
    max_step_m: float = 0.05  # one update moves a marker at most this far
    max_step_deg: float = 2.0
    max_evidence: int = 2000  # items kept per marker (the newest)


@dataclass(frozen=True)
class Sighting:
    """One world marker in one image: its pose in the sensor's optical frame and its covariance.

    ``p_sensor_marker_m`` (3,), ``R_sensor_marker`` (3, 3), ``cov`` (6, 6): ``[dp, dtheta]`` with dp
    in the sensor frame (m) and dtheta about the marker's axes (rad)."""

    marker_id: int
    p_sensor_marker_m: NDArray[np.float64]
    R_sensor_marker: NDArray[np.float64]
    cov: NDArray[np.float64]


@dataclass(frozen=True)
class Evidence:
    """Where one image places one marker, from the other markers it shows (world frame)."""

    p_world_marker_m: NDArray[np.float64]
    R_world_marker: NDArray[np.float64]
    cov: NDArray[np.float64]  # (6, 6)
    direction: NDArray[np.float64]  # (3,) unit: from the marker towards the camera, in the marker's frame
    camera: Hashable  # which camera (sensor) took the image
    capture_time_us: int
    others: frozenset[int] = frozenset()  # the markers that placed the camera


@dataclass(frozen=True)
class Estimate:
    """A marker's refined pose in the world frame, from its inlying evidence.

    ``cov`` (6, 6) is the refined pose's covariance; ``views`` the independent views among the inliers;
    ``spread_deg`` the widest angle of a viewing direction from their mean; ``offset_m`` /
    ``offset_deg`` how far it is from the current map pose; ``distance2`` that offset's squared
    Mahalanobis distance under ``cov``."""

    marker_id: int
    p_world_marker_m: NDArray[np.float64]
    R_world_marker: NDArray[np.float64]
    cov: NDArray[np.float64]
    items: int
    outliers: int
    views: int
    spread_deg: float
    offset_m: NDArray[np.float64]
    offset_deg: float
    distance2: float
    scatter: float = 1.0  # the inliers' median squared distance over its chi-square median (at least 1)

    @property
    def sigma_m(self) -> NDArray[np.float64]:
        """(3,) 1-sigma of the position along the world axes, m."""
        return np.sqrt(np.diag(self.cov)[:3])

    @property
    def sigma_deg(self) -> NDArray[np.float64]:
        """(3,) 1-sigma of the rotation about the world axes, degrees."""
        R = self.R_world_marker
        return np.degrees(np.sqrt(np.diag(R @ self.cov[3:, 3:] @ R.T)))

    @property
    def max_sigma_m(self) -> float:
        return float(math.sqrt(max(np.linalg.eigvalsh(self.cov[:3, :3])[-1], 0.0)))

    @property
    def max_sigma_deg(self) -> float:
        return float(math.degrees(math.sqrt(max(np.linalg.eigvalsh(self.cov[3:, 3:])[-1], 0.0))))


@dataclass(frozen=True)
class Update:
    """A marker moved by :meth:`MapRefiner.step`: its new map pose and covariance, and the estimate."""

    marker_id: int
    p_world_marker_m: NDArray[np.float64]
    R_world_marker: NDArray[np.float64]
    cov: NDArray[np.float64]
    step_m: float
    step_deg: float
    reached: bool  # the step reached the estimate (not cut short by the step bound)
    estimate: Estimate


@dataclass
class _MapPose:
    p: NDArray[np.float64]
    R: NDArray[np.float64]
    cov: NDArray[np.float64] = field(default_factory=lambda: np.zeros((6, 6)))


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
        seen = [s for s in sightings if s.marker_id in self._map]
        ids = [s.marker_id for s in seen]
        if len(set(ids)) != len(ids):  # an id twice in one image: which one is it?
            self.counters["rejected_duplicate"] += 1
            return 0
        if len(seen) < self.options.min_others + 1:
            self.counters["rejected_few_markers"] += 1
            return 0
        n = len(seen)
        p_sm = np.array([s.p_sensor_marker_m for s in seen])
        R_sm = np.array([s.R_sensor_marker for s in seen])
        C_sm = np.array([s.cov for s in seen])
        cams = self._camera_candidates(seen, p_sm, R_sm, C_sm)
        if cams is None:
            self.counters["rejected_singular"] += 1
            return 0
        fused = _leave_one_out(*cams)
        if fused is None:
            self.counters["rejected_singular"] += 1
            return 0
        p_ws, R_ws, C_ws, chi2_values = fused
        # T_world_marker = T_world_sensor T_sensor_marker, the camera's and the square's errors together.
        Jp, Je = covariance.compose_jacobians(R_ws, p_sm, R_sm)
        cov = covariance.transform(Jp, C_ws) + covariance.transform(Je, C_sm)
        cov = 0.5 * (cov + np.swapaxes(cov, -1, -2))
        p_wm = p_ws + (R_ws @ p_sm[..., None])[..., 0]
        R_wm = R_ws @ R_sm
        to_camera = -(np.swapaxes(R_sm, -1, -2) @ p_sm[..., None])[..., 0]
        directions = to_camera / np.maximum(np.linalg.norm(to_camera, axis=1, keepdims=True), 1e-9)
        # With one other there is nothing to check it against: min_others 1 leaves trust to the caller.
        limit = chdtri(6 * (n - 2), self.options.consistency_p) if n > 2 else math.inf
        added = 0
        ids_seen = frozenset(ids)
        for i, s in enumerate(seen):
            if s.marker_id in self.anchors:
                self.counters["rejected_anchor"] += 1
                continue
            if chi2_values[i] > limit:
                self.counters["rejected_inconsistent"] += 1
                continue
            items = self._evidence.setdefault(s.marker_id, deque(maxlen=self.options.max_evidence))
            others = ids_seen - {s.marker_id}
            items.append(Evidence(p_wm[i], R_wm[i], cov[i], directions[i], camera, int(capture_time_us), others))
            added += 1
        if added:
            self.counters["images"] += 1
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

        A robust start (the median position, the rotation of the item nearest it), then the
        information-weighted mean, iterated with outliers gated: an item is an outlier when its
        Mahalanobis distance, after scaling every item's covariance by the evidence's own scatter
        (the median distance over the chi-square median, at least 1), has a tail probability below
        ``outlier_p``. The mean's covariance is the inliers' information inverted, scaled by that
        scatter and by frames per independent view."""
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
        med = np.median(P, axis=0)
        k0 = int(np.argmin(np.linalg.norm(P - med, axis=1)))
        p_ref, R_ref = med, Rs[k0]
        inlier = np.ones(len(items), dtype=bool)
        scale = 1.0
        gate = chdtri(6, o.outlier_p)
        for _ in range(5):
            r = residuals(P, Rs, p_ref, R_ref)  # (n, 6) about the reference
            x = np.linalg.solve(W[inlier].sum(axis=0), np.einsum("nij,nj->i", W[inlier], r[inlier]))
            p_ref, R_ref = p_ref + x[:3], R_ref @ Rotation.from_rotvec(x[3:]).as_matrix()
            r = residuals(P, Rs, p_ref, R_ref)
            d2 = np.einsum("ni,nij,nj->n", r, W, r)
            scale = max(1.0, float(np.median(d2[inlier])) / chdtri(6, 0.5))
            new = d2 / scale <= gate
            if new.sum() < 2:
                return None
            if np.array_equal(new, inlier):
                break
            inlier = new
        views = _views(items, inlier, o.view_gap_s)
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
            p_ref - m.p, float(np.degrees(np.linalg.norm(delta[3:]))), d2_map, scale,
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


def residuals(P: NDArray, Rs: NDArray, p_ref: NDArray, R_ref: NDArray) -> NDArray[np.float64]:
    """(n, 6) errors ``[p - p_ref, Log(R_ref^T R)]`` of poses about a reference (dtheta in its axes)."""
    rot = Rotation.from_matrix(np.swapaxes(R_ref, -1, -2) @ Rs).as_rotvec()
    return np.concatenate([P - p_ref, rot], axis=1)


def _leave_one_out(P: NDArray, Rs: NDArray, C: NDArray) -> tuple[NDArray, NDArray, NDArray, NDArray] | None:
    """For each of n candidate poses (p (n, 3), R (n, 3, 3), C (n, 6, 6)), the information-weighted
    mean of the others: p (n, 3), R (n, 3, 3), its covariance (n, 6, 6), and the chi-square of those
    others about it (6 (n - 2) degrees of freedom when they agree). Gauss-Newton, twice, each mean
    about its own reference (the first of its others to start)."""
    n = len(P)
    try:
        W = np.linalg.inv(C)
    except np.linalg.LinAlgError:
        return None
    others = ~np.eye(n, dtype=bool)
    Wo = W[None] * others[:, :, None, None]  # (i, k, 6, 6): candidate k's weight in i's mean
    info = Wo.sum(axis=1)
    first = np.where(np.arange(n) == 0, 1, 0)
    p_ref, R_ref = P[first], Rs[first]
    try:
        for _ in range(2):
            r = _residuals_each(P, Rs, p_ref, R_ref)
            x = np.linalg.solve(info, np.einsum("ikab,ikb->ia", Wo, r)[..., None])[..., 0]
            p_ref = p_ref + x[:, :3]
            R_ref = R_ref @ Rotation.from_rotvec(x[:, 3:]).as_matrix()
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        return None
    r = _residuals_each(P, Rs, p_ref, R_ref)
    values = np.einsum("ika,ikab,ikb->i", r, Wo, r)
    return p_ref, R_ref, 0.5 * (cov + np.swapaxes(cov, -1, -2)), values


def _residuals_each(P: NDArray, Rs: NDArray, p_ref: NDArray, R_ref: NDArray) -> NDArray[np.float64]:
    """(m, n, 6): the n poses' errors about each of m references (:func:`residuals`)."""
    m, n = len(p_ref), len(P)
    rel = np.swapaxes(R_ref, -1, -2)[:, None] @ Rs[None]
    rot = Rotation.from_matrix(rel.reshape(m * n, 3, 3)).as_rotvec().reshape(m, n, 3)
    return np.concatenate([P[None] - p_ref[:, None], rot], axis=2)


def _views(items: Sequence[Evidence], inlier: NDArray[np.bool_], gap_s: float) -> int:
    """Independent views among the inliers: per camera, images at least ``gap_s`` after the last counted."""
    last: dict[Hashable, int] = {}
    n = 0
    gap_us = gap_s * 1e6
    for e, ok in sorted(zip(items, inlier, strict=True), key=lambda t: t[0].capture_time_us):
        if not ok:
            continue
        t = last.get(e.camera)
        if t is None or e.capture_time_us - t >= gap_us:
            last[e.camera] = e.capture_time_us
            n += 1
    return n
