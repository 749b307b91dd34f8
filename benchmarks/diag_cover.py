"""Where a scene's ``cover`` (bench_hard: availability while a tag is fully in view) goes, offline.

The scene's frames in capture order through the node's detector (the autopilot's rate and velocity as the
node holds them: bench_hard's ``node_rates`` and ``node_velocities``); every frame the benchmark's ideal node
counts (a tag fully in view, ``SimWorld.visible_frames``: every corner where the camera images it, a
rolling shutter's at its own row's instant, at least the detector's ``BORDER_MARGIN_PX`` inside the image;
see bench_hard) from which the detector gives the drone no observation, with the detector's reason, and
every stretch of frames in view. Then the cover an ideal node
would have if it published every such frame, and the detector's frames only, each ``latency`` after its
capture: what the frames dropped and the capture-to-arrival delay at each re-acquisition cost, before any
live run's own misses (frames skipped behind real time). Its bar: the cover the detector's frames allow at
the node's delay (``BAR_LATENCY_S``) against bench_hard's cover bar: a live node cannot do better.

    python benchmarks/diag_cover.py [--scenario rolling] [--duration 20]
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_hard as bh

from atlas_onboard.sim import report, runner, scenarios
from atlas_onboard.sim.runner import WARMUP_S
from atlas_onboard.sim.world import SimWorld

LATENCIES_S = (0.0, 0.02, 0.04, 0.06)
BAR_LATENCY_S = 0.02  # a node's capture-to-arrival delay on an idle machine
COVER_BAR_PCT = 99.0  # bench_hard's cover bar


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="rolling")
    ap.add_argument("--duration", type=float, default=20.0)
    args = ap.parse_args()
    scenario = scenarios.get(args.scenario)
    world = scenario.world()
    sim_world = SimWorld(scenario)
    directory = runner._rendered_frames(scenario, 0, args.duration, lambda _m: None)
    rates = bh.node_rates(sim_world, args.duration, 0)
    velocities = bh.node_velocities(sim_world, args.duration, 0)
    ideal = sim_world.visible_frames(bh.ENTITY, args.duration)
    published = []
    for _sensor, det, frames, fps, n in bh.drone_cameras(sim_world, world, directory, args.duration):
        in_view = set(np.round(ideal * fps).astype(int))
        index = sorted(in_view)
        starts = [index[0]] + [b for a, b in itertools.pairwise(index) if b - a > 1]
        ends = [a for a, b in itertools.pairwise(index) if b - a > 1] + [index[-1]]
        print("frames in view (first-last):", ", ".join(f"{a}-{b}" for a, b in zip(starts, ends, strict=True)))
        for j in range(n):
            t_us = round(j / fps * 1e6)
            mds = det.detect(np.asarray(frames[j]), t_us, None, rates(t_us), velocities(t_us))
            if mds:
                published.append(j / fps)
            if j in in_view and not mds:
                where = "first of a stretch" if j in starts else "last of a stretch" if j in ends else "inside"
                print(f"frame {j} ({j / fps:.3f} s, {where}): found {det.report.found}, dropped {det.report.dropped}")
    pub = np.array(published)
    print(f"{'latency ms':>10} {'ideal node cover %':>19} {'detector frames cover %':>24}")
    for lat in LATENCIES_S:
        ideal_cover = report.coverage(ideal + lat, ideal, WARMUP_S, args.duration) * 100
        det_cover = report.coverage(pub + lat, ideal, WARMUP_S, args.duration) * 100
        print(f"{lat * 1e3:>10.0f} {ideal_cover:>19.2f} {det_cover:>24.2f}")
    at = report.coverage(pub + BAR_LATENCY_S, ideal, WARMUP_S, args.duration) * 100
    ok = "pass" if at >= COVER_BAR_PCT else "fail"
    print(f"BAR detector_frames_cover_{BAR_LATENCY_S * 1e3:.0f}ms {at:.2f} % {COVER_BAR_PCT:g} {ok}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
