"""The simulated world at time t: ground truth of every entity, camera intrinsics, and which marker
each camera can see (for rendering order and for the expected availability of each entity).

A marker is in view when the detector can use it: every corner, where the camera images it (a rolling
shutter's at its own row's instant), at least the detector's ``BORDER_MARGIN_PX`` inside the image (nearer,
the corner refit's search across each edge would reach past the image, and the detector refuses it)."""

from __future__ import annotations

from collections import deque
from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import RigidTransform, Rotation

from atlas_onboard.config import WORLD, MarkerConfig, SensorConfig, WorldConfig
from atlas_onboard.config.settings import READOUT_BOTTOM_UP
from atlas_onboard.core.shutter import RowClock
from atlas_onboard.detector.search import BORDER_MARGIN_PX
from atlas_onboard.sim.scenario import Optics, Scenario

if TYPE_CHECKING:
    from atlas_onboard.detector.calibration import Calibration

FRESH_S = 0.2  # PX4's EKF2 does not start fusing external vision across a gap longer than this
FRESH_STEP_S = 0.005


MIN_SIDE_PX = 16.0  # a tag36h11 needs about 2 px per cell (8 cells across) to decode
MAX_VIEW_ANGLE_DEG = 70.0
ROW_PASSES = 3  # turns to find a rolling-shutter corner's row and that row's instant (SimWorld._imaged)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics with OpenCV's pixel-centre convention, plus distortion (k1 k2 p1 p2 k3)."""

    width_px: int
    height_px: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float]

    @classmethod
    def from_fov(cls, width_px: int, height_px: int, optics: Optics) -> Intrinsics:
        f = (width_px / 2.0) / np.tan(np.radians(optics.hfov_deg) / 2.0)
        return cls(width_px, height_px, f, f, (width_px - 1) / 2.0, (height_px - 1) / 2.0, optics.distortion)

    @property
    def camera_matrix(self) -> NDArray[np.float64]:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def calibration(self) -> Calibration:
        """The camera's calibration, as the simulator writes it for its nodes: exact, its residual the
        rendered lens's (:data:`~atlas_onboard.detector.render.LENS_RESIDUAL_PX`)."""
        from atlas_onboard.detector.calibration import Calibration
        from atlas_onboard.detector.render import LENS_RESIDUAL_PX

        dist = np.array(self.distortion)
        return Calibration(self.width_px, self.height_px, self.camera_matrix, dist, False, LENS_RESIDUAL_PX)

    def project(self, p_cam: NDArray[np.float64]) -> NDArray[np.float64]:
        """Pixel coordinates (N, 2) of points (N, 3) in the optical frame, with distortion."""
        x = p_cam[:, 0] / p_cam[:, 2]
        y = p_cam[:, 1] / p_cam[:, 2]
        k1, k2, p1, p2, k3 = self.distortion
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2**3
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=1)


def marker_corners(size_m: float) -> NDArray[np.float64]:
    """Corners in the marker frame, OpenCV order: top-left, top-right, bottom-right, bottom-left."""
    h = size_m / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


@dataclass(frozen=True)
class Sighting:
    """A marker a camera can see at some instant: truth for rendering and for scoring detections."""

    sensor: SensorConfig
    marker: MarkerConfig
    M_sensor_marker: NDArray[np.float64]  # (4, 4) rigid, at the frame's stamp
    corners_px: NDArray[np.float64]  # (4, 2) where the camera images them (rolling shutter: each at its row's instant)
    distance_m: float

    @property
    def T_sensor_marker(self) -> RigidTransform:
        # A product of rigid matrices is rigid to rounding: no re-orthonormalization needed.
        return RigidTransform(self.M_sensor_marker, normalize=False, copy=False)


