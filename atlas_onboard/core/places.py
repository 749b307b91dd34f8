"""A moved world marker used at its measured place, not lost.

Where images in which trusted markers placed the camera put the marker, with the covariance of that
estimate, is its measured place, used instead of the world file's while new evidence keeps fitting it.

Pure: the time is each image's capture stamp, passed in.
"""

from __future__ import annotations

import itertools
import math
from collections import deque
from collections.abc import Callable, Hashable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform
from scipy.special import chdtri  # chi-square's inverse survival function (scipy.stats costs 0.6 s to import)

from atlas_onboard.core import covariance
from atlas_onboard.core.refine import Estimate, MapRefiner, RefineOptions, WorldMarkerPose, residuals
from atlas_onboard.core.refine import Sighting as PlacedSighting
from atlas_onboard.core.refine.records import Image
from atlas_onboard.core.worldcheck import MAX_EVIDENCE, WINDOW_S
from atlas_onboard.errors import GeometryError

PLACE_MIN_VIEWS = 2  # independent views (refine's view gap): one burst cannot show its own shared error or a move
PLACE_MAX_SCATTER = 9.0  # the evidence (images, and views about each other) may scatter at most 3x (in sigma)
PLACE_SCALE_P = 0.05  # the views' scatter ratio is taken at its upper bound of this tail probability
PLACE_MAX_OUTLIERS = 0.25  # of the evidence items, the share the robust mean may set aside
PLACE_MAX_SIGMA_M = 0.02  # a place more uncertain than this is not used (its poses would be worth little)
PLACE_MAX_SIGMA_DEG = 3.0
RECHECK_P = 1e-4  # a new item does not fit the place when its position's distance has this tail probability
RECHECK_MIN_M = 0.01  # and it is at least this far (closer, the pose errs by less than the bars allow)
RECHECK_MIN_DEG = 2.0  # or turned by at least this much (and beyond the same distance, in rotation)
RECHECK_LAST = 5  # the newest trusted items that decide whether the place still holds
RECHECK_MISFITS = 3  # of those, this many that do not fit: the marker has moved again


def place_covariance(est: Estimate) -> NDArray[np.float64]:
    """(6, 6) an honest covariance of a marker's estimated pose however few views back it.

    Images of one view share their errors, so the views are the samples: the pose's covariance with each
    view worth one average image of it (``est.view_cov``), times the views' scatter ratio at its upper
    bound: if that model is right up to a factor k, the views' chi-square is k times a chi-square variable
    of ``est.view_dof`` degrees of freedom, so k is below it over the chi-square's ``PLACE_SCALE_P``
    quantile with probability ``1 - PLACE_SCALE_P``. Few views give a wide bound (a large factor), many a
    factor near their scatter; never below the model or the images' own scatter."""
    if est.view_cov is None or est.view_dof < 6:
        raise GeometryError(f"expected an estimate from two or more views, got {est.views}")
    k = max(1.0, est.scatter, est.view_chi2 / chdtri(est.view_dof, 1.0 - PLACE_SCALE_P))
    return est.view_cov * k


