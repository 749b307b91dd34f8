"""Live map refinement (issue 21): one world marker 10 cm from where it is, two drones' cameras.

The ``map`` scenario's two cameras are rendered once (a recording each, from ``--start`` for
``--duration``); every run then processes the same frames in capture order, in this process, with the
real detector, listener, graph and :class:`~atlas_onboard.node.refine.LiveRefinement` (no transport, no
clocks: load-free and repeatable). Runs:

- ``truth, joint`` (the anchor): the true world file, the default detector (joint solves), no refinement;
- ``moved, joint``: the world file with marker ``--marker`` 10 cm off, the default (refinement off);
- ``moved, refine``: the same, refinement on (defaults: one image a camera every 0.5 s marker by marker);
- ``truth, refine``: the true world file with refinement on: a good map must not move, and its pose
  error is what refinement's per-marker images cost (the anchor of the ``after`` state).

Printed: the refined marker's error against time; each run's position error of both drones (mean,
median, p95, RMSE) per state: ``before`` (until the marker has reached its refined pose) and ``after``,
with ratios to the anchors in the same frames; ``BAR`` lines.

    python benchmarks/bench_refine.py [--start 44] [--duration 16] [--marker 2] [--out DIR]
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import yaml

from atlas_onboard.config import RefineConfig, load_world
from atlas_onboard.detector.workers import CameraDetectorSpec
from atlas_onboard.listener import Listener
from atlas_onboard.node.refine import LiveRefinement
from atlas_onboard.node.setup import make_graph
from atlas_onboard.recording.format import read_frames, read_info
from atlas_onboard.sim import recordings, scenarios
from atlas_onboard.sim.world import SimWorld

SCENARIO = "map"
SENSORS = (1, 2)
MOVE_M = (0.1, 0.0, 0.0)
BAR_MARKER_MM = 5.0  # the refined marker within this of the truth
BAR_TIME_S = 10.0  # ...this long after the first image
BAR_AFTER_RATIO = 1.2  # pose RMSE after refinement vs the true map, same detector and frames
BAR_COST_RATIO = 1.5  # refinement's per-marker detection vs the default joint solves, true map, median error


def _frames(recs: dict[int, Path]) -> list[tuple[int, int, np.ndarray]]:
    """(capture us, sensor id, image) of every camera's frames, in capture order."""
    out = [(f.capture_time_us, sid, f.gray) for sid, path in recs.items() for f in read_frames(path)]
    return sorted(out, key=lambda x: (x[0], x[1]))


def run(world_file: Path, recs: dict[int, Path], refine: bool, marker: int, truth_world) -> dict:
    """Process every frame; returns per-frame errors (m) by entity, the marker's error track and updates."""
    world = load_world(world_file)
    graph = make_graph(world)
    listener = Listener(world, graph)
    # As the node's cameras run (with live refinement's per-marker images when refining).
    detectors = {
        sid: CameraDetectorSpec(world.sensors[sid], world, read_info(p).calibration, 2.0,
                                RefineConfig() if refine else None).build()
        for sid, p in recs.items()
    }  # fmt: skip
    refinement = LiveRefinement(world, RefineConfig()) if refine else None
    sim = SimWorld(scenarios.get(SCENARIO), truth_world)
    true_marker = truth_world.markers[marker].T_entity_marker.translation
    errors: list[tuple[float, str, float]] = []
    track: list[tuple[float, float]] = []
    reached_s = math.nan
    t0 = None
    for stamp_us, sid, gray in FRAMES[id(recs)]:
        t_s = stamp_us / 1e6
        t0 = t_s if t0 is None else t0
        now_ns = stamp_us * 1000
        mds = detectors[sid].detect(gray, stamp_us)
        mds = [replace(md, frame_remaining=len(mds) - 1 - i) for i, md in enumerate(mds)]
        reasons = listener.accept_many([(md, now_ns) for md in mds])
        if refinement is not None:
            refinement.add([md for md, r in zip(mds, reasons, strict=True) if r is None], now_ns)
            for u in refinement.step(now_ns, listener):
                if u.marker_id == marker and u.reached and math.isnan(reached_s):
                    reached_s = t_s - t0
        result = graph.evaluate(now_ns)
        listener.set_estimates(result.poses)
        entity = world.sensors[sid].entity
        pose = result.poses.get(entity)
        if pose is not None:
            truth = sim.truth(t_s, {entity})[entity]
            errors.append((t_s - t0, entity, float(np.linalg.norm(np.asarray(pose.p_world_m) - truth.translation))))
        p_marker = listener.marker_pose(marker)[:3, 3]
        track.append((t_s - t0, float(np.linalg.norm(p_marker - true_marker))))
    moved = sorted(refinement.markers_refined) if refinement is not None else []
    notes = ""
    if refinement is not None:
        est = refinement.refiner.estimate(marker)
        why = refinement.refiner.verdict(est) if est is not None else "no evidence"
        notes = f"marker {marker}: {why or 'refined'}; " + " ".join(
            f"{k}={v}" for k, v in refinement.counters().items()
        )
    return {"errors": errors, "track": track, "reached_s": reached_s, "moved": moved, "notes": notes}


