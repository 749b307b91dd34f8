"""What `run --record` costs the pose output: latency and rate of one node with and without recording.

A rendered flight of the simulator's ``map`` scenario (640x480 at 15 fps, the camera seeing three to
seven markers) is replayed to a node process as its camera (``replay: realtime``: paced on the
recorded stamps, frames the detector has no time for dropped, like a live camera); a simulated
autopilot receives its VISION_POSITION_ESTIMATE. Latency is from a frame's capture stamp (its
recorded stamp shifted to the replay) to the pose's arrival at the autopilot: detection, the graph
and the link. The anchor is the same node without ``--record``, in the same run: the two take turns
(``--blocks`` each), so that a drift of the machine's speed falls on both alike.

    python benchmarks/bench_record.py [--seconds 10] [--blocks 2] [--jpg] [--keep DIR]

Bars: with recording, the median latency within 10 % of the anchor's and at least 95 % of its poses.
"""

from __future__ import annotations

import argparse
import copy
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from atlas_onboard.recording.format import read_frames
from atlas_onboard.sim import recordings, scenarios
from atlas_onboard.sim.autopilot import SimAutopilot

SCENARIO, SENSOR, ENTITY, START_S = "map", 1, "mapper1", 8.0


def run_node(doc: dict, rec: Path, work: Path, record_dir: Path | None, image_format: str) -> dict:
    """One replay of the recording; latencies (ms), poses, frames and the recorder's counters."""
    ap = SimAutopilot(system_id=1).start()
    d = copy.deepcopy(doc)
    for s in d["entities"][ENTITY]["sensors"]:
        if s["id"] == SENSOR:
            s["camera"] = {"source": str(rec), "replay": "realtime", "fps": 15}
    node: dict = {"system_id": 1, "autopilot": {"url": f"udpout:127.0.0.1:{ap.port}"}}
    if record_dir is not None:
        node["record"] = {"dir": str(record_dir), "image_format": image_format}
    d["nodes"] = {ENTITY: node}
    world = work / "world.yaml"
    world.write_text(yaml.safe_dump(d, sort_keys=False))
    log = work / "node.log"
    with open(log, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "atlas_onboard", "run", "--config", str(world)],
                                stdout=out, stderr=subprocess.STDOUT)  # fmt: skip
        try:
            deadline = time.monotonic() + 600
            while "end of" not in log.read_text(errors="replace") and time.monotonic() < deadline:
                if proc.poll() is not None:
                    raise SystemExit(f"the node stopped:\n{log.read_text()[-2000:]}")
                time.sleep(0.1)
            time.sleep(0.5)
        finally:
            proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
    ap.stop()
    text = log.read_text(errors="replace")
    final = next(x for x in reversed(text.splitlines()) if " final " in x)
    counters = {k: int(v) for k, v in (p.split("=", 1) for p in final.split(" final ", 1)[1].split())}
    got = [m for m in ap.snapshot() if m.kind == "VISION_POSITION_ESTIMATE"]
    latency_ms = np.array([(m.arrival_s - m.usec / 1e6) * 1e3 for m in got])
    return {"latency_ms": latency_ms, "poses": len(got), "counters": counters}


def stats(x: np.ndarray) -> str:
    return f"mean {x.mean():7.1f}  median {np.median(x):7.1f}  p95 {np.percentile(x, 95):7.1f}"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="length of the flight replayed (s)")
    ap.add_argument("--blocks", type=int, default=2, help="replays of each state, alternating")
    ap.add_argument("--jpg", action="store_true", help="record JPEG frames instead of PNG")
    ap.add_argument("--keep", type=Path, help="keep (and reuse) the rendered flight in this directory")
    args = ap.parse_args()
    fmt = "jpg" if args.jpg else "png"
    base = Path(tempfile.mkdtemp(prefix="atlas-bench-record-"))
    flight_dir = args.keep or base / "flight"
    doc = recordings.world_doc(scenarios.get(SCENARIO))
    t0 = time.monotonic()
    rec = recordings.record(SCENARIO, doc, (SENSOR,), args.seconds, 1, flight_dir, detect=False, start_s=START_S)
    rec_path = rec[SENSOR]
    n_frames = len(list(read_frames(rec_path, with_images=False)))
    print(f"flight: {n_frames} frames of 640x480 at 15 fps ({time.monotonic() - t0:.0f} s to render or load)")
    anchor, recording = "anchor (no record)", f"--record ({fmt})"
    results: dict[str, list[dict]] = {anchor: [], recording: []}
    for b in range(args.blocks):
        for name, runs in results.items():
            work = base / f"{'rec' if name == recording else 'plain'}-{b}"
            work.mkdir()
            record_dir = work / "recordings" if name == recording else None
            runs.append(run_node(doc, rec_path, work, record_dir, fmt))
            r = runs[-1]
            print(f"block {b} {name:<20} poses {r['poses']:>4} frames {r['counters'].get('camera_cam_frames', 0):>4}"
                  f"  latency median {np.median(r['latency_ms']):6.1f} ms", flush=True)  # fmt: skip
    print(f"{'state':<20} {'poses':>6} {'frames':>7}  latency capture -> autopilot (ms)")
    summary = {}
    for name, runs in results.items():
        lat = np.concatenate([r["latency_ms"] for r in runs])
        poses = sum(r["poses"] for r in runs)
        frames = sum(r["counters"].get("camera_cam_frames", 0) for r in runs)
        summary[name] = (lat, poses)
        print(f"{name:<20} {poses:>6} {frames:>7}  {stats(lat)}")
        written = sum(r["counters"].get("camera_cam_record_written", 0) for r in runs)
        if name == recording:
            behind = sum(r["counters"].get("camera_cam_record_dropped_queue_full", 0) for r in runs)
            print(f"{'':<20} recorded {written} of {frames} frames detected ({behind} dropped: writer behind)")
    (lat_a, poses_a), (lat_r, poses_r) = summary.values()
    ratio = float(np.median(lat_r) / np.median(lat_a))
    rate = poses_r / poses_a if poses_a else float("nan")
    print(f"median latency with/without recording: {ratio:.3f}; poses with/without: {rate:.3f}")
    print(f"BAR record_latency_median_ratio {ratio:.3f} x 1.10 {'pass' if ratio <= 1.10 else 'fail'}")
    print(f"BAR record_poses_ratio {rate:.3f} x 0.95 {'pass' if rate >= 0.95 else 'fail'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