class SimWorld:
    """Ground truth for a scenario; time ``t`` is seconds since the start of the run."""

    def __init__(self, scenario: Scenario, world: WorldConfig | None = None) -> None:
        self.scenario = scenario
        self.world = world if world is not None else scenario.world()
        self.cameras: dict[int, tuple[SensorConfig, Intrinsics]] = {}
        self._visibility: dict[float, tuple[NDArray[np.float64], dict[str, NDArray[np.bool_]]]] = {}
        for ent in self.world.entities:
            for s in ent.sensors:
                if s.camera is not None and s.camera.width_px > 0:
                    intr = Intrinsics.from_fov(
                        s.camera.width_px, s.camera.height_px, scenario.optics_of(ent.name, s.name)
                    )
                    self.cameras[s.id] = (s, intr)
        # When each row is exposed, relative to the frame's stamp (the renderer's row times).
        self._row_clocks = {
            sid: RowClock(s.camera.readout_ms / 1000.0, intr.height_px, s.camera.readout_order == READOUT_BOTTOM_UP)
            for sid, (s, intr) in self.cameras.items()
            if s.camera is not None
        }
        # 4x4 matrices of the fixed mountings: sightings are computed with plain matrix products
        # (scipy's RigidTransform costs a few hundred microseconds an operation).
        self._T_entity_sensor = {sid: s.T_entity_sensor.as_matrix() for sid, (s, _) in self.cameras.items()}
        self._markers = [
            (m, m.T_entity_marker.as_matrix(), marker_corners(m.size_m)) for m in self.world.markers.values()
        ]
        # The same, stacked per entity, for a first test of every marker at once (:meth:`sightings`).
        self._marker_stacks = {
            ent: (
                [k for k, (m, _, _) in enumerate(self._markers) if m.entity == ent],
                np.stack([M for m, M, _ in self._markers if m.entity == ent]),
                np.stack([c for m, _, c in self._markers if m.entity == ent]),
            )
            for ent in dict.fromkeys(m.entity for m, _, _ in self._markers)
        }

    def truth(self, t: float, names: Collection[str] | None = None) -> dict[str, RigidTransform]:
        """``T_world_entity`` of every entity at time t (entities without a trajectory sit at the origin);
        of the entities in ``names`` only, when given."""
        identity = RigidTransform.identity()
        out = dict.fromkeys(self.world.entity_names if names is None else names, identity)
        for name, traj in self.scenario.trajectories.items():
            if names is not None and name not in out:
                continue
            p, q = traj.pose(np.array([t]))
            M = np.eye(4)
            M[:3, :3] = Rotation.from_quat(q[0]).as_matrix()
            M[:3, 3] = p[0]
            out[name] = RigidTransform(M, normalize=False, copy=False)  # a rotation matrix already
        return out

    def truth_series(self, name: str, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Positions (N, 3) and quaternions xyzw (N, 4) of one entity at times t."""
        traj = self.scenario.trajectories.get(name)
        if traj is None:
            n = len(t)
            return np.zeros((n, 3)), np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))
        return traj.pose(np.asarray(t, dtype=float))

    def sightings(
        self, sensor_id: int, truth: Mapping[str, RigidTransform | NDArray[np.float64]], t_s: float | None = None
    ) -> list[Sighting]:
        """Markers the camera sees: every corner at least ``BORDER_MARGIN_PX`` inside the image (with a
        rolling shutter and ``t_s`` given, each corner where its own row's instant images it), facing the
        camera, big enough, not hidden by a nearer marker, and none while the scenario's occlusions block
        the camera's view at ``t_s`` (when given). ``truth``: each entity's ``T_world_entity`` (at ``t_s``),
        as a transform or a 4x4 matrix.

        Sorted far to near, the order in which a renderer paints them.
        """
        sensor, intr = self.cameras[sensor_id]
        if t_s is not None and self.scenario.occluded(sensor.entity, sensor.name, t_s):
            return []
        M_world_sensor = _matrix(truth[sensor.entity]) @ self._T_entity_sensor[sensor_id]
        M_sensor_world = _rigid_inverse(M_world_sensor)
        M_sensor_entity: dict[str, NDArray[np.float64]] = {}
        candidates = []
        rolling = t_s is not None and self._row_clocks[sensor_id].readout_s > 0
        for k in self._maybe_in_view(sensor_id, sensor.entity, M_sensor_world, truth, t_s if rolling else None):
            m, M_entity_marker, corners_m = self._markers[k]
            if m.entity not in M_sensor_entity:
                M_sensor_entity[m.entity] = M_sensor_world @ _matrix(truth[m.entity])
            M_sm = M_sensor_entity[m.entity] @ M_entity_marker
            R, p = M_sm[:3, :3], M_sm[:3, 3]
            corners = corners_m @ R.T + p
            if np.any(corners[:, 2] < 0.05):
                continue
            distance = float(np.linalg.norm(p))
            to_camera = -p / distance
            normal = R[:, 2]  # the marker's z axis (out of its face) in the sensor frame
            if np.degrees(np.arccos(np.clip(normal @ to_camera, -1, 1))) > MAX_VIEW_ANGLE_DEG:
                continue
            px = intr.project(corners)
            if rolling:
                assert t_s is not None
                imaged = self._imaged(sensor_id, m, M_entity_marker, corners_m, truth, t_s, px)
                if imaged is None:
                    continue
                px = imaged
            m_ = BORDER_MARGIN_PX
            if np.any(px[:, 0] < m_) or np.any(px[:, 0] > intr.width_px - 1 - m_):
                continue
            if np.any(px[:, 1] < m_) or np.any(px[:, 1] > intr.height_px - 1 - m_):
                continue
            if np.min(np.linalg.norm(px - np.roll(px, -1, axis=0), axis=1)) < MIN_SIDE_PX:
                continue
            candidates.append(Sighting(sensor, m, M_sm, px, distance))
        candidates.sort(key=lambda s: -s.distance_m)
        visible = []
        for i, s in enumerate(candidates):
            nearer = candidates[i + 1 :]
            if any(_inside(c, n.corners_px) for n in nearer for c in s.corners_px):
                continue
            visible.append(s)
        return visible

    def _maybe_in_view(
        self,
        sensor_id: int,
        own: str,
        M_sensor_world: NDArray[np.float64],
        truth: Mapping[str, RigidTransform | NDArray[np.float64]],
        rolling_t_s: float | None = None,
    ) -> list[int]:
        """Indices (into ``_markers``, in order) of the markers of other entities whose corners all
        lie in front of the camera and inside its image, up to a pixel: every marker at once, so that
        :meth:`sightings` tests one by one only the few that may be seen. The margin covers the
        rounding of products taken in another order there: this test never drops a marker that
        :meth:`sightings` would keep. A rolling shutter's frame at ``rolling_t_s``: each corner anywhere
        between where the first row's and the last row's instants image it (over one readout the image
        moves along a line to well under the pixel of margin)."""
        intr, sensors, times = self.cameras[sensor_id][1], [M_sensor_world], [0.0]
        if rolling_t_s is not None:
            half = self._row_clocks[sensor_id].readout_s / 2.0
            times = [rolling_t_s, rolling_t_s - half, rolling_t_s + half]
            sensor = self.cameras[sensor_id][0]
            M_ws = self._world_poses(sensor.entity, np.array(times[1:]), truth) @ self._T_entity_sensor[sensor_id]
            sensors += [_rigid_inverse(M) for M in M_ws]
        keep: list[int] = []
        m_ = BORDER_MARGIN_PX - 1.0
        for ent, (index, M_em, corners_m) in self._marker_stacks.items():
            if ent == own:
                continue
            entity = [_matrix(truth[ent])]
            if rolling_t_s is not None:
                entity += list(self._world_poses(ent, np.array(times[1:]), truth))
            pxs = []
            for k, (M_sw, M_we) in enumerate(zip(sensors, entity, strict=True)):
                M = (M_sw @ M_we) @ M_em  # (k, 4, 4)
                corners = corners_m @ np.swapaxes(M[:, :3, :3], 1, 2) + M[:, None, :3, 3]  # (k, 4, 3)
                z = corners[..., 2]
                if k == 0:
                    ok = np.all(z >= 0.05 - 1e-9, axis=1)
                pxs.append(intr.project(np.where(z[..., None] > 0.01, corners, 1.0).reshape(-1, 3)).reshape(-1, 4, 2))
            lo, hi = np.min(pxs, axis=0), np.max(pxs, axis=0)
            ok &= np.all((hi[..., 0] >= m_) & (lo[..., 0] <= intr.width_px - 1 - m_), axis=1)
            ok &= np.all((hi[..., 1] >= m_) & (lo[..., 1] <= intr.height_px - 1 - m_), axis=1)
            keep += [i for i, good in zip(index, ok, strict=True) if good]
        return sorted(keep)

    def _world_poses(
        self, name: str, times: NDArray[np.float64], truth: Mapping[str, RigidTransform | NDArray[np.float64]]
    ) -> NDArray[np.float64]:
        """``T_world_entity`` (len(times), 4, 4) of ``name`` at ``times`` (s): its trajectory's, or its pose in
        ``truth`` (an entity without a trajectory stays where it is)."""
        traj = self.scenario.trajectories.get(name)
        if traj is None:
            return np.tile(_matrix(truth[name]), (len(times), 1, 1))
        p, q = traj.pose(times)
        M = np.tile(np.eye(4), (len(times), 1, 1))
        M[:, :3, :3] = Rotation.from_quat(q).as_matrix()
        M[:, :3, 3] = p
        return M

    def _imaged(self, sensor_id: int, marker: MarkerConfig, M_entity_marker: NDArray[np.float64],
                corners_m: NDArray[np.float64], truth: Mapping[str, RigidTransform | NDArray[np.float64]],
                t_s: float, px: NDArray[np.float64]) -> NDArray[np.float64] | None:  # fmt: skip
        """Where a rolling-shutter camera images a marker's corners ``corners_m`` (marker frame) in its frame
        stamped ``t_s``, each with the camera's and the marker's poses at the instant of the row it falls
        on; ``px``: where the stamp's poses image them. The row and its instant are found by turns, each
        shrinking the row's error by the image's vertical speed times the readout per row (hundredths).
        None when a corner is then behind the camera."""
        sensor, intr = self.cameras[sensor_id]
        clock = self._row_clocks[sensor_id]
        for _ in range(ROW_PASSES):
            times = t_s + clock.dt_s(np.clip(px[:, 1], 0.0, intr.height_px - 1.0))
            M_ws = self._world_poses(sensor.entity, times, truth) @ self._T_entity_sensor[sensor_id]
            M_sm = np.linalg.inv(M_ws) @ self._world_poses(marker.entity, times, truth) @ M_entity_marker
            corners = np.einsum("kij,kj->ki", M_sm[:, :3, :3], corners_m) + M_sm[:, :3, 3]
            if np.any(corners[:, 2] < 0.05):
                return None
            px = intr.project(corners)
        return px

    def observed_edges(
        self, t: float, truth: Mapping[str, RigidTransform | NDArray[np.float64]] | None = None
    ) -> list[tuple[str, str]]:
        """(observer entity, observed entity) pairs a camera can see at time t (mocap included);
        ``truth`` (as :meth:`sightings` takes it) saves computing the poses at t again."""
        truth = self.truth(t) if truth is None else truth
        edges = [(s.sensor.entity, s.marker.entity) for sid in self.cameras for s in self.sightings(sid, truth, t)]
        if self.scenario.mocap is not None:
            edges += [(WORLD, name) for name in self.scenario.drones]
        return edges

    def frame_period_s(self) -> float:
        """The shortest period of the scenario's sensors (cameras and mocap), seconds."""
        rates = [s.camera.fps for s, _ in self.cameras.values() if s.camera is not None and s.camera.fps > 0]
        if self.scenario.mocap is not None:
            rates.append(self.scenario.mocap.rate_hz)
        return 1.0 / max(rates, default=30.0)

    def expected_availability(self, t0_s: float, t1_s: float, fresh_s: float = FRESH_S) -> dict[str, float]:
        """Per entity, the availability (:func:`fresh_share`) of an ideal node that publishes at every
        frame time (multiples of :meth:`frame_period_s`) at which the entity has a path of visible
        markers to the world, with no delay: what :func:`atlas_onboard.sim.report.score` compares
        the real one against."""
        frames, reached = self._frame_visibility(t1_s)
        return {name: fresh_share(frames[seen], t0_s, t1_s, fresh_s) for name, seen in reached.items()}

    def visible_frames(self, name: str, t1_s: float) -> NDArray[np.float64]:
        """Frame times in [0, t1] at which ``name`` has a path of visible markers to the world."""
        frames, reached = self._frame_visibility(t1_s)
        return frames[reached[name]] if name in reached else np.zeros(0)

    def _frame_visibility(self, t1_s: float) -> tuple[NDArray[np.float64], dict[str, NDArray[np.bool_]]]:
        """Frame times in [0, t1] and, per entity, whether it had a path to the world at each (cached)."""
        if t1_s not in self._visibility:
            step = self.frame_period_s()
            frames = np.arange(0, np.floor(t1_s / step + 1e-9) + 1) * step
            names = [n for n in self.world.entity_names if n != WORLD]
            reached = {n: np.zeros(len(frames), dtype=bool) for n in names}
            # Every trajectory evaluated at all frame times at once, as 4x4 matrices.
            series = {}
            for name, traj in self.scenario.trajectories.items():
                p, q = traj.pose(frames)
                M = np.tile(np.eye(4), (len(frames), 1, 1))
                M[:, :3, :3] = Rotation.from_quat(q).as_matrix()
                M[:, :3, 3] = p
                series[name] = M
            eye = np.eye(4)
            for i, t in enumerate(frames):
                truth = {n: series[n][i] if n in series else eye for n in self.world.entity_names}
                for name in _reachable(self.observed_edges(float(t), truth)) - {WORLD}:
                    reached[name][i] = True
            self._visibility[t1_s] = (frames, reached)
        return self._visibility[t1_s]


def fresh_share(times_s: NDArray[np.float64], t0_s: float, t1_s: float, fresh_s: float = FRESH_S) -> float:
    """Availability: the share of [t0, t1] (sampled every 5 ms) at which the newest of ``times_s``
    (pose arrivals) is at most ``fresh_s`` old, i.e. the share of time the receiver holds a pose fresh
    enough to use. PX4 stops starting vision fusion across gaps over 200 ms and ArduPilot marks the
    source unhealthy after 300 ms: the default is the stricter of the two."""
    grid = np.arange(t0_s, t1_s, FRESH_STEP_S)
    t = np.sort(np.asarray(times_s, dtype=float))
    if len(grid) == 0 or len(t) == 0:
        return 0.0
    k = np.searchsorted(t, grid, side="right") - 1  # the newest arrival at or before each instant
    newest = np.where(k >= 0, t[np.maximum(k, 0)], -np.inf)
    return float(np.mean(grid - newest <= fresh_s))


def _matrix(T: RigidTransform | NDArray[np.float64]) -> NDArray[np.float64]:
    return T if isinstance(T, np.ndarray) else T.as_matrix()


def _rigid_inverse(M: NDArray[np.float64]) -> NDArray[np.float64]:
    """The inverse of a 4x4 rigid transform matrix."""
    out = np.eye(4)
    R_t = M[:3, :3].T
    out[:3, :3] = R_t
    out[:3, 3] = -R_t @ M[:3, 3]
    return out


def _reachable(edges: list[tuple[str, str]]) -> set[str]:
    adj: dict[str, set[str]] = {}
    for a, b in edges:
        adj.setdefault(a, set()).add(b)
        adj.setdefault(b, set()).add(a)
    seen = {WORLD}
    queue = deque([WORLD])
    while queue:
        for n in adj.get(queue.popleft(), ()):
            if n not in seen:
                seen.add(n)
                queue.append(n)
    return seen


def _inside(point: NDArray[np.float64], quad: NDArray[np.float64]) -> bool:
    """True if a pixel lies inside a convex quadrilateral (either winding)."""
    signs = []
    for i in range(4):
        a, b = quad[i], quad[(i + 1) % 4]
        signs.append(np.sign((b[0] - a[0]) * (point[1] - a[1]) - (b[1] - a[1]) * (point[0] - a[0])))
    return all(s >= 0 for s in signs) or all(s <= 0 for s in signs)
