"""Every simulated output of the offline scenarios, this tree against a base git revision, hashed bit for bit.

For each scenario, every camera's frames (rendered from ground truth, as the simulator's cameras render them)
go through the real detector, and each frame's observations go to every drone's listener and graph at their
capture time (:mod:`atlas_onboard.sim.offline`'s estimator, no processes or clocks). Hashed, in order: every
MarkerData field, the detector's counters, each listener's verdict on each observation, every pose of every
graph evaluation (position, quaternion, level, order, count, sigma, stamp, frame, 6x6 covariance, ...), the
6x6 the autopilot would receive, and the listeners' and graphs' counters. ``--variants`` runs each scenario
again with the edge filters that the defaults leave unused (``ema``: eq. 3 with alpha 0.5; ``kalman``: the
per-edge blend, records without their 6x6). Each tree runs in a child process of its own.

    python benchmarks/offline_digest.py [--base main] [--frames 45] [--scenarios relay,swarm] [--variants]

Exit status 0 when every digest is identical, 1 otherwise.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from bench_per_marker import export_revision

ROOT = Path(__file__).resolve().parents[1]
SCENARIOS = ("paper-test1", "paper-test2", "relay", "relay-follow", "paths", "swarm", "gaps", "hard", "rolling")
VARIANTS = ("ema", "kalman")


def child(tree: Path, scenario_name: str, frames: int, variant: str) -> None:
    """Print ``<records> <sha256>`` of one scenario's outputs computed by the package in ``tree``."""
    sys.path.insert(0, str(tree))
    import numpy as np

    import atlas_onboard

    assert Path(atlas_onboard.__file__).is_relative_to(tree), atlas_onboard.__file__
    from atlas_onboard.detector.pipeline import Detector
    from atlas_onboard.listener import Listener
    from atlas_onboard.sim import offline, scenarios
    from atlas_onboard.sim.camera import FrameRenderer, camera_seed
    from atlas_onboard.sim.world import SimWorld

    try:
        from atlas_onboard.node.setup import make_graph
    except ImportError:  # a base from before the node package: the listener made the graph
        from atlas_onboard.listener import make_graph  # type: ignore[attr-defined,no-redef]

    h = hashlib.sha256()
    count = 0

    def feed(x: Any) -> None:
        if isinstance(x, np.ndarray):
            h.update(f"{x.dtype}{x.shape}".encode() + np.ascontiguousarray(x).tobytes())
        elif isinstance(x, tuple | list):
            h.update(b"(")
            for y in x:
                feed(y)
            h.update(b")")
        elif dataclasses.is_dataclass(x) and not isinstance(x, type):
            feed([getattr(x, f.name) for f in dataclasses.fields(x)])
        else:
            h.update(repr(x).encode() + b",")  # repr of a float is exact

    def put(*items: Any) -> None:
        nonlocal count
        count += 1
        feed(items)

    scenario = scenarios.get(scenario_name)
    world = scenario.world()
    sim = SimWorld(scenario, world)
    if variant == "ema":
        world = dataclasses.replace(
            world, fusion=dataclasses.replace(world.fusion, ema_alpha=0.5, age_sigma_m_per_s=0.0)
        )
    elif variant == "kalman":
        world = dataclasses.replace(world, fusion=dataclasses.replace(world.fusion, age_sigma_m_per_s=0.3))
    cams = [
        (sensor, FrameRenderer(scenario, world, sensor, camera_seed(0, sid)),
         Detector(sensor, world, intr.calibration(), decimate=2.0))
        for sid, (sensor, intr) in sorted(sim.cameras.items())
    ]  # fmt: skip
    nodes = {}
    for drone in scenario.drones:
        graph = make_graph(world, drone)
        nodes[drone] = (graph, Listener(world, graph))
    fps = min(r.fps for _, r, _ in cams)
    first = round(1.0 * fps)
    for j in range(first, first + frames):
        t = j / fps
        now_ns = round(t * 1e9)
        mds = []
        for sensor, renderer, det in cams:
            if scenario.occluded(sensor.entity, sensor.name, t):
                continue
            for md in det.detect(renderer(round(t * renderer.fps)), round(t * 1e6)):
                if variant:
                    md = dataclasses.replace(md, covariance=())
                mds.append(md)
                put("md", md)
            put("detector counters", sorted(det.counters.items()))
        for drone, (graph, listener) in nodes.items():
            verdicts = listener.accept_many([(md, now_ns) for md in mds])
            put("verdicts", drone, [None if v is None else v.value for v in verdicts])
            result = graph.evaluate(now_ns)
            listener.set_estimates(result.poses)
            for name, pose in sorted(result.poses.items()):
                put("pose", drone, name, pose)
                if name == drone and pose.covariance is not None:
                    put("published", offline.published_covariance(pose.covariance))
            put("counters", drone, sorted(listener.rejected.snapshot().items()),
                sorted(listener.counters.snapshot().items()), listener.accepted, graph.gated_total,
                graph.too_fast_total)  # fmt: skip
    print(count, h.hexdigest())


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="main", help="git revision to compare against (default main)")
    ap.add_argument("--frames", type=int, default=45, help="frames per scenario from 1 s (default 45)")
    ap.add_argument("--scenarios", default=",".join(SCENARIOS), help="comma-separated (default: all offline ones)")
    ap.add_argument("--variants", action="store_true", help="also each scenario with the ema and kalman filters")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)  # tree, scenario, frames, variant
    args = ap.parse_args()
    if args.child:
        child(Path(args.child[0]), args.child[1], int(args.child[2]), args.child[3])
        return 0
    runs = [(s, "") for s in args.scenarios.split(",")]
    if args.variants:
        runs += [(s, v) for s in args.scenarios.split(",") for v in VARIANTS]
    identical = 0
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "base"
        try:
            export_revision(args.base, base)
        except (OSError, subprocess.CalledProcessError) as exc:
            print(f"offline_digest: cannot export {args.base!r} with git archive: {exc}", file=sys.stderr)
            return 2
        print(f"{'scenario':14} {'variant':8} {'records':>8}  {'base ' + args.base:18} {'this tree':18} same")
        for scenario, variant in runs:
            got = []
            for tree in (base, ROOT):
                cmd = [sys.executable, __file__, "--child", str(tree), scenario, str(args.frames), variant]
                out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.split()
                got.append(out)
            same = got[0] == got[1]
            identical += same
            print(f"{scenario:14} {variant or '-':8} {got[1][0]:>8}  {got[0][1][:16]:18} {got[1][1][:16]:18} "
                  f"{'yes' if same else 'NO'}")  # fmt: skip
    ok = identical == len(runs)
    print(f"BAR offline_outputs_identical {identical} runs {len(runs)} {'pass' if ok else 'fail'}")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
