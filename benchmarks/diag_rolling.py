"""Which part of the rolling-shutter model is wrong: the rolling scene's camera flown at a constant motion.

The rolling scene's camera, room and tags (``rolling``: 25 ms readout, and its global-shutter twin
``rolling-global``), the drone held at a pose of that flight and then moved at one constant motion only:
still, turning (30 deg/s about one body axis), or travelling (0.6 m/s along one world axis). The frames
are rendered by the simulator (rows at their own instants) and run through the real detector, given the
autopilot's exact body rate, singles (``joint`` off) and joint solves. Per motion and shutter: the
camera's world position from each observation (eq. 1) against the truth at the stamp: RMSE, median,
max, the worst axis's share within 3 sigma, and the median sigma. ``oracle v``: the detector's velocity
(from its own recent poses) replaced by the true one, to tell the velocity estimate from the model.

    python benchmarks/diag_rolling.py [--frames 12] [--starts 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from atlas_onboard.core import covariance
from atlas_onboard.core.markerdata import upper_to_matrix
from atlas_onboard.core.shutter import GYRO_SIGMA_RAD_S, BodyRate, BodyVelocity, CameraMotion, RateHistory
from atlas_onboard.detector.motion import CameraMotionModel
from atlas_onboard.sim import scenarios
from atlas_onboard.sim.autopilot import SimAutopilot
from atlas_onboard.sim.camera import FrameRenderer, camera_seed
from atlas_onboard.sim.gyro import Gyro, GyroNoise
from atlas_onboard.sim.world import SimWorld

WARMUP = 4  # frames before scoring: the detector's velocity history fills
RATE = np.radians(30.0)
SPEED = 0.6
MOTIONS = {
    "still": (np.zeros(3), np.zeros(3)),
    "roll": (np.array([RATE, 0.0, 0.0]), np.zeros(3)),
    "pitch": (np.array([0.0, RATE, 0.0]), np.zeros(3)),
    "yaw": (np.array([0.0, 0.0, RATE]), np.zeros(3)),
    "east": (np.zeros(3), np.array([SPEED, 0.0, 0.0])),
    "north": (np.zeros(3), np.array([0.0, SPEED, 0.0])),
    "up": (np.zeros(3), np.array([0.0, 0.0, SPEED / 2])),
}


@dataclass(frozen=True)
class ConstantMotion:
    """A body at ``p0``, ``R0`` at t = 0, turning at ``w_body`` (FLU, rad/s) and moving at ``v_world`` (m/s)."""

    p0: NDArray[np.float64]
    R0: Rotation
    w_body: NDArray[np.float64]
    v_world: NDArray[np.float64]

    def pose(self, t: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        p = self.p0[None, :] + t[:, None] * self.v_world[None, :]
        q = (self.R0 * Rotation.from_rotvec(t[:, None] * self.w_body[None, :])).as_quat()
        return p, q

    def velocity(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.tile(self.v_world, (len(np.atleast_1d(t)), 1))

    def body_rates(self, t: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.tile(self.w_body, (len(np.atleast_1d(t)), 1))


class _Oracle(CameraMotionModel):
    """The detector's motion model with the true velocity (camera frame) in place of its estimate."""

    v_cam: NDArray[np.float64] = np.zeros(3)

    def at(self, t_us: int, rate: BodyRate | None, velocity: BodyVelocity | None = None) -> CameraMotion:
        m = super().at(t_us, rate, velocity)
        return dataclasses.replace(m, velocity=self.v_cam, velocity_cov=1e-6 * np.eye(3), velocity_known=True)


