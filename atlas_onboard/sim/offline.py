"""A scenario's estimator, stage by stage, without processes or clocks: how honest each covariance is.

Every camera's frames are rendered from ground truth (as the simulator's cameras render them) and
run through the real detector; each frame's observations go to the listener and a graph of every
drone's own (its cameras the anchor) at their capture time, with no transport delay, and the graph
is evaluated then. What the machine's load does to a live run (late and stale observations) is left
out: this measures the estimator's own consistency, per stage:

- ``detection``: each detection's pose ``T_sensor_marker`` against truth, with the detector's 6x6;
- ``output``: each drone's fused pose ``T_world_drone`` against truth at its capture time, with the
  6x6 the autopilot receives (NED/FRD, the 21 floats of the MAVLink message rounded to float32 and
  read back), positive definite or counted as not.

The errors follow :mod:`atlas_onboard.core.covariance`'s convention ``[dp, dtheta]``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from atlas_onboard.config import FusionConfig, WorldConfig
from atlas_onboard.core.markerdata import upper_to_matrix
from atlas_onboard.listener import Listener
from atlas_onboard.mavlink.covariance import covariance_21_from_enu_flu
from atlas_onboard.node.setup import make_graph
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.world import SimWorld, fresh_share


@dataclass
class StageErrors:
    """Errors (N, 6) of one stage's estimates against truth and their covariances (N, 6, 6)."""

    errors: list[NDArray[np.float64]] = field(default_factory=list)
    covariances: list[NDArray[np.float64]] = field(default_factory=list)
    not_positive_definite: int = 0
    times_s: list[float] = field(default_factory=list)  # each estimate's capture time

    def add(self, e: NDArray[np.float64], C: NDArray[np.float64], t_s: float = float("nan")) -> None:
        if np.linalg.eigvalsh(C).min() <= 0.0:
            self.not_positive_definite += 1
            return
        self.errors.append(np.asarray(e, dtype=float))
        self.covariances.append(np.asarray(C, dtype=float))
        self.times_s.append(t_s)

    def availability(self, t0_s: float, t1_s: float) -> float:
        """The share of [t0, t1] at which the newest estimate was fresh (:func:`fresh_share`), each
        estimate published at its capture time: what the fusion gives before any load delays it."""
        return fresh_share(np.array(self.times_s), t0_s, t1_s)

    def attitude_rmse_deg(self) -> float:
        return float(np.degrees(np.sqrt(np.mean([e[3:] @ e[3:] for e in self.errors]))))

    def nees(self, dims: slice = slice(0, 6)) -> NDArray[np.float64]:
        """NEES of every estimate over the error components ``dims``."""
        return np.array([e[dims] @ np.linalg.solve(C[dims, dims], e[dims]) for e, C in self._pairs()])

    def within_3_sigma(self) -> NDArray[np.float64]:
        """Share of estimates within 3 standard deviations, per component (6,)."""
        return np.mean([np.abs(e) <= 3.0 * np.sqrt(np.diag(C)) for e, C in self._pairs()], axis=0)

    def rmse_m(self) -> float:
        return float(np.sqrt(np.mean([e[:3] @ e[:3] for e in self.errors])))

    def _pairs(self) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
        return list(zip(self.errors, self.covariances, strict=True))


def pose_error(
    p_est: NDArray[np.float64], R_est: Rotation, p_true: NDArray[np.float64], R_true: Rotation
) -> NDArray[np.float64]:
    """``[p_true - p_est, Log(R_est^-1 R_true)]``: the error the covariances describe."""
    return np.concatenate([np.asarray(p_true) - np.asarray(p_est), (R_est.inv() * R_true).as_rotvec()])


