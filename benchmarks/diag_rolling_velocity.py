"""The rolling scene offline, with and without the autopilot's velocity, beside its global-shutter twin.

The run's frames of ``rolling`` (25 ms readout) and ``rolling-global`` in capture order through the node's
detector, given the autopilot's gyro rate as the node holds it (bench_hard's ``node_rates``) and, on the
rolling camera, once without and once with the autopilot's EKF velocity as the node holds it
(``node_velocities``: the simulated autopilot's LOCAL_POSITION_NED). Every observation's camera position in
the world (eq. 1 through its marker) against the truth at its stamp: mean, median, p95, max, RMSE beside the
twin's (the anchor), and the worst axis's share within 3 sigma and the share within 3 sigma on all three axes
at once, from the observation's own covariance. Offline: the machine's load does not enter.

    python benchmarks/diag_rolling_velocity.py [--duration 20]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_hard as bh
from diag_rolling import score

from atlas_onboard.sim import runner, scenarios
from atlas_onboard.sim.runner import WARMUP_S
from atlas_onboard.sim.world import SimWorld

RUNS = (("rolling-global", False), ("rolling", False), ("rolling", True))


def errors(scenario_name: str, with_velocity: bool, duration_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Per observation from WARMUP_S: the position error (N, 3) and the position sigmas (N, 3), mm."""
    scenario = scenarios.get(scenario_name)
    world = scenario.world()
    sim_world = SimWorld(scenario)
    directory = runner._rendered_frames(scenario, 0, duration_s, lambda _m: None)
    rates = bh.node_rates(sim_world, duration_s, 0)
    velocities = bh.node_velocities(sim_world, duration_s, 0)
    rows = []
    for sensor, det, frames, fps, n in bh.drone_cameras(sim_world, world, directory, duration_s):
        for j in range(n):
            t = j / fps
            t_us = round(t * 1e6)
            mds = det.detect(
                np.asarray(frames[j]), t_us, None, rates(t_us), velocities(t_us) if with_velocity else None
            )
            if t >= WARMUP_S:
                rows += score(world, sim_world, sensor, t, mds)
    e = np.array([r[0] for r in rows]).reshape(-1, 3) * 1e3
    s = np.array([np.sqrt(np.diag(r[1])) for r in rows]).reshape(-1, 3) * 1e3
    return e, s


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    args = ap.parse_args()
    print(f"{'run':<26} {'n':>4} {'mean':>6} {'median':>7} {'p95':>6} {'max':>6} {'RMSE':>6} {'/twin':>6}"
          f" {'3s min%':>8} {'3s all%':>8}")  # fmt: skip
    twin = float("nan")
    bars = []
    for name, with_velocity in RUNS:
        e, s = errors(name, with_velocity, args.duration)
        norm = np.linalg.norm(e, axis=1)
        inside = np.abs(e) <= 3.0 * s
        rmse = float(np.sqrt(np.mean(norm**2)))
        twin = rmse if name == "rolling-global" else twin
        label = f"{name}{' +velocity' if with_velocity else ''}"
        w3, w3all = float(inside.mean(axis=0).min()) * 100, float(inside.all(axis=1).mean()) * 100
        print(
            f"{label:<26} {len(e):>4} {norm.mean():>6.2f} {np.median(norm):>7.2f} {np.percentile(norm, 95):>6.2f}"
            f" {norm.max():>6.1f} {rmse:>6.2f} {rmse / twin:>6.2f} {w3:>8.1f} {w3all:>8.1f}"
        )
        if name == "rolling":
            tag = "velocity" if with_velocity else "rate_only"
            bars += [(f"{tag}.rmse_ratio", rmse / twin, "x", 2.0, "<="), (f"{tag}.within3_min", w3, "%", 99.0, ">=")]
    for bar, value, unit, limit, op in bars:
        ok = value <= limit if op == "<=" else value >= limit
        print(f"BAR {bar} {value:.4g} {unit} {limit:g} {'pass' if ok else 'fail'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
