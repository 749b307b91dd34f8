"""The detector's CPU per marker in view, this tree against a base git revision, in one run.

The demo's scene with ten floor tags in view (a drone 1 m over 16 cm floor tags, 640x480, lens distortion;
``write_demo(n_tags=10)``) with 1, 2, 5 and 10 tags in the world file (the others in view are not looked
for): ``Detector.detect`` as the node runs it (decimate 2 with tracking), its thread CPU per frame, and the
same minus its marker search (``find``): the work after the search (corner refit, poses and covariances,
the joint solve, the world check). Each measurement is a child process pinned to one core (``taskset -c
0``, OpenCV on one thread) running one tree's code on the same frames; the trees' children alternate, so a
change of the machine's load touches both alike. The per-marker cost is the least-squares slope of the
mean CPU per frame over the mean number of markers found per frame (1 to 10 tags).

    python benchmarks/bench_per_marker.py [--base main] [--repeats 2] [--seconds 4] [--core 0]

The base is exported with ``git archive`` into a temporary directory (nothing in the work tree changes).
Bars: this tree's CPU per additional marker in view after the search at most ``BAR_MS`` (640x480, one
core), and at most ``BAR_RATIO`` of the base's (a fifth).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TAGS = (1, 2, 5, 10)
BAR_MS = 0.8  # CPU ms per additional marker in view after the search, 640x480, one core
BAR_RATIO = 0.2  # of the base's


def export_revision(revision: str, dest: Path) -> None:
    """Write ``revision``'s files into the new directory ``dest`` (``git archive``; the work tree is not
    touched). Raises OSError or CalledProcessError when git cannot export it."""
    dest.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(dest)], input=archive.stdout, check=True)


def child(tree: Path, scene: Path, n_tags: int) -> None:
    """Print [detect ms, find ms, markers found] per frame of the scene's frames with the first ``n_tags``
    tags configured."""
    sys.path.insert(0, str(tree))
    import cv2
    import yaml

    from atlas_onboard.config import parse_world
    from atlas_onboard.detector.calibration import load as load_calibration
    from atlas_onboard.detector.pipeline import Detector

    cv2.setNumThreads(1)
    doc = yaml.safe_load((scene / "world.yaml").read_text())
    doc["entities"]["world"]["markers"] = doc["entities"]["world"]["markers"][:n_tags]
    world = parse_world(doc)
    cal = load_calibration(scene / "calibration.yaml")
    frames = [cv2.imread(str(f), cv2.IMREAD_GRAYSCALE) for f in sorted((scene / "frames").iterdir())]
    det = Detector(world.sensors[next(iter(world.sensors))], world, cal, decimate=2.0)
    spent = [0.0]
    find = det.find

    def timed_find(*args, **kwargs):  # type: ignore[no-untyped-def]
        t0 = time.thread_time()
        try:
            return find(*args, **kwargs)
        finally:
            spent[0] += time.thread_time() - t0

    det.find = timed_find  # type: ignore[method-assign]
    for img in frames[:5]:  # warm up (imports, caches)
        det.detect(img, 0)
    out = []
    for k, img in enumerate(frames):
        spent[0] = 0.0
        t0 = time.thread_time()
        det.detect(img, 33_333 * k)
        out.append(((time.thread_time() - t0) * 1e3, spent[0] * 1e3, len(det.report.found)))
    print(json.dumps(out))


def _stats(ms: list[float]) -> str:
    return (
        f"{statistics.mean(ms):>6.2f} {statistics.median(ms):>6.2f} {float(np.percentile(ms, 95)):>6.2f} {len(ms):>5}"
    )


def _slope(x: list[float], y: list[float]) -> float:
    """Least-squares slope of y over x."""
    return float(np.polyfit(np.array(x), np.array(y), 1)[0])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", default="main", help="git revision to compare against (default main)")
    ap.add_argument("--repeats", type=int, default=2, help="children per tree and tag count (default 2)")
    ap.add_argument("--seconds", type=float, default=4.0, help="demo camera time, s (default 4: 120 frames)")
    ap.add_argument("--core", default="0", help="the core the children are pinned to (default 0)")
    ap.add_argument("--child", nargs=3, help=argparse.SUPPRESS)  # tree, scene, tags
    args = ap.parse_args()
    if args.child:
        child(Path(args.child[0]), Path(args.child[1]), int(args.child[2]))
        return 0
    with tempfile.TemporaryDirectory() as tmp_s:
        tmp = Path(tmp_s)
        base = tmp / "base"
        try:
            export_revision(args.base, base)
        except (OSError, subprocess.CalledProcessError) as exc:
            print(f"bench_per_marker: cannot export {args.base!r} with git archive: {exc}", file=sys.stderr)
            return 2
        sys.path.insert(0, str(ROOT))
        from atlas_onboard.sim.demo import write_demo

        scene = tmp / "scene"
        write_demo(scene, seconds=args.seconds, n_tags=max(TAGS))
        trees = {f"base {args.base}": base, "this tree": ROOT}
        ms: dict[tuple[str, int, str], list[float]] = {}
        found: dict[tuple[str, int], list[int]] = {}
        for r in range(args.repeats):
            for n in TAGS:
                order = list(trees.items()) if r % 2 == 0 else list(trees.items())[::-1]
                for name, tree in order:
                    cmd = ["taskset", "-c", args.core, sys.executable, __file__, "--child", str(tree), str(scene)]
                    env = {**os.environ, "OMP_NUM_THREADS": "1"}
                    run = subprocess.run([*cmd, str(n)], capture_output=True, text=True, check=True, env=env)
                    for detect_ms, find_ms, n_found in json.loads(run.stdout.strip().splitlines()[-1]):
                        ms.setdefault((name, n, "detect"), []).append(detect_ms)
                        ms.setdefault((name, n, "after search"), []).append(detect_ms - find_ms)
                        found.setdefault((name, n), []).append(n_found)
    print("Detector.detect on the demo's 10-tag scene (640x480), thread CPU ms per frame, one core", end=" ")
    print(f"(taskset -c {args.core}); found: markers found per frame")
    print(f"{'tree':16} {'tags':>4} {'found':>5} {'part':13} {'mean':>6} {'median':>6} {'p95':>6} {'n':>5}")
    for n in TAGS:
        for name in trees:
            for part in ("detect", "after search"):
                seen = statistics.mean(found[(name, n)])
                print(f"{name:16} {n:>4} {seen:>5.2f} {part:13} {_stats(ms[(name, n, part)])}")
    print("per additional marker in view: least-squares slope of the means over the markers found, ms CPU")
    slopes: dict[tuple[str, str], float] = {}
    for part in ("detect", "after search"):
        for name in trees:
            x = [statistics.mean(found[(name, n)]) for n in TAGS]
            slopes[(name, part)] = _slope(x, [statistics.mean(ms[(name, n, part)]) for n in TAGS])
        a, b = (slopes[(name, part)] for name in trees)
        print(f"  {part:13} base {a:.3f} -> this tree {b:.3f} ms/marker (ratio {b / a:.2f})")
    base_name = next(iter(trees))
    ratio = slopes[("this tree", "after search")] / slopes[(base_name, "after search")]
    print(f"BAR per_marker_ratio_to_base {ratio:.2f} ratio {BAR_RATIO} {'pass' if ratio <= BAR_RATIO else 'fail'}")
    value = slopes[("this tree", "after search")]
    print(f"BAR per_marker_ms {value:.2f} ms {BAR_MS} {'pass' if value <= BAR_MS else 'fail'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