def published_covariance(cov_enu_flu: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 6x6 (NED/FRD) an autopilot reads from the message: the 21 floats as float32."""
    c21 = np.asarray(covariance_21_from_enu_flu(cov_enu_flu), dtype=np.float32).astype(float)
    return upper_to_matrix(c21)


_J_ENU_NED = np.zeros((6, 6))  # ENU/FLU errors into NED/FRD: x <-> y, z and the body y, z flip
_J_ENU_NED[0, 1] = _J_ENU_NED[1, 0] = 1.0
_J_ENU_NED[2, 2] = -1.0
_J_ENU_NED[3, 3] = 1.0
_J_ENU_NED[4, 4] = _J_ENU_NED[5, 5] = -1.0


def run(
    scenario_name: str, frames: int, seed: int = 0, world: WorldConfig | None = None, start_s: float = 1.0
) -> tuple[StageErrors, dict[str, StageErrors]]:
    """``frames`` frames of every camera of the scenario from ``start_s``: the detection stage's errors
    and each drone's output errors (see the module's docstring)."""
    scenario = scenarios.get(scenario_name)
    world = world if world is not None else scenario.world()
    detections, outputs = run_fusions(scenario_name, frames, {"": world.fusion}, seed, world, start_s)
    return detections, outputs[""]


def run_fusions(
    scenario_name: str,
    frames: int,
    fusions: dict[str, FusionConfig],
    seed: int = 0,
    world: WorldConfig | None = None,
    start_s: float = 1.0,
) -> tuple[StageErrors, dict[str, dict[str, StageErrors]]]:
    """As :func:`run`, with each drone's listener and graph run once per fusion setting on the same
    detections: each setting's output errors, by its key in ``fusions``, then by drone."""
    from atlas_onboard.detector.pipeline import Detector
    from atlas_onboard.sim.camera import FrameRenderer, camera_seed

    scenario = scenarios.get(scenario_name)
    world = world if world is not None else scenario.world()
    sim = SimWorld(scenario, world)
    cams = []
    for sid, (sensor, intr) in sorted(sim.cameras.items()):
        cal = intr.calibration()
        renderer = FrameRenderer(scenario, world, sensor, camera_seed(seed, sid))
        cams.append((sensor, renderer, Detector(sensor, world, cal, decimate=2.0)))
    nodes = {}
    for key, fusion in fusions.items():
        variant = dataclasses.replace(world, fusion=fusion)
        for drone in scenario.drones:
            graph = make_graph(variant, drone)
            nodes[key, drone] = (graph, Listener(variant, graph))
    detections = StageErrors()
    outputs = {key: {d: StageErrors() for d in scenario.drones} for key in fusions}
    fps = min(r.fps for _, r, _ in cams)
    first = round(start_s * fps)
    for j in range(first, first + frames):
        t = j / fps
        truth = sim.truth(t)
        now_ns = round(t * 1e9)
        mds = []
        for sensor, renderer, det in cams:
            if scenario.occluded(sensor.entity, sensor.name, t):
                continue
            index = round(t * renderer.fps)
            for md in det.detect(renderer(index), round(t * 1e6)):
                mds.append(md)
                if not md.covariance or md.ambiguity_ratio > 0.5:
                    continue
                marker = world.markers[md.marker_id]
                T_true = (truth[sensor.entity] * sensor.T_entity_sensor).inv() * (
                    truth[marker.entity] * marker.T_entity_marker
                )
                w, x, y, z = md.q_sensor_marker_wxyz
                e = pose_error(md.p_sensor_marker_m, Rotation.from_quat([x, y, z, w]), T_true.translation,
                               T_true.rotation)  # fmt: skip
                detections.add(e, upper_to_matrix(np.array(md.covariance)))
        for (key, drone), (graph, listener) in nodes.items():
            listener.accept_many([(md, now_ns) for md in mds])
            result = graph.evaluate(now_ns)
            listener.set_estimates(result.poses)
            est = result.poses.get(drone)
            if est is None or est.capture_time_us != round(t * 1e6) or est.covariance is None:
                continue  # not seen in this frame: nothing new to send
            T = truth[drone]
            e = pose_error(est.p_world_m, Rotation.from_quat(est.q_world_xyzw), T.translation, T.rotation)
            outputs[key][drone].add(_J_ENU_NED @ e, published_covariance(est.covariance), t)
    return detections, outputs