def run(
    scenario: scenarios.Scenario, motion: ConstantMotion, frames: int, joint: bool, oracle: bool
) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
    """(error, 3x3 covariance) of the camera's world position of every scored observation."""
    from atlas_onboard.detector.pipeline import Detector

    sc = replace(scenario, trajectories={"drone": motion})
    world = sc.world()
    sim = SimWorld(sc, world)
    (sid, (sensor, intr)), *_ = sorted(sim.cameras.items())
    renderer = FrameRenderer(sc, world, sensor, camera_seed(0, sid))
    det = Detector(sensor, world, intr.calibration(), decimate=2.0, joint=joint)
    model = _Oracle(sensor.camera, sensor.T_entity_sensor, intr.height_px)
    if oracle:
        det.motion_model = model
    out = []
    for i in range(frames):
        t = i / renderer.fps
        img = renderer(i)
        rate = BodyRate(motion.w_body.copy(), GYRO_SIGMA_RAD_S**2 * np.eye(3))
        if oracle:
            R_wc = (sim.truth(t)[sensor.entity] * sensor.T_entity_sensor).rotation
            model.v_cam = R_wc.inv().apply(motion.v_world)
        mds = det.detect(img, round(t * 1e6), None, rate)
        if i < WARMUP:
            continue
        out.extend(score(world, sim, sensor, t, mds))
    return out


def scene(frames: int, start_s: float, stride: int) -> None:
    """The rolling flight itself: each shutter's frames from ``start_s``, the detector given no rate, the
    true body rate, or the true rate and velocity (oracle v); singles and joint."""
    from atlas_onboard.detector.pipeline import Detector

    print(f"the rolling flight, {frames} frames from {start_s:g} s (scored every {stride})")
    head = ("rates", "mode", "shutter", "n", "RMSE mm", "med mm", "max mm", "w3 worst", "sigma mm")
    print("{:>7} {:>7} {:>8} {:>4} {:>8} {:>7} {:>7} {:>8} {:>8}".format(*head))
    for shutter in ("rolling", "rolling-global"):
        sc = scenarios.get(shutter)
        world = sc.world()
        sim = SimWorld(sc, world)
        traj = sc.trajectories["drone"]
        (sid, (sensor, intr)), *_ = sorted(sim.cameras.items())
        renderer = FrameRenderer(sc, world, sensor, camera_seed(0, sid))
        first = round(start_s * renderer.fps)
        images = [renderer(i) for i in range(first, first + frames)]
        history = RateHistory()
        hz, delay = SimAutopilot.attitude_hz, SimAutopilot.attitude_delay_s
        gyro = Gyro(GyroNoise(), 17)
        sample_times = np.arange(first / renderer.fps - 1.0, (first + frames) / renderer.fps + 1.0, 1.0 / hz)
        for rates in ("none", "node", "true", "oracle"):
            for joint in (False, True):
                det = Detector(sensor, world, intr.calibration(), decimate=2.0, joint=joint)
                model = _Oracle(sensor.camera, sensor.T_entity_sensor, intr.height_px)
                if rates == "oracle":
                    det.motion_model = model
                rows = []
                for k, img in enumerate(images):
                    t = (first + k) / renderer.fps
                    w = traj.body_rates(np.array([t]))[0]
                    rate = None if rates == "none" else BodyRate(w, GYRO_SIGMA_RAD_S**2 * np.eye(3))
                    if rates == "node":  # as the live node holds them: 25 Hz, sent 15 ms late, the newest
                        for ts in sample_times[(sample_times + delay <= t) & (sample_times + delay > t - 0.2)]:
                            w_ts = gyro.read(ts, traj.body_rates(np.array([ts]))[0], hz)
                            history.add(round((ts + delay) * 1e6), w_ts)
                        rate = history.rate_at(round(t * 1e6))
                    R_wc = (sim.truth(t)[sensor.entity] * sensor.T_entity_sensor).rotation
                    model.v_cam = R_wc.inv().apply(traj.velocity(np.array([t]))[0])
                    mds = det.detect(img, round(t * 1e6), None, rate)
                    if k < WARMUP or k % stride:
                        continue
                    rows += score(world, sim, sensor, t, mds)
                _print(rates, "joint" if joint else "single", shutter, rows)


