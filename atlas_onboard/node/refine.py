"""Live map refinement in the node (opt-in: ``nodes.<entity>.refine`` or ``run --write-map``).

The node hands every observation it accepted (its own cameras' and its peers') to :class:`LiveRefinement`,
which groups them by image (sensor and capture stamp) and gives each image's world markers to the pure
:class:`~atlas_onboard.core.refine.MapRefiner`. Once a second it lets the refiner move the markers whose
evidence is converged and significant, puts each moved marker's pose and covariance into the listener
(eq. 1's ``T3``, from then on instead of the world file's), logs it (its first step and the step that
reaches the refined pose), counts it and, when a marker has reached its refined pose, sends a
STATUSTEXT (at most one a minute). At exit it writes the refined world file, if asked, atomically and
in the format ``map`` writes.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from atlas_onboard.config import WORLD, RefineConfig, WorldConfig
from atlas_onboard.core import covariance
from atlas_onboard.core.ambiguity import AMBIGUITY_THRESHOLD
from atlas_onboard.core.markerdata import MarkerData
from atlas_onboard.core.refine import MapRefiner, Sighting, Update
from atlas_onboard.errors import AtlasError
from atlas_onboard.fsio import write_atomic

_logger = logging.getLogger(__name__)

NS = 1_000_000_000
STEP_NS = NS  # how often refined poses may be applied (each a bounded step)
IMAGE_WAIT_NS = NS // 2  # an image whose last observation never came is used after this long
STATUS_NS = 60 * NS  # at most one STATUSTEXT a minute
LOG_NS = 60 * NS  # a marker's update is logged the first time, then at most once a minute


class LiveRefinement:
    """The node's side of the refinement: images in, the listener's marker poses out (see the module)."""

    def __init__(self, world: WorldConfig, config: RefineConfig, sensors: frozenset[int] | None = None) -> None:
        """``sensors``: the only sensors whose observations are evidence (None: every accepted one)."""
        self.world = world
        self.config = config
        self._sensors = sensors
        markers = {m.id: m for m in world.entity(WORLD).markers}
        self.refiner = MapRefiner(
            {
                mid: (m.T_entity_marker.translation, m.T_entity_marker.rotation.as_matrix())
                for mid, m in markers.items()
            },
            anchors=config.anchors,
        )
        self._world_ids = frozenset(markers)
        self._world_sensors = frozenset(s.id for s in world.entity(WORLD).sensors)
        self._images: dict[tuple[int, int], tuple[int, list[Sighting]]] = {}  # (sensor, stamp) -> (arrival, ...)
        self._next_step_ns = 0
        self._last_status_ns: int | None = None
        self._logged_ns: dict[int, int] = {}
        self._status: list[str] = []
        self.skipped_ambiguous = 0
        self.markers_refined: set[int] = set()

    # --- observations in ------------------------------------------------------------------------------

    def add(self, accepted: Sequence[MarkerData], now_ns: int) -> None:
        """Accepted observations (any order, any images); an image is used once its last one is in."""
        for md in accepted:
            key = (md.sensor_id, md.capture_time_us)
            evidence = self._sensors is None or md.sensor_id in self._sensors
            if evidence and md.marker_id in self._world_ids and md.sensor_id not in self._world_sensors:
                if md.ambiguity_ratio > AMBIGUITY_THRESHOLD:  # its square may be the mirrored one
                    self.skipped_ambiguous += 1
                else:
                    self._images.setdefault(key, (now_ns, []))[1].append(_sighting(md))
            if md.frame_remaining == 0 and key in self._images:  # the image's last observation (any marker)
                self._use(key)

    def _use(self, key: tuple[int, int]) -> None:
        _, sightings = self._images.pop(key)
        if len(sightings) > 1:  # (a joint solve's image: one observation of the whole pattern, no evidence)
            self.refiner.add_image(key[0], key[1], sightings)

    # --- updates out ----------------------------------------------------------------------------------

    def step(self, now_ns: int, listener: object) -> list[Update]:
        """Once a second: use the images left waiting, apply the refined poses due (to ``listener``,
        a :class:`~atlas_onboard.listener.Listener`); returns the updates made."""
        if now_ns < self._next_step_ns:
            return []
        self._next_step_ns = now_ns + STEP_NS
        for key in [k for k, (t, _) in self._images.items() if now_ns - t >= IMAGE_WAIT_NS]:
            self._use(key)
        updates = self.refiner.step()
        for u in updates:
            M = np.eye(4)
            M[:3, :3], M[:3, 3] = u.R_world_marker, u.p_world_marker_m
            listener.set_marker_pose(u.marker_id, M, u.cov)  # type: ignore[attr-defined]
            self.markers_refined.add(u.marker_id)
            self._say(u, now_ns)
        return updates

    def _say(self, u: Update, now_ns: int) -> None:
        """Log a marker's first step and the step that reaches its estimate (others at most once a
        minute per marker); a STATUSTEXT when one reaches it, at most one a minute."""
        mid = u.marker_id
        dx, dy, dz = self.refiner.file_offset_m(mid)
        est = u.estimate
        last = self._logged_ns.get(mid)
        if last is None or u.reached or now_ns - last >= LOG_NS:
            self._logged_ns[mid] = now_ns
            _logger.warning(
                "world marker %d %s: moved %.1f mm (%.2f deg) towards what %d views show; now %+.3f %+.3f %+.3f m"
                " from the world file, 1-sigma %.1f mm, %.2f deg (%d evidence items, %d outliers)",
                mid, "refined" if u.reached else "being refined", u.step_m * 1000, u.step_deg, est.views, dx, dy, dz,
                est.max_sigma_m * 1000, est.max_sigma_deg, est.items, est.outliers,
            )  # fmt: skip
        if u.reached and (self._last_status_ns is None or now_ns - self._last_status_ns >= STATUS_NS):
            self._last_status_ns = now_ns
            text = f"atlas: marker {mid} refined {round(dx * 100):+d} {round(dy * 100):+d} {round(dz * 100):+d} cm"
            self._status.append(text[:50])

    def take_status(self) -> list[str]:
        """STATUSTEXT lines to send (at most one a minute), emptied by the call."""
        out, self._status = self._status, []
        return out

    def counters(self) -> dict[str, int]:
        c = self.refiner.counters
        out = {f"refine_{k}": v for k, v in c.items()}
        out["refine_skipped_ambiguous"] = self.skipped_ambiguous
        out["refine_markers_refined"] = len(self.markers_refined)
        return out

    # --- the refined world file -----------------------------------------------------------------------

    def write(self, path: Path) -> None:
        """The world file with every refined marker's pose and 1-sigma (the others as they were), written
        atomically in the format ``map`` writes; AtlasError (one line) when it cannot be written."""
        from atlas_onboard.mapping.output import refined_world_text
        from atlas_onboard.mapping.report import MarkerReport

        if self.world.source is None:
            raise AtlasError(f"{path}: the running world file has no source file to rewrite")
        sizes = {m.id: m.size_m for m in self.world.entity(WORLD).markers}
        reports = {}
        for mid in sorted(self._world_ids):
            est = self.refiner.estimate(mid)
            views = est.views if est is not None else 0
            if mid in self.config.anchors:
                reports[mid] = MarkerReport(mid, sizes[mid], views, "anchor")
            elif mid in self.refiner.moved:
                p, R, cov = self.refiner.pose(mid)
                M = np.eye(4)
                M[:3, :3], M[:3, 3] = R, p
                sigma_m = np.sqrt(np.diag(cov)[:3])
                sigma_deg = np.degrees(np.sqrt(np.diag(R @ cov[3:, 3:] @ R.T)))
                reports[mid] = MarkerReport(mid, sizes[mid], views, "refined", M, _triple(sigma_m), _triple(sigma_deg))
            else:
                why = self.refiner.verdict(est) if est is not None else "no evidence"
                reports[mid] = MarkerReport(mid, sizes[mid], views, "kept", detail=f"not refined: {why}")
        text = refined_world_text(self.world, reports, "world markers refined live by atlas-onboard run (refine)")
        try:
            write_atomic(Path(path), text)
        except OSError as exc:
            raise AtlasError(f"{path}: cannot write the refined map: {exc.strerror}") from None


def _triple(v: np.ndarray) -> tuple[float, float, float]:
    return float(v[0]), float(v[1]), float(v[2])


def _sighting(md: MarkerData) -> Sighting:
    """A world marker's pose in its sensor and that pose's covariance (modelled from sigma when the
    record carries none, as the listener does)."""
    p = np.array(md.p_sensor_marker_m, dtype=float)
    w, x, y, z = md.q_sensor_marker_wxyz
    n = math.sqrt(w * w + x * x + y * y + z * z)
    R = Rotation.from_quat([x / n, y / n, z / n, w / n]).as_matrix()
    cov = md.covariance_matrix()
    if cov is None:
        cov = covariance.diagonal(
            md.sigma_m, float(covariance.attitude_sigma_rad(md.sigma_m, float(np.linalg.norm(p))))
        )
    return Sighting(md.marker_id, p, R, cov)