FRAMES: dict[int, list] = {}


def _stats(e: list[float]) -> str:
    if not e:
        return "    n/a"
    a = np.array(e) * 1000
    return (
        f"n {len(a):4d}  mean {a.mean():6.2f}  median {np.median(a):6.2f}  p95 {np.percentile(a, 95):6.2f}"
        f"  rmse {math.sqrt(np.mean(a**2)):6.2f} mm"
    )


def _rmse(e: list[float]) -> float:
    return math.sqrt(np.mean(np.square(e))) if e else math.nan


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--start", type=float, default=44.0, help="scenario time of the first frame, s")
    p.add_argument("--duration", type=float, default=16.0, help="seconds of flight")
    p.add_argument("--marker", type=int, default=2, help="the world marker moved 10 cm in the world file")
    p.add_argument("--out", type=Path, help="keep the recordings here (default: a temporary directory)")
    args = p.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="bench-refine-") as tmp:
        out = args.out or Path(tmp)
        out.mkdir(parents=True, exist_ok=True)
        doc = recordings.world_doc(scenarios.get(SCENARIO))
        recs = recordings.record(SCENARIO, doc, SENSORS, args.duration, 1, out, detect=False, start_s=args.start)
        FRAMES[id(recs)] = _frames(recs)
        truth_file, moved_file = out / "truth.yaml", out / "moved.yaml"
        truth_file.write_text(yaml.safe_dump(doc, sort_keys=False))
        moved_file.write_text(yaml.safe_dump(recordings.edit_marker(doc, args.marker, move_m=MOVE_M), sort_keys=False))
        truth_world = load_world(truth_file)
        runs = {
            "truth, joint": run(truth_file, recs, False, args.marker, truth_world),
            "moved, joint": run(moved_file, recs, False, args.marker, truth_world),
            "moved, refine": run(moved_file, recs, True, args.marker, truth_world),
            "truth, refine": run(truth_file, recs, True, args.marker, truth_world),
        }
    ref = runs["moved, refine"]
    print(f"bench_refine: scenario {SCENARIO}, {args.duration:g} s from {args.start:g} s, cameras {SENSORS},")
    print(f"  marker {args.marker} moved {MOVE_M} m in the world file; {len(FRAMES[id(recs)])} frames")
    print("refined marker's error against time (moved, refine):")
    for t_s in range(int(args.duration) + 1):
        at = [e for t, e in ref["track"] if t <= t_s]
        if at:
            print(f"  t {t_s:3d} s  error {at[-1] * 1000:7.2f} mm")
    reached = ref["reached_s"]
    final_mm = ref["track"][-1][1] * 1000
    split = reached if math.isfinite(reached) else math.inf
    print(f"marker reached its refined pose at {reached:.1f} s; final error {final_mm:.2f} mm")
    print("position error of both drones per state (before / after the marker reached its refined pose):")
    table = {}
    for name, r in runs.items():
        before = [e for t, _, e in r["errors"] if t < split]
        after = [e for t, _, e in r["errors"] if t >= split]
        table[name] = (before, after)
        print(f"  {name:14s} before {_stats(before)}")
        print(f"  {'':14s} after  {_stats(after)}   markers moved: {r['moved']}")
        if r["notes"]:
            print(f"  {'':14s} {r['notes']}")
    print("ratios (RMSE) in the same frames:")
    for state, k in (("before", 0), ("after", 1)):
        anchor = _rmse(table["truth, joint"][k])
        for name in ("moved, joint", "moved, refine", "truth, refine"):
            print(f"  {state:6s} {name:14s} / truth, joint: {_rmse(table[name][k]) / anchor:6.2f}")
    after_ratio = _rmse(table["moved, refine"][1]) / _rmse(table["truth, refine"][1])
    all_refine, all_joint = (
        [*table["truth, refine"][0], *table["truth, refine"][1]],
        [*table["truth, joint"][0], *table["truth, joint"][1]],
    )
    cost_rmse = _rmse(all_refine) / _rmse(all_joint)
    cost_ratio = float(np.median(all_refine) / np.median(all_joint))
    print(f"refinement's cost on the true map (per-marker detection vs joint), whole run: RMSE x{cost_rmse:.2f},"
          f" median x{cost_ratio:.2f}")  # fmt: skip
    good_moved = len(runs["truth, refine"]["moved"])
    bars = [
        ("refined_marker_error", final_mm, "mm", BAR_MARKER_MM, final_mm <= BAR_MARKER_MM),
        ("refined_marker_time", reached, "s", BAR_TIME_S, reached <= BAR_TIME_S),
        ("pose_rmse_after_vs_true_map", after_ratio, "ratio", BAR_AFTER_RATIO, after_ratio <= BAR_AFTER_RATIO),
        ("refine_cost_vs_joint_true_map", cost_ratio, "ratio", BAR_COST_RATIO, cost_ratio <= BAR_COST_RATIO),
        ("good_map_markers_moved", good_moved, "markers", 0, good_moved == 0),
    ]
    for name, value, unit, limit, ok in bars:
        print(f"BAR {name} {value:.3g} {unit} {limit:g} {'pass' if ok else 'fail'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