@dataclass(frozen=True)
class MeasuredPlace(WorldMarkerPose):
    """Where a moved world marker really is, from images in which trusted markers placed the camera.

    Attributes:
        marker_id: the marker.
        p_world_marker_m: (3,) its measured position, world frame, m.
        R_world_marker: (3, 3) its measured rotation.
        cov: (6, 6) the place's covariance (``[dp, dtheta]``, dp world frame m, dtheta marker axes rad):
            :func:`place_covariance`, honest however few views back it.
        offset_m: (3,) measured position minus the world file's, world frame, m.
        scatter: the evidence's scatter factor (squared distances over what the covariances say, >= 1).
        items: evidence items used; views: independent views among them.
        since_us: capture time of the image in which it was established.
    """

    offset_m: NDArray[np.float64]
    scatter: float
    items: int
    views: int
    since_us: int

    def fits(
        self, p_world_marker_m: NDArray[np.float64], R_world_marker: NDArray[np.float64], cov: NDArray[np.float64]
    ) -> bool:
        """Whether a new sighting of the marker's pose in the world (covariance ``cov`` (6, 6), scaled by the
        evidence's scatter) is where the place is: a position beyond ``RECHECK_P`` of both covariances and
        ``RECHECK_MIN_M`` away, or a rotation beyond it and ``RECHECK_MIN_DEG``, does not fit. The floors:
        images from one view share errors their covariances do not show, and a move below them costs the
        pose less than its bars."""
        r = residuals(p_world_marker_m[None], R_world_marker[None], self.p_world_marker_m, self.R_world_marker)[0]
        C = self.scatter * cov + self.cov
        gate = chdtri(3, RECHECK_P)
        try:
            far = float(r[:3] @ np.linalg.solve(C[:3, :3], r[:3])) > gate and np.linalg.norm(r[:3]) >= RECHECK_MIN_M
            turned = float(r[3:] @ np.linalg.solve(C[3:, 3:], r[3:])) > gate and (
                math.degrees(float(np.linalg.norm(r[3:]))) >= RECHECK_MIN_DEG
            )
        except np.linalg.LinAlgError:
            return False
        return not (far or turned)

    def correct(
        self,
        p_sensor_marker_m: NDArray[np.float64],
        R_sensor_marker: NDArray[np.float64],
        cov: NDArray[np.float64],
        T_world_file: RigidTransform,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """A sighting of the marker re-expressed for its world-file pose ``T_world_file``:
        ``T_sensor_marker' = T_sensor_marker T_place^-1 T_file``, so that eq. 1 with the file pose places
        the sensor where the measured place does. Returns p' (3,), R' (3, 3), its covariance (6, 6: the
        sighting's ``cov`` and the place's together) and the (3, 3) covariance the place adds to the
        sensor's position in the world frame."""
        R_world_file, p_world_file_m = T_world_file.rotation.as_matrix(), T_world_file.translation
        # D = T_place^-1 T_file: the place's error through the inverse, then composed with the exact file pose.
        R_mw = self.R_world_marker.T
        C_inv = covariance.transform(covariance.inverse_jacobian(self.p_world_marker_m, self.R_world_marker), self.cov)
        d = R_mw @ (p_world_file_m - self.p_world_marker_m)
        R_d = R_mw @ R_world_file
        Jp_d, _ = covariance.compose_jacobians(R_mw, p_world_file_m, R_world_file)
        C_d = covariance.transform(Jp_d, C_inv)
        Jp, Je = covariance.compose_jacobians(R_sensor_marker, d, R_d)
        C = covariance.transform(Jp, cov) + covariance.transform(Je, C_d)
        # The sensor in the world through the place: T_place T_marker_sensor, the place's share of its position.
        R_ms = R_sensor_marker.T
        Jw, _ = covariance.compose_jacobians(self.R_world_marker, -R_ms @ p_sensor_marker_m, R_ms)
        C_sensor = covariance.transform(Jw, self.cov)[:3, :3]
        return (
            p_sensor_marker_m + R_sensor_marker @ d,
            R_sensor_marker @ R_d,
            0.5 * (C + C.T),
            0.5 * (C_sensor + C_sensor.T),
        )


class MeasuredPlaces:
    """The measured places of moved world markers (:class:`MeasuredPlace`), on the evidence of
    :class:`~atlas_onboard.core.refine.MapRefiner` (leave-one-out: the other markers of an image place the
    camera, the camera places the marker; the map stays the world file's).

    Only items whose placing markers the caller trusts count (``trusted``, asked when a place is
    established and when an item is re-checked: a marker placed by a moved or suspect one, or by itself,
    would be circular). A place is established when the evidence is consistent (its scatter and
    outliers bounded), from several independent views and precise enough; it is then re-checked with
    every new trusted item: when ``RECHECK_MISFITS`` of the newest ``RECHECK_LAST`` do not fit it (the
    marker was moved again, or is on something that moves), it is withdrawn and the evidence before those
    items forgotten, so that a new place can only come from what was seen since.
    """

    def __init__(
        self,
        T_world_marker: Mapping[int, tuple[NDArray[np.float64], NDArray[np.float64]]],
        window_s: float = WINDOW_S,
    ) -> None:
        # One other marker may place the camera (pairs): trust is decided by the caller, per item.
        self.refiner = MapRefiner(T_world_marker, options=RefineOptions(min_others=1, max_evidence=MAX_EVIDENCE))
        self.window_us = round(window_s * 1e6)
        self._places: dict[int, MeasuredPlace] = {}
        self._checks: dict[int, deque[tuple[int, bool]]] = {}  # marker -> (capture time us, fits) newest last
        # Images not yet turned into evidence (no place to re-check in them), oldest first: see add_image.
        self._pending: deque[Image] = deque()
        self._first = 0  # the number of the oldest of them (images numbered as they come)
        self._done: dict[int, int] = {}  # marker -> the number of the first image whose evidence it lacks

    def add_image(
        self,
        camera: Hashable,
        capture_time_us: int,
        sightings: Sequence[PlacedSighting],
        trusted: Callable[[frozenset[int]], bool],
    ) -> list[MeasuredPlace]:
        """One image's world markers (two or more); returns the places withdrawn by this image's evidence.

        The image is kept, and a marker's evidence from the kept images is computed (in capture order, the
        same items) only when the marker's place is sought or re-checked: here, the markers of the image
        that have a place. An image older than the window before the newest (capture stamps rising) is
        forgotten, since no estimate would take it."""
        if len(sightings) < 2:
            return []
        self._pending.append(Image(camera, capture_time_us, tuple(sightings)))
        while self._pending[0].capture_time_us < capture_time_us - self.window_us:
            self._pending.popleft()
            self._first += 1
        placed = {s.marker_id for s in sightings if s.marker_id in self._places}
        if not placed:
            return []
        self._catch_up(placed)
        out = []
        for s in sightings:
            place = self._places.get(s.marker_id)
            item = self.refiner.latest(s.marker_id)
            if place is None or item is None or item.capture_time_us != capture_time_us or not trusted(item.others):
                continue
            checks = self._checks.setdefault(s.marker_id, deque(maxlen=RECHECK_LAST))
            checks.append((capture_time_us, place.fits(item.p_world_marker_m, item.R_world_marker, item.cov)))
            misfits = [t for t, fits in checks if not fits]
            if len(misfits) >= RECHECK_MISFITS:
                self._checks.pop(s.marker_id, None)
                withdrawn = self._places.pop(s.marker_id, None)  # (None: dropped meanwhile by another thread)
                if withdrawn is not None:
                    out.append(withdrawn)
                self.refiner.forget(s.marker_id, misfits[0])
        return out

    def establish(self, marker_id: int, now_us: int, trusted: Callable[[frozenset[int]], bool]) -> MeasuredPlace | str:
        """The marker's measured place from its trusted evidence within the window, kept and returned, or
        why there is none yet (one line)."""
        if marker_id in self._places:
            return self._places[marker_id]
        self._catch_up({marker_id})
        since = now_us - self.window_us
        est = self.refiner.estimate(marker_id, accept=lambda e: e.capture_time_us >= since and trusted(e.others))
        if est is None:
            return "too little evidence from trusted markers"
        if est.views < PLACE_MIN_VIEWS:
            return f"{est.views} independent views (needs {PLACE_MIN_VIEWS})"
        view_scatter = est.view_chi2 / est.view_dof
        if max(est.scatter, view_scatter) > PLACE_MAX_SCATTER or est.outliers > PLACE_MAX_OUTLIERS * est.items:
            return (
                f"inconsistent evidence (scatter {est.scatter:.1f}, views {view_scatter:.1f},"
                f" {est.outliers} of {est.items} outliers)"
            )
        cov = place_covariance(est)
        place = MeasuredPlace(
            marker_id, est.p_world_marker_m, est.R_world_marker, cov, est.offset_m, est.scatter,
            est.items - est.outliers, est.views, now_us,
        )  # fmt: skip
        if place.max_sigma_m > PLACE_MAX_SIGMA_M or place.max_sigma_deg > PLACE_MAX_SIGMA_DEG:
            return f"not precise enough (sigma {place.max_sigma_m * 1000:.1f} mm, {place.max_sigma_deg:.2f} deg)"
        self._places[marker_id] = place
        return place

    def place(self, marker_id: int) -> MeasuredPlace | None:
        return self._places.get(marker_id)

    def _catch_up(self, markers: set[int]) -> None:
        """The kept images' evidence of ``markers`` not computed yet, oldest first, the items the images
        give one at a time (one marker at a time, the images with as many markers at once)."""
        end = self._first + len(self._pending)
        for m in sorted(markers):
            since = max(self._done.get(m, self._first), self._first)
            if since < end:
                self.refiner.add_images(list(itertools.islice(self._pending, since - self._first, None)), m)
                self._done[m] = end

    def drop(self, marker_id: int) -> None:
        """Forget a marker's place (it fits the world file again)."""
        self._places.pop(marker_id, None)
        self._checks.pop(marker_id, None)