def score(world, sim, sensor, t, mds):
    true_cam = (sim.truth(t)[sensor.entity] * sensor.T_entity_sensor).translation
    out = []
    for md in mds:
        if not md.covariance or md.ambiguity_ratio > 0.5:
            continue
        T_wm = world.markers[md.marker_id].T_entity_marker
        w, x, y, z = md.q_sensor_marker_wxyz
        R = Rotation.from_quat([x, y, z, w]).as_matrix()
        p = np.array(md.p_sensor_marker_m)
        p_world_cam = T_wm.apply(-R.T @ p)
        Ji = covariance.inverse_jacobian(p, R)
        R_wm = T_wm.rotation.as_matrix()
        C = R_wm @ covariance.transform(Ji, upper_to_matrix(np.array(md.covariance)))[:3, :3] @ R_wm.T
        out.append((p_world_cam - true_cam, C))
    return out


def _print(name: str, mode: str, shutter: str, rows: list) -> float:
    if not rows:
        print(f"{name:>7} {mode:>7} {shutter[:8]:>8}    0")
        return float("nan")
    e = np.array([r[0] for r in rows]) * 1e3
    s = np.array([np.sqrt(np.diag(r[1])) for r in rows]) * 1e3
    norm = np.linalg.norm(e, axis=1)
    w3 = float(np.mean(np.abs(e) <= 3 * s, axis=0).min())
    rmse = float(np.sqrt(np.mean(norm**2)))
    print(
        f"{name:>7} {mode:>7} {shutter[:8]:>8} {len(e):>4} {rmse:>8.2f} {np.median(norm):>7.2f}"
        f" {norm.max():>7.2f} {w3:>8.3f} {np.median(np.linalg.norm(s, axis=1)):>8.2f}"
    )
    return rmse


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--starts", type=int, default=3)
    ap.add_argument("--motions", default=",".join(MOTIONS))
    ap.add_argument("--modes", default="single,joint,oracle")
    ap.add_argument("--scene", type=int, default=0, help="frames of the rolling flight itself (0: not run)")
    ap.add_argument("--scene-start", type=float, default=4.0)
    ap.add_argument("--scene-stride", type=int, default=1)
    args = ap.parse_args()
    if args.scene:
        scene(args.scene, args.scene_start, args.scene_stride)
        return 0
    base = scenarios.get("rolling")
    flight = base.trajectories["drone"]
    starts = np.linspace(4.0, 16.0, args.starts)
    head = ("motion", "mode", "shutter", "n", "RMSE mm", "med mm", "max mm", "w3 worst", "sigma mm")
    print("{:>7} {:>7} {:>8} {:>4} {:>8} {:>7} {:>7} {:>8} {:>8}".format(*head))
    bars = []
    for name in args.motions.split(","):
        w_body, v_world = MOTIONS[name]
        for mode in args.modes.split(","):
            rmse = {}
            for shutter in ("rolling", "rolling-global"):
                sc = scenarios.get(shutter)
                rows = []
                for t0 in starts:
                    p, q = flight.pose(np.array([t0]))
                    motion = ConstantMotion(p[0], Rotation.from_quat(q[0]), w_body, v_world)
                    rows += run(sc, motion, args.frames, mode != "single", mode == "oracle")
                if not rows:
                    print(f"{name:>7} {mode:>7} {shutter:>8}    0")
                    continue
                e = np.array([r[0] for r in rows]) * 1e3
                s = np.array([np.sqrt(np.diag(r[1])) for r in rows]) * 1e3
                norm = np.linalg.norm(e, axis=1)
                w3 = float(np.mean(np.abs(e) <= 3 * s, axis=0).min())
                rmse[shutter] = float(np.sqrt(np.mean(norm**2)))
                print(
                    f"{name:>7} {mode:>7} {shutter[:8]:>8} {len(e):>4} {rmse[shutter]:>8.2f} {np.median(norm):>7.2f}"
                    f" {norm.max():>7.2f} {w3:>8.3f} {np.median(np.linalg.norm(s, axis=1)):>8.2f}"
                )
            if len(rmse) == 2 and mode != "oracle":
                bars.append((f"{name}.{mode}.rmse_ratio", rmse["rolling"] / max(rmse["rolling-global"], 1e-9)))
    for bar, ratio in bars:
        print(f"BAR {bar} {ratio:.3g} x 2 {'pass' if ratio <= 2.0 else 'fail'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
